//! The BWM release layout (the embedded default dataset): a `demo.jsonl` manifest with one line
//! per episode naming its parquet file (per-frame `observation.state` / `action` lists) and its mp4.

use std::fs::File;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use arrow_array::{Array, Float32Array, Float64Array, ListArray};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use serde::Deserialize;

/// One manifest line.
#[derive(Debug, Clone, Deserialize)]
pub struct Episode {
    pub episode_index: i64,
    pub length: usize,
    #[serde(default)]
    pub start_frame: usize,
    pub video: String,
    pub action: String,
    #[serde(default)]
    pub prompt: String,
    #[serde(default)]
    pub task: String,
}

/// Which parquet column and which of its indices form the action vector, in order.
#[derive(Debug, Clone, PartialEq, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ActionSpec {
    pub column: String,
    pub indices: Vec<usize>,
    /// The stat.json group holding this vector's statistics.
    pub stats_group: String,
}

impl ActionSpec {
    /// BWM's `eef_abs`: absolute end-effector poses read from `observation.state`:
    /// left xyz, left euler, left gripper, right xyz, right euler, right gripper.
    pub fn eef_abs() -> Self {
        Self {
            column: "observation.state".into(),
            indices: vec![7, 8, 9, 10, 11, 12, 6, 20, 21, 22, 23, 24, 25, 19],
            stats_group: "state_pose".into(),
        }
    }
}

pub struct BwmDataset {
    pub root: PathBuf,
    pub episodes: Vec<Episode>,
}

impl BwmDataset {
    /// Opens a dataset root holding `demo.jsonl` (or the manifest file itself).
    pub fn open(path: &Path) -> Result<Self> {
        let (root, manifest) = if path.is_dir() {
            (path.to_path_buf(), path.join("demo.jsonl"))
        } else {
            (path.parent().unwrap_or(Path::new(".")).to_path_buf(), path.to_path_buf())
        };
        let text = std::fs::read_to_string(&manifest).with_context(|| format!("reading manifest {}", manifest.display()))?;
        let episodes = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
            .map(|(i, l)| {
                serde_json::from_str(l).with_context(|| format!("{}: line {} is not a valid episode entry", manifest.display(), i + 1))
            })
            .collect::<Result<Vec<Episode>>>()?;
        ensure!(!episodes.is_empty(), "{}: no episodes listed", manifest.display());
        Ok(Self { root, episodes })
    }

    /// The action vectors of one episode, [frames][d_a], checked against the manifest length.
    pub fn actions(&self, episode: &Episode, spec: &ActionSpec) -> Result<Vec<Vec<f32>>> {
        let path = self.root.join(&episode.action);
        let rows = read_list_column(&path, &spec.column)?;
        ensure!(
            rows.len() == episode.length,
            "{}: {} rows but the manifest says {} frames",
            path.display(),
            rows.len(),
            episode.length
        );
        rows.iter()
            .enumerate()
            .map(|(i, row)| {
                spec.indices
                    .iter()
                    .map(|&j| {
                        let v = *row.get(j).with_context(|| {
                            format!("{}: row {i} of '{}' has {} values, index {j} requested", path.display(), spec.column, row.len())
                        })?;
                        ensure!(v.is_finite(), "{}: row {i} of '{}' holds a non-finite value", path.display(), spec.column);
                        Ok(v)
                    })
                    .collect()
            })
            .collect()
    }
}

/// Reads a list<float> column of a parquet file, one Vec per row.
pub fn read_list_column(path: &Path, column: &str) -> Result<Vec<Vec<f32>>> {
    let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let reader = ParquetRecordBatchReaderBuilder::try_new(file)
        .with_context(|| format!("{}: not a readable parquet file", path.display()))?
        .build()?;
    let mut rows = Vec::new();
    for batch in reader {
        let batch = batch.with_context(|| format!("reading {}", path.display()))?;
        let Some(col) = batch.column_by_name(column) else {
            let names: Vec<_> = batch.schema().fields().iter().map(|f| f.name().clone()).collect();
            bail!("{}: no column '{column}' (columns: {})", path.display(), names.join(", "));
        };
        let list = col
            .as_any()
            .downcast_ref::<ListArray>()
            .with_context(|| format!("{}: column '{column}' is not a list column", path.display()))?;
        for i in 0..list.len() {
            let values = list.value(i);
            let row: Vec<f32> = if let Some(a) = values.as_any().downcast_ref::<Float32Array>() {
                a.values().to_vec()
            } else if let Some(a) = values.as_any().downcast_ref::<Float64Array>() {
                a.values().iter().map(|&v| v as f32).collect()
            } else {
                bail!("{}: column '{column}' holds {:?}, expected floats", path.display(), values.data_type());
            };
            rows.push(row);
        }
    }
    Ok(rows)
}
