//! Where episodes start: frame 0 and the initial pose/joints of dataset episodes, or x0 images
//! with initial state files.

use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use bwm_data::frames::{fit, stack_views_vertically};
use bwm_data::{open_dataset, ActionSpec};
use image::RgbImage;

use super::config::{EvalConfig, TaskConfig};
use crate::msgpack_numpy::{Dtype, NdArray};

pub struct Start {
    /// Where it comes from, for the records ("dataset episode 41", "x0.png").
    pub source: String,
    /// x0 at the world model's frame size.
    pub x0: RgbImage,
    /// Views stacked in x0.
    pub views: usize,
    pub pose: Option<Vec<f32>>,
    pub joints: Option<Vec<f32>>,
    pub prompt: String,
    pub fps: f64,
}

pub struct Task {
    pub cfg: TaskConfig,
    pub starts: Vec<Start>,
}

/// Loads every task's starts; `need_pose` / `need_joints` say which initial vectors the
/// policies' adapters use.
pub fn load_tasks(cfg: &EvalConfig, need_pose: bool, need_joints: bool) -> Result<Vec<Task>> {
    let size = cfg.frame_size()?;
    cfg.tasks
        .iter()
        .map(|t| {
            let starts = match &t.dataset {
                Some(path) => dataset_starts(cfg, t, path, size, need_pose, need_joints),
                None => file_starts(cfg, t, size, need_pose, need_joints),
            }
            .with_context(|| format!("task '{}'", t.name))?;
            Ok(Task {
                cfg: t.clone(),
                starts,
            })
        })
        .collect()
}

fn dataset_starts(
    cfg: &EvalConfig,
    t: &TaskConfig,
    path: &Path,
    size: (u32, u32),
    need_pose: bool,
    need_joints: bool,
) -> Result<Vec<Start>> {
    let source = open_dataset(path)?;
    let infos = source.episodes();
    let positions: Vec<usize> = match &t.episodes {
        Some(list) => list.clone(),
        None => (0..infos.len()).collect(),
    };
    ensure!(!positions.is_empty(), "no episodes selected");
    let views = t.cameras.cameras.len().max(1);
    let pose_spec = ActionSpec::parse(&t.pose_actions)?;
    let joint_spec = ActionSpec::parse(&t.joint_actions)?;
    positions
        .iter()
        .map(|&pos| {
            let info = infos.get(pos).with_context(|| {
                format!(
                    "episode position {pos} is out of range ({} episodes in {})",
                    infos.len(),
                    path.display()
                )
            })?;
            let what = || format!("dataset episode {} (position {pos})", info.index);
            let frame = source
                .frames(pos, 0..1, &t.cameras)
                .with_context(what)?
                .into_iter()
                .next()
                .with_context(what)?;
            let first = |spec: &ActionSpec| -> Result<Vec<f32>> {
                source
                    .vectors(pos, spec)
                    .with_context(what)?
                    .into_iter()
                    .next()
                    .with_context(|| format!("{}: no vectors", what()))
            };
            let prompt = t.prompt.clone().unwrap_or_else(|| {
                if info.task.is_empty() {
                    t.name.clone()
                } else {
                    info.task.clone()
                }
            });
            Ok(Start {
                source: format!("{} episode {}", path.display(), info.index),
                x0: fit(&frame, size.0, size.1, cfg.resize),
                views,
                pose: if need_pose {
                    Some(first(&pose_spec)?)
                } else {
                    None
                },
                joints: if need_joints {
                    Some(first(&joint_spec)?)
                } else {
                    None
                },
                prompt,
                fps: cfg.fps.unwrap_or(source.fps(pos).unwrap_or(30.0)),
            })
        })
        .collect()
}

