//! Safetensors in and out of tch tensors. Writing streams one tensor at a time to the file (each
//! is copied to host memory only while it is written), so a 5B model's optimizer state never needs
//! a second full copy in RAM.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use anyhow::{bail, Context, Result};
use bwm_model::weights::{SafetensorsSource, WeightSource};
use safetensors::tensor::{Dtype, View};
use tch::{Device, Kind, Tensor};

struct TensorView<'a> {
    tensor: &'a Tensor,
    dtype: Dtype,
    shape: Vec<usize>,
    bytes: usize,
}

impl<'a> TensorView<'a> {
    fn new(name: &str, tensor: &'a Tensor) -> Result<Self> {
        let kind = tensor.kind();
        let dtype = match kind {
            Kind::Float => Dtype::F32,
            Kind::BFloat16 => Dtype::BF16,
            Kind::Half => Dtype::F16,
            Kind::Double => Dtype::F64,
            Kind::Int64 => Dtype::I64,
            Kind::Int => Dtype::I32,
            Kind::Uint8 => Dtype::U8,
            Kind::Bool => Dtype::BOOL,
            other => bail!("tensor '{name}': dtype {other:?} cannot be written to safetensors"),
        };
        let shape: Vec<usize> = tensor.size().iter().map(|&d| d as usize).collect();
        let bytes = shape.iter().product::<usize>() * kind.elt_size_in_bytes();
        Ok(Self { tensor, dtype, shape, bytes })
    }
}

impl View for TensorView<'_> {
    fn dtype(&self) -> Dtype {
        self.dtype
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        let host = self.tensor.detach().to_device(Device::Cpu).contiguous();
        let mut out = vec![0u8; self.bytes];
        host.copy_data_u8(&mut out, host.numel());
        Cow::Owned(out)
    }
    fn data_len(&self) -> usize {
        self.bytes
    }
}

/// Writes `tensors` (any device) to `path` and fsyncs it. Names must be unique.
pub fn write_tensors(path: &Path, tensors: &[(String, Tensor)], metadata: &BTreeMap<String, String>) -> Result<()> {
    let mut views = Vec::with_capacity(tensors.len());
    let mut seen = std::collections::BTreeSet::new();
    for (name, t) in tensors {
        if !seen.insert(name.as_str()) {
            bail!("tensor name '{name}' appears twice");
        }
        views.push((name.clone(), TensorView::new(name, t)?));
    }
    let meta: HashMap<String, String> = metadata.clone().into_iter().collect();
    safetensors::tensor::serialize_to_file(views, if meta.is_empty() { None } else { Some(meta) }, path)
        .with_context(|| format!("writing {}", path.display()))?;
    std::fs::File::open(path)
        .and_then(|f| f.sync_all())
        .with_context(|| format!("syncing {}", path.display()))?;
    Ok(())
}

/// `write_tensors` into `path` as a whole or not at all: written beside it (`NAME.tmp`, its folder
/// created) and renamed into place, so that a reader never sees half a file.
pub fn write_tensors_replacing(path: &Path, tensors: &[(String, Tensor)], metadata: &BTreeMap<String, String>) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp);
    if let Err(e) = write_tensors(&tmp, tensors, metadata) {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    std::fs::rename(&tmp, path).with_context(|| format!("renaming {} to {}", tmp.display(), path.display()))
}

/// Every tensor of a safetensors file, in its stored dtype, on `device`.
pub fn read_tensors(path: &Path, device: Device) -> Result<BTreeMap<String, Tensor>> {
    let source = SafetensorsSource::open(path)?;
    let mut out = BTreeMap::new();
    for name in source.names() {
        let kind = source.kind(&name).with_context(|| format!("{}: '{name}'", path.display()))?;
        out.insert(name.clone(), source.load(&name, kind, device)?);
    }
    Ok(out)
}

/// The `__metadata__` map of a safetensors file.
pub fn read_metadata(path: &Path) -> Result<BTreeMap<String, String>> {
    Ok(bwm_model::weights::safetensors_metadata(path)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_dtype_values_and_metadata() {
        let dir = bwm_testdir::TestDir::new("ckpt-tf");
        let path = dir.join("t.safetensors");
        let a = Tensor::randn([3, 5], (Kind::Float, Device::Cpu));
        let b = Tensor::randn([7], (Kind::Float, Device::Cpu)).to_kind(Kind::BFloat16);
        let c = Tensor::arange(6, (Kind::Int64, Device::Cpu)).view([2, 3]).transpose(0, 1);
        let meta = BTreeMap::from([("step".to_string(), "12".to_string())]);
        write_tensors(&path, &[("a".into(), a.shallow_clone()), ("b".into(), b.shallow_clone()), ("c".into(), c.shallow_clone())], &meta).unwrap();
        let back = read_tensors(&path, Device::Cpu).unwrap();
        assert!(back["a"].equal(&a));
        assert_eq!(back["b"].kind(), Kind::BFloat16);
        assert!(back["b"].equal(&b));
        assert!(back["c"].equal(&c.contiguous()));
        assert_eq!(read_metadata(&path).unwrap()["step"], "12");
        let dup = write_tensors(&path, &[("a".into(), a.shallow_clone()), ("a".into(), a)], &BTreeMap::new());
        assert!(dup.unwrap_err().to_string().contains("twice"));
    }
}
