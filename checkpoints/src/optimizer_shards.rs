//! Sharded optimizer state in a checkpoint folder: the trained tensors are packed end to end into
//! one flat vector (in `layout` order), and each data-parallel rank writes the slice it owns as
//! `optimizer-RRRRR-of-WWWWW.safetensors` (1-D tensors `master`, `exp_avg`, `exp_avg_sq`, and
//! `ema` when configured; the slice bounds and the layout in the metadata). Reading takes any
//! element range from whichever files hold it, so a run resumes on another number of ranks.
//! The unsharded form of earlier checkpoints (`optimizer.safetensors` with `master.<name>`...)
//! reads through the same functions.

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use memmap2::Mmap;
use safetensors::SafeTensors;
use tch::{Device, Kind, Tensor};

use crate::tensor_file::write_tensors;

pub const LEGACY_FILE: &str = "optimizer.safetensors";
const START: &str = "bwm.shard_start";
const END: &str = "bwm.shard_end";
const LAYOUT: &str = "bwm.layout";

/// The packing order: (name, element count) of each trained tensor.
pub type Layout = Vec<(String, usize)>;

pub fn shard_file_name(rank: usize, world: usize) -> String {
    format!("optimizer-{rank:05}-of-{world:05}.safetensors")
}

/// Writes rank `rank`'s slice `range` of the flat state (`tensors`: name -> 1-D f32 of
/// `range.len()` elements) into `dir`.
pub fn write_shard(
    dir: &Path,
    rank: usize,
    world: usize,
    range: Range<usize>,
    layout: &Layout,
    tensors: &[(String, Tensor)],
) -> Result<PathBuf> {
    for (name, t) in tensors {
        ensure!(
            t.numel() == range.len(),
            "optimizer shard '{name}' has {} elements, the range {range:?} {}",
            t.numel(),
            range.len()
        );
    }
    let meta = BTreeMap::from([
        (START.to_string(), range.start.to_string()),
        (END.to_string(), range.end.to_string()),
        (LAYOUT.to_string(), serde_json::to_string(layout)?),
    ]);
    let path = dir.join(shard_file_name(rank, world));
    write_tensors(&path, tensors, &meta)?;
    Ok(path)
}

struct ShardFile {
    path: PathBuf,
    range: Range<usize>,
    mmap: Mmap,
}

/// The optimizer state files of one checkpoint folder.
pub struct OptimizerState {
    dir: PathBuf,
    shards: Vec<ShardFile>,
    legacy: Option<Mmap>,
    layout: Layout,
}

