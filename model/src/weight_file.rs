//! A weight file opened by its kind, above the readers of each kind (`weights` owns the
//! `WeightSource` trait and the safetensors reader, `pth` the PyTorch archive reader).

use std::path::Path;

use crate::pth;
use crate::weights::{SafetensorsSource, WeightSource, WeightsError};

/// Opens a weight file by its kind: a PyTorch `.pth`/`.pt` archive, or safetensors (a file, a
/// shard index, or a directory).
pub fn open_source(path: &Path) -> Result<Box<dyn WeightSource>, WeightsError> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("pth") | Some("pt") | Some("bin") => Ok(Box::new(pth::open(path)?)),
        _ => Ok(Box::new(SafetensorsSource::open(path)?)),
    }
}