fn file_starts(
    cfg: &EvalConfig,
    t: &TaskConfig,
    size: (u32, u32),
    need_pose: bool,
    need_joints: bool,
) -> Result<Vec<Start>> {
    t.starts
        .iter()
        .enumerate()
        .map(|(j, s)| {
            let views = s.images.len();
            ensure!(size.1 % views as u32 == 0, "start {j}: {views} images do not split the {}-pixel-high frame evenly", size.1);
            let view_h = size.1 / views as u32;
            let images = s
                .images
                .iter()
                .map(|p| Ok(fit(&image::open(p).with_context(|| format!("start {j}: reading {}", p.display()))?.to_rgb8(), size.0, view_h, cfg.resize)))
                .collect::<Result<Vec<_>>>()?;
            let x0 = stack_views_vertically(&images)?;
            let read = |p: &Option<std::path::PathBuf>, what: &str, needed: bool| -> Result<Option<Vec<f32>>> {
                match p {
                    Some(p) => Ok(Some(read_vector(p).with_context(|| format!("start {j}: {what} file"))?)),
                    None if needed => bail!("start {j}: the policies' adapters need the initial {what}: add {what} = \"file.json\""),
                    None => Ok(None),
                }
            };
            Ok(Start {
                source: s.images.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join("+"),
                x0,
                views,
                pose: read(&s.pose, "pose", need_pose)?,
                joints: read(&s.joints, "joints", need_joints)?,
                prompt: s.prompt.clone().or_else(|| t.prompt.clone()).unwrap_or_else(|| t.name.clone()),
                fps: cfg.fps.unwrap_or(30.0),
            })
        })
        .collect()
}

/// A vector from a JSON list of numbers or a 1-D .npy (any numeric dtype, little-endian).
pub fn read_vector(path: &Path) -> Result<Vec<f32>> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let v = if bytes.starts_with(b"\x93NUMPY") {
        let a =
            read_npy(&bytes).with_context(|| format!("{}: not a readable .npy", path.display()))?;
        ensure!(
            a.shape.len() == 1,
            "{}: expected a 1-D array, got {}",
            path.display(),
            a.describe()
        );
        a.to_f32()
    } else {
        serde_json::from_slice::<Vec<f32>>(&bytes).with_context(|| {
            format!(
                "{}: expected a JSON list of numbers or a .npy file",
                path.display()
            )
        })?
    };
    ensure!(
        !v.is_empty() && v.iter().all(|x| x.is_finite()),
        "{}: the vector is empty or holds NaN/infinite values",
        path.display()
    );
    Ok(v)
}

/// The array of a .npy file (format versions 1-3, C order).
fn read_npy(bytes: &[u8]) -> Result<NdArray> {
    ensure!(bytes.len() >= 10, "file too short");
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            ensure!(bytes.len() >= 12, "file too short");
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => bail!("unknown .npy version {v}"),
    };
    let header = bytes
        .get(start..start + header_len)
        .context("truncated header")?;
    let header = std::str::from_utf8(header).context("header is not text")?;
    let field = |name: &str| -> Result<&str> {
        let at = header
            .find(&format!("'{name}':"))
            .with_context(|| format!("header has no '{name}'"))?;
        Ok(header[at + name.len() + 3..].trim_start())
    };
    let descr = field("descr")?;
    let descr = descr
        .strip_prefix('\'')
        .and_then(|d| d.split('\'').next())
        .context("header 'descr' is not a string")?;
    ensure!(
        field("fortran_order")?.starts_with("False"),
        "Fortran-order arrays are not supported"
    );
    let shape = field("shape")?;
    let shape = shape
        .strip_prefix('(')
        .and_then(|s| s.split(')').next())
        .context("header 'shape' is not a tuple")?;
    let shape = shape
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .with_context(|| format!("shape entry '{s}'"))
        })
        .collect::<Result<Vec<_>>>()?;
    NdArray::new(
        Dtype::parse(descr)?,
        shape,
        bytes[start + header_len..].to_vec(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_from_json_and_npy() {
        let dir = bwm_testdir::TestDir::new("eval-vec");
        let json = dir.join("s.json");
        std::fs::write(&json, "[1, 2.5, -3]").unwrap();
        assert_eq!(read_vector(&json).unwrap(), vec![1.0, 2.5, -3.0]);
        // np.save of np.array([1.5, -2.0], dtype=np.float64)
        let header = "{'descr': '<f8', 'fortran_order': False, 'shape': (2,), }";
        let mut h = header.to_string();
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut npy = b"\x93NUMPY\x01\x00".to_vec();
        npy.extend((h.len() as u16).to_le_bytes());
        npy.extend(h.as_bytes());
        npy.extend(1.5f64.to_le_bytes());
        npy.extend((-2.0f64).to_le_bytes());
        let path = dir.join("s.npy");
        std::fs::write(&path, &npy).unwrap();
        assert_eq!(read_vector(&path).unwrap(), vec![1.5, -2.0]);
        std::fs::write(&json, "{\"a\": 1}").unwrap();
        assert!(read_vector(&json).is_err());
    }
}