impl OptimizerState {
    /// Opens the shard files of `dir` (or its legacy `optimizer.safetensors`) and checks that they
    /// were written for `layout` and cover it without gaps.
    pub fn open(dir: &Path, layout: &Layout) -> Result<Self> {
        let mut shards = Vec::new();
        let entries =
            std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))?;
        for entry in entries {
            let path = entry?.path();
            let name = path
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or_default();
            if !(name.starts_with("optimizer-") && name.ends_with(".safetensors")) {
                continue;
            }
            let mmap = map(&path)?;
            let (_, meta) = SafeTensors::read_metadata(&mmap)
                .with_context(|| format!("{}: not a safetensors file", path.display()))?;
            let meta = meta.metadata().clone().unwrap_or_default();
            let field = |k: &str| {
                meta.get(k)
                    .with_context(|| format!("{}: no '{k}' in the metadata", path.display()))
            };
            let stored: Layout = serde_json::from_str(field(LAYOUT)?)
                .with_context(|| format!("{}: bad {LAYOUT}", path.display()))?;
            ensure!(
                &stored == layout,
                "{} was written for another set of trained tensors ({} tensors, {} elements; this run trains {} tensors, {} elements)",
                path.display(),
                stored.len(),
                stored.iter().map(|(_, n)| n).sum::<usize>(),
                layout.len(),
                layout.iter().map(|(_, n)| n).sum::<usize>()
            );
            let bound = |k: &str| -> Result<usize> {
                let v = field(k)?;
                v.parse().with_context(|| format!("{}: '{k}' is {v:?}, not an element index", path.display()))
            };
            let range = bound(START)?..bound(END)?;
            ensure!(range.start <= range.end, "{}: its elements {}..{} run backwards", path.display(), range.start, range.end);
            shards.push(ShardFile { path, range, mmap });
        }
        let legacy = if shards.is_empty() && dir.join(LEGACY_FILE).is_file() {
            Some(map(&dir.join(LEGACY_FILE))?)
        } else {
            None
        };
        ensure!(
            !shards.is_empty() || legacy.is_some(),
            "{}: no optimizer state (optimizer-*-of-*.safetensors)",
            dir.display()
        );
        shards.sort_by_key(|s| s.range.start);
        let total: usize = layout.iter().map(|(_, n)| n).sum();
        if legacy.is_none() {
            let mut covered = 0;
            for s in &shards {
                ensure!(
                    s.range.start <= covered,
                    "{}: optimizer shards leave elements {covered}..{} uncovered",
                    dir.display(),
                    s.range.start
                );
                ensure!(
                    s.range.start == covered,
                    "{}: optimizer shards overlap at elements {}..{covered} ({})",
                    dir.display(),
                    s.range.start,
                    s.path.display()
                );
                covered = s.range.end;
            }
            ensure!(
                covered >= total,
                "{}: optimizer shards cover {covered} of {total} elements",
                dir.display()
            );
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            shards,
            legacy,
            layout: layout.clone(),
        })
    }

    /// Whether the state holds `key` (e.g. `ema`).
    pub fn has(&self, key: &str) -> Result<bool> {
        Ok(match &self.legacy {
            Some(m) => {
                let st = SafeTensors::deserialize(m)?;
                self.layout
                    .iter()
                    .all(|(n, _)| st.tensor(&format!("{key}.{n}")).is_ok())
            }
            None => self.shards.iter().all(|s| {
                SafeTensors::deserialize(&s.mmap)
                    .map(|st| st.tensor(key).is_ok())
                    .unwrap_or(false)
            }),
        })
    }

    /// Elements `range` of the flat state `key` as a 1-D f32 tensor on `device`; elements past the
    /// layout's end (padding) are zero.
    pub fn read_range(&self, key: &str, range: Range<usize>, device: Device) -> Result<Tensor> {
        let out = Tensor::zeros([range.len() as i64], (Kind::Float, Device::Cpu));
        let copy = |bytes: &[u8], src_start: usize, expected: usize, what: &dyn Fn() -> String| -> Result<()> {
            // Elements [src_start, src_start + n) of the flat state, f32 little-endian.
            ensure!(bytes.len() % 4 == 0, "{}: not f32 data", what());
            let n = bytes.len() / 4;
            ensure!(n == expected, "{}: {n} elements where its place in the state holds {expected}", what());
            let (lo, hi) = (range.start.max(src_start), range.end.min(src_start + n));
            if lo < hi {
                let piece = Tensor::from_data_size(
                    &bytes[(lo - src_start) * 4..(hi - src_start) * 4],
                    &[(hi - lo) as i64],
                    Kind::Float,
                );
                out.narrow(0, (lo - range.start) as i64, (hi - lo) as i64)
                    .copy_(&piece);
            }
            Ok(())
        };
        match &self.legacy {
            Some(m) => {
                let st = SafeTensors::deserialize(m)?;
                let mut offset = 0;
                for (name, n) in &self.layout {
                    if offset < range.end && offset + n > range.start {
                        let key_name = format!("{key}.{name}");
                        let view = st.tensor(&key_name).with_context(|| {
                            format!("{}: no '{key_name}'", self.dir.join(LEGACY_FILE).display())
                        })?;
                        ensure!(
                            view.dtype() == safetensors::Dtype::F32,
                            "'{key_name}' is not f32"
                        );
                        copy(view.data(), offset, *n, &|| key_name.clone())?;
                    }
                    offset += n;
                }
            }
            None => {
                for s in self
                    .shards
                    .iter()
                    .filter(|s| s.range.start < range.end && s.range.end > range.start)
                {
                    let st = SafeTensors::deserialize(&s.mmap)?;
                    let view = st
                        .tensor(key)
                        .with_context(|| format!("{}: no '{key}'", s.path.display()))?;
                    ensure!(
                        view.dtype() == safetensors::Dtype::F32,
                        "{}: '{key}' is not f32",
                        s.path.display()
                    );
                    copy(view.data(), s.range.start, s.range.len(), &|| format!("{}: '{key}'", s.path.display()))?;
                }
            }
        }
        Ok(out.to_device(device))
    }

    /// The flat state `key` cut back into the trained tensors (1-D each), by name.
    pub fn read_named(&self, key: &str, device: Device) -> Result<Vec<(String, Tensor)>> {
        let total: usize = self.layout.iter().map(|(_, n)| n).sum();
        let flat = self.read_range(key, 0..total, device)?;
        let mut offset = 0i64;
        let mut out = Vec::with_capacity(self.layout.len());
        for (name, n) in &self.layout {
            out.push((name.clone(), flat.narrow(0, offset, *n as i64)));
            offset += *n as i64;
        }
        Ok(out)
    }
}

