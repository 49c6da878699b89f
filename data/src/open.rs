//! The dataset a path holds, in whichever format the files show.

use std::path::Path;

use anyhow::{bail, ensure, Result};

use crate::bwm_layout::BwmSource;
use crate::lerobot::LeRobotDataset;
use crate::robotwin::{self, RoboTwinDataset};
use crate::source::EpisodeSource;

/// Opens a dataset, detecting its format:
/// - a directory with `demo.jsonl`, or a `.jsonl` manifest: the BWM release layout;
/// - a directory with `meta/info.json`: LeRobot, v2.0/v2.1 (`meta/episodes.jsonl`, one file per
///   episode) or v3.0 (`meta/episodes/*/*.parquet`, many episodes per file) by its `codebase_version`;
/// - an `.hdf5` file, or a directory holding `*.hdf5` files (directly or in `data/`): RoboTwin 2.0,
///   original or 2026 layout, per file.
pub fn open_dataset(path: &Path) -> Result<Box<dyn EpisodeSource>> {
    ensure!(path.exists(), "dataset {} does not exist", path.display());
    if path.is_file() {
        return match path.extension().and_then(|e| e.to_str()) {
            Some("jsonl") => Ok(Box::new(BwmSource::open(path)?)),
            Some("hdf5" | "h5") => Ok(Box::new(RoboTwinDataset::open(path)?)),
            _ => bail!("{}: not a dataset (expected a directory, a .jsonl manifest or an .hdf5 file)", path.display()),
        };
    }
    if path.join("demo.jsonl").is_file() {
        return Ok(Box::new(BwmSource::open(path)?));
    }
    if path.join("meta/info.json").is_file() {
        return Ok(Box::new(LeRobotDataset::open(path)?));
    }
    if robotwin::has_hdf5_files(path)? {
        return Ok(Box::new(RoboTwinDataset::open(path)?));
    }
    bail!(
        "{}: no dataset format recognized (looked for demo.jsonl, meta/info.json, and *.hdf5 files here or in data/)",
        path.display()
    )
}