/// The packing layout stored in a checkpoint folder's shard files (the first one found).
pub fn stored_layout(dir: &Path) -> Result<Layout> {
    for entry in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let path = entry?.path();
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default();
        if name.starts_with("optimizer-") && name.ends_with(".safetensors") {
            let meta = crate::tensor_file::read_metadata(&path)?;
            let text = meta
                .get(LAYOUT)
                .with_context(|| format!("{}: no {LAYOUT}", path.display()))?;
            return Ok(serde_json::from_str(text)?);
        }
    }
    bail!("{}: no optimizer shard files", dir.display())
}

fn map(path: &Path) -> Result<Mmap> {
    let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    // SAFETY: checkpoint files are written once (temporary folder + rename) and never modified.
    unsafe { Mmap::map(&file) }.with_context(|| format!("mapping {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_read_across_shards_and_from_the_legacy_form() {
        let dir = bwm_testdir::TestDir::new("optshards");
        let layout: Layout = vec![("a".into(), 5), ("b".into(), 6)];
        let flat = Tensor::arange(12, (Kind::Float, Device::Cpu)); // 11 elements + 1 padding
        for (rank, r) in [(0usize, 0..4usize), (1, 4..8), (2, 8..12)] {
            let part = flat.narrow(0, r.start as i64, r.len() as i64);
            write_shard(
                &dir,
                rank,
                3,
                r,
                &layout,
                &[
                    ("master".into(), part.shallow_clone()),
                    ("exp_avg".into(), part * 2),
                ],
            )
            .unwrap();
        }
        let state = OptimizerState::open(&dir, &layout).unwrap();
        assert!(state
            .read_range("master", 3..9, Device::Cpu)
            .unwrap()
            .equal(&flat.narrow(0, 3, 6)));
        assert!(state
            .read_range("exp_avg", 0..6, Device::Cpu)
            .unwrap()
            .equal(&(flat.narrow(0, 0, 6) * 2)));
        assert!(state.has("exp_avg").unwrap() && !state.has("ema").unwrap());
        let named = state.read_named("master", Device::Cpu).unwrap();
        assert_eq!(named[1].0, "b");
        assert!(named[1].1.equal(&flat.narrow(0, 5, 6)));
        assert_eq!(stored_layout(&dir).unwrap(), layout);
        assert!(
            OptimizerState::open(&dir, &vec![("a".into(), 5)]).is_err(),
            "another layout is refused"
        );
        std::fs::remove_file(dir.join(shard_file_name(1, 3))).unwrap();
        assert!(OptimizerState::open(&dir, &layout)
            .err()
            .expect("a gap is an error")
            .to_string()
            .contains("uncovered"));
        // A shard whose data is shorter than its range, or whose range overlaps another's, is
        // refused rather than read as zeros or overwritten.
        let shard = |range: Range<usize>, n: i64| {
            let meta = BTreeMap::from([
                (START.to_string(), range.start.to_string()),
                (END.to_string(), range.end.to_string()),
                (LAYOUT.to_string(), serde_json::to_string(&layout).unwrap()),
            ]);
            write_tensors(&dir.join(shard_file_name(1, 3)), &[("master".into(), flat.narrow(0, 4, n))], &meta).unwrap();
        };
        shard(4..8, 3);
        let e = OptimizerState::open(&dir, &layout).unwrap().read_range("master", 0..12, Device::Cpu).unwrap_err().to_string();
        assert!(e.contains("3 elements where its place in the state holds 4"), "{e}");
        shard(3..8, 5);
        let e = OptimizerState::open(&dir, &layout).err().expect("an overlap is an error").to_string();
        assert!(e.contains("optimizer shards overlap at elements 3..4"), "{e}");

        let legacy = dir.join("legacy");
        std::fs::create_dir_all(&legacy).unwrap();
        write_tensors(
            &legacy.join(LEGACY_FILE),
            &[
                ("master.a".into(), flat.narrow(0, 0, 5)),
                ("master.b".into(), flat.narrow(0, 5, 6).view([2, 3])),
            ],
            &BTreeMap::new(),
        )
        .unwrap();
        let state = OptimizerState::open(&legacy, &layout).unwrap();
        assert!(state
            .read_range("master", 2..11, Device::Cpu)
            .unwrap()
            .equal(&flat.narrow(0, 2, 9)));
    }
}
