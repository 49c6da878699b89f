//! The latent cache `bwm prepare` writes and the trainer reads, and an `index.json` describing it.
//! The trainer never decodes video.
//!
//! Layout (version 2): shard files `shard-NNNNN.safetensors`, each holding n clips stacked:
//! `latents` `[n, C, F, h, w]` bf16, `actions` `[n, F_pixel, d_a]` normalized f32, `episode` `[n]` i64,
//! `frame_ids` [n, F_pixel] i64 and, when the cache keeps pixels, `frames` [n, 3, F_pixel, H, W]
//! u8 (validation against real pixels). A cache of raw clips (`has_latents: false`, written by
//! `bwm prepare --raw`) has `frames` and no `latents`: the trainer encodes them as it reads them.
//! `index.json` lists the clips in order; a clip's `file`
//! names its shard, and its row in the shard is its position among the index's clips of that
//! file. Version 1 caches (one f32 file per clip, unstacked) still load.
//!
//! Sample order: global sample index g -> epoch g / N, slot g % N of a permutation of the N
//! training clips keyed by (seed, epoch); so a run resumes at any sample index, and any number of
//! ranks sharing a global batch read the same clips.

use std::collections::{BTreeMap, HashMap};
use std::io::{Read, Seek, SeekFrom};
use std::path::{Component, Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

pub const INDEX_FILE: &str = "index.json";
/// The layout `CacheWriter` and `write_shard` produce.
pub const CACHE_VERSION: u32 = 2;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClipEntry {
    pub file: String,
    pub episode: i64,
    /// Pixel frames of the episode that form the clip, in clip order (x0, history, future).
    pub frames: Vec<usize>,
    #[serde(default)]
    pub task: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CacheIndex {
    pub version: u32,
    /// [C, F, h, w] of every clip's latents.
    pub latent_shape: Vec<i64>,
    pub action_dim: i64,
    /// Pixel frames per clip: 1 (x0) + history + future.
    pub pixel_frames: usize,
    pub history_frames: usize,
    pub future_frames: usize,
    /// Pixel size (width, height) the clips were encoded at.
    pub resolution: [u32; 2],
    pub fps: f64,
    /// What produced the latents (VAE file and width), for the record.
    pub vae: String,
    pub has_frames: bool,
    /// False for raw clips: pixel frames only, encoded by the trainer.
    #[serde(default = "yes")]
    pub has_latents: bool,
    pub clips: Vec<ClipEntry>,
}

fn yes() -> bool {
    true
}

impl CacheIndex {
    /// [3, F_pixel, H, W]: a clip's pixel frames.
    pub fn frame_shape(&self) -> Vec<i64> {
        let [w, h] = self.resolution;
        vec![3, self.pixel_frames as i64, h as i64, w as i64]
    }

    /// [F_pixel, d_a]: a clip's actions.
    pub fn action_shape(&self) -> Vec<i64> {
        vec![self.pixel_frames as i64, self.action_dim]
    }

    /// An index without clips yet, for clips of x0 + `history` + `future` pixel frames.
    pub fn new(latent_shape: Vec<i64>, action_dim: i64, history: usize, future: usize, resolution: [u32; 2], fps: f64, vae: impl Into<String>) -> Self {
        Self {
            version: CACHE_VERSION,
            latent_shape,
            action_dim,
            pixel_frames: 1 + history + future,
            history_frames: history,
            future_frames: future,
            resolution,
            fps,
            vae: vae.into(),
            has_frames: false,
            has_latents: true,
            clips: vec![],
        }
    }
}

/// What `bwm prepare` records in `index.json` besides `CacheIndex`'s fields, at the same level;
/// every field is optional, so indexes written without them load.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IndexExtras {
    /// The distinct sizes [width, height] of the source frames (cameras composed, before any
    /// resizing) of the cached episodes.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub source_resolution: Vec<[u32; 2]>,
    /// Hash of `plan`: a rerun of `bwm prepare` continues this cache only when its plan hashes
    /// the same.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan_hash: Option<String>,
    /// The arguments, statistics and clip list the cache was prepared from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan: Option<serde_json::Value>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clips_per_shard: Option<usize>,
}

impl IndexExtras {
    /// The JSON keys of the fields above.
    pub const KEYS: [&'static str; 4] = ["source_resolution", "plan_hash", "plan", "clips_per_shard"];
}

/// Reads an index file: `CacheIndex`'s fields (unknown ones are an error) and the extras.
pub fn read_index(path: &Path) -> Result<(CacheIndex, IndexExtras)> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut value: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    let object = value.as_object_mut().with_context(|| format!("{}: not a JSON object", path.display()))?;
    let mut extras = serde_json::Map::new();
    for key in IndexExtras::KEYS {
        if let Some(v) = object.remove(key) {
            extras.insert(key.to_string(), v);
        }
    }
    let index: CacheIndex = serde_json::from_value(value).with_context(|| format!("parsing {}", path.display()))?;
    let extras: IndexExtras = serde_json::from_value(serde_json::Value::Object(extras)).with_context(|| format!("parsing {}", path.display()))?;
    Ok((index, extras))
}

/// Writes `dir/name` whole or not at all (temporary file, fsync, rename).
pub fn write_index(dir: &Path, name: &str, index: &CacheIndex, extras: &IndexExtras) -> Result<()> {
    let mut value = serde_json::to_value(index)?;
    let object = value.as_object_mut().context("the index serializes to a JSON object")?;
    if let serde_json::Value::Object(more) = serde_json::to_value(extras)? {
        object.extend(more);
    }
    write_atomically(dir, name, serde_json::to_string_pretty(&value)?.as_bytes())
}

/// Writes `dir/name` through a temporary file of this process, fsynced, then renamed over it.
pub fn write_atomically(dir: &Path, name: &str, bytes: &[u8]) -> Result<()> {
    let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    let written = (|| -> Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        std::io::Write::write_all(&mut f, bytes)?;
        f.sync_all()?;
        Ok(())
    })();
    if let Err(e) = written.and_then(|_| Ok(std::fs::rename(&tmp, dir.join(name))?)) {
        let _ = std::fs::remove_file(&tmp);
        return Err(e.context(format!("writing {}", dir.join(name).display())));
    }
    sync_dir(dir);
    Ok(())
}

/// Makes renames in `dir` durable; best effort (not every filesystem allows syncing a folder).
pub(crate) fn sync_dir(dir: &Path) {
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

/// One clip as the trainer sees it.
pub struct Clip {
    pub latents: Tensor,
    pub actions: Tensor,
    pub frames: Option<Tensor>,
}

/// One clip's latents and actions as f32 values (row-major, shapes as in the index), read
/// without any tensor operation, for loader threads; a raw clip has its u8 pixel frames
/// [3, F_pixel, H, W] instead of latents.
pub struct ClipValues {
    pub latents: Vec<f32>,
    pub actions: Vec<f32>,
    pub frames: Vec<u8>,
}

#[derive(Debug, Clone)]
pub struct LatentCache {
    pub dir: PathBuf,
    pub index: CacheIndex,
    pub extras: IndexExtras,
    /// Each clip's row in its file.
    rows: Vec<usize>,
}

impl LatentCache {
    pub fn open(dir: &Path) -> Result<Self> {
        let path = dir.join(INDEX_FILE);
        if !path.is_file() {
            bail!("{} does not exist (create the cache with `bwm prepare`)", path.display());
        }
        let (index, extras) = read_index(&path)?;
        ensure!(
            index.version == 1 || index.version == CACHE_VERSION,
            "{}: cache version {} is not supported (expected 1 or {CACHE_VERSION})",
            path.display(),
            index.version
        );
        ensure!(!index.clips.is_empty(), "{}: the cache holds no clips", path.display());
        ensure!(
            index.latent_shape.len() == 4 && index.latent_shape.iter().all(|&n| n > 0),
            "{}: latent_shape {:?} must be [C, F, h, w] of positive sizes",
            path.display(),
            index.latent_shape
        );
        ensure!(
            index.pixel_frames == 1 + index.history_frames + index.future_frames && index.future_frames > 0,
            "{}: pixel_frames {} must be 1 (x0) + history_frames {} + future_frames {} (at least 1)",
            path.display(),
            index.pixel_frames,
            index.history_frames,
            index.future_frames
        );
        ensure!(index.action_dim > 0, "{}: action_dim {} must be positive", path.display(), index.action_dim);
        ensure!(index.has_latents || index.has_frames, "{}: the cache holds neither latents nor pixel frames", path.display());
        let mut seen: HashMap<&str, usize> = HashMap::new();
        let mut rows = Vec::with_capacity(index.clips.len());
        for (i, c) in index.clips.iter().enumerate() {
            // Joined to the cache folder when the clip is read: a path that leaves it is refused.
            let inside = !c.file.is_empty() && Path::new(&c.file).components().all(|p| matches!(p, Component::Normal(_) | Component::CurDir));
            ensure!(inside, "{}: clip {i}'s file {} is not a relative path inside the cache folder", path.display(), c.file);
            let row = seen.entry(c.file.as_str()).or_insert(0);
            ensure!(index.version > 1 || *row == 0, "{}: clips {i} and an earlier one share the file {} (version 1 has one file per clip)", path.display(), c.file);
            rows.push(*row);
            *row += 1;
        }
        Ok(Self { dir: dir.to_path_buf(), index, extras, rows })
    }

    pub fn len(&self) -> usize {
        self.index.clips.len()
    }

    pub fn is_empty(&self) -> bool {
        self.index.clips.is_empty()
    }

    /// How many leading clips are for training when the clips of the last `holdout_episodes`
    /// episodes are held out; an error unless those clips form the cache's tail.
    pub fn training_clips(&self, holdout_episodes: usize) -> Result<usize> {
        let mut episodes: Vec<i64> = Vec::new();
        for c in &self.index.clips {
            if episodes.last() != Some(&c.episode) {
                ensure!(!episodes.contains(&c.episode), "{}: clips of episode {} are not contiguous", self.dir.display(), c.episode);
                episodes.push(c.episode);
            }
        }
        ensure!(
            holdout_episodes < episodes.len(),
            "data.holdout_episodes = {holdout_episodes} leaves no training episode (the cache has {})",
            episodes.len()
        );
        let held: Vec<i64> = episodes[episodes.len() - holdout_episodes..].to_vec();
        Ok(self.index.clips.iter().filter(|c| !held.contains(&c.episode)).count())
    }

    /// Reads clip `i` (latents and actions as f32, frames as u8), checking its shapes against
    /// the index. Only the clip's rows of its shard are read.
    pub fn load(&self, i: usize, device: Device) -> Result<Clip> {
        ensure!(
            self.index.has_latents,
            "{} holds raw clips (bwm prepare --raw): they have no latents until the trainer encodes them",
            self.dir.display()
        );
        let (mut file, row) = self.open_clip(i)?;
        let latents = self.field(&mut file, "latents", row)?;
        let actions = self.field(&mut file, "actions", row)?;
        let frames = file.read("frames", row)?;
        let path = file.path.clone();
        let tensor = |f: Field| Tensor::f_from_data_size(&f.bytes, &f.shape, f.kind).with_context(|| format!("{}: '{}'", path.display(), f.name));
        Ok(Clip {
            latents: tensor(latents)?.to_kind(Kind::Float).to_device(device),
            actions: tensor(actions)?.to_kind(Kind::Float).to_device(device),
            frames: frames.map(tensor).transpose()?.map(|f| f.to_device(device)),
        })
    }

    /// Clip `i`'s actions [F_pixel, d_a] as f32, read alone (a raw clip's frames are not read).
    pub fn load_actions(&self, i: usize, device: Device) -> Result<Tensor> {
        let (mut file, row) = self.open_clip(i)?;
        let f = self.field(&mut file, "actions", row)?;
        Ok(Tensor::f_from_data_size(&f.bytes, &f.shape, f.kind).with_context(|| format!("{}: 'actions'", file.path.display()))?.to_kind(Kind::Float).to_device(device))
    }

    /// Clip `i`'s latents (or, raw, pixel frames) and actions as f32 values, converted without
    /// tensor operations.
    pub fn load_values(&self, i: usize) -> Result<ClipValues> {
        let (mut file, row) = self.open_clip(i)?;
        let actions = self.field(&mut file, "actions", row)?.to_f32()?;
        if self.index.has_latents {
            let latents = self.field(&mut file, "latents", row)?.to_f32()?;
            return Ok(ClipValues { latents, actions, frames: Vec::new() });
        }
        let frames = self.field(&mut file, "frames", row)?;
        ensure!(frames.kind == Kind::Uint8, "{}: frames are {:?}, expected u8", file.path.display(), frames.kind);
        Ok(ClipValues { latents: Vec::new(), actions, frames: frames.bytes })
    }

    /// Clip `i`'s pixel frames [3, F_pixel, H, W] u8 and f32 actions, for a cache that keeps frames.
    pub fn load_frames(&self, i: usize, device: Device) -> Result<(Tensor, Tensor)> {
        let (mut file, row) = self.open_clip(i)?;
        let mut read = |name: &str| -> Result<Tensor> {
            let f = self.field(&mut file, name, row)?;
            Ok(Tensor::f_from_data_size(&f.bytes, &f.shape, f.kind)?.to_device(device))
        };
        let frames = read("frames")?;
        Ok((frames, read("actions")?.to_kind(Kind::Float)))
    }

    /// The file of clip `i`, and its row there (None: version 1, the whole tensors).
    fn open_clip(&self, i: usize) -> Result<(ShardReader, Option<usize>)> {
        let entry = self.index.clips.get(i).with_context(|| format!("clip {i} out of range ({} clips)", self.len()))?;
        let file = ShardReader::open(&self.dir.join(&entry.file))?;
        Ok((file, (self.index.version > 1).then(|| self.rows[i])))
    }

    /// `latents` or `actions` of a clip, checked against the index's shapes.
    fn field(&self, file: &mut ShardReader, name: &str, row: Option<usize>) -> Result<Field> {
        let f = file.read(name, row)?.with_context(|| format!("{}: no '{name}' tensor", file.path.display()))?;
        let expected = match name {
            "latents" => self.index.latent_shape.clone(),
            "frames" => self.index.frame_shape(),
            _ => self.index.action_shape(),
        };
        ensure!(f.shape == expected, "{}: {name} have shape {:?}, the index says {expected:?}", file.path.display(), f.shape);
        Ok(f)
    }
}

/// Bytes of one tensor (or one row of it) of a safetensors file.
struct Field {
    name: String,
    kind: Kind,
    shape: Vec<i64>,
    bytes: Vec<u8>,
}

impl Field {
    fn to_f32(&self) -> Result<Vec<f32>> {
        Ok(match self.kind {
            Kind::Float => self.bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
            // bf16 is the upper half of an f32.
            Kind::BFloat16 => self.bytes.chunks_exact(2).map(|b| f32::from_bits((u16::from_le_bytes([b[0], b[1]]) as u32) << 16)).collect(),
            Kind::Double => self.bytes.chunks_exact(8).map(|b| f64::from_le_bytes(b.try_into().unwrap_or_default()) as f32).collect(),
            k => bail!("'{}' is {k:?}; expected f32, bf16 or f64", self.name),
        })
    }
}

/// Where one tensor of a safetensors file lies.
struct Slot {
    kind: Kind,
    shape: Vec<i64>,
    /// Byte range within the data section.
    start: u64,
    end: u64,
}

/// Reads single rows (index along the first dimension) of a safetensors file's tensors without
/// reading the rest of the file.
struct ShardReader {
    path: PathBuf,
    file: std::fs::File,
    slots: BTreeMap<String, Slot>,
    data_start: u64,
}

impl ShardReader {
    fn open(path: &Path) -> Result<Self> {
        let mut file = std::fs::File::open(path).with_context(|| format!("opening shard {}", path.display()))?;
        let mut len = [0u8; 8];
        file.read_exact(&mut len).with_context(|| format!("{}: reading the safetensors header", path.display()))?;
        let n = u64::from_le_bytes(len);
        let file_len = file.metadata()?.len();
        ensure!(n < file_len && n <= 100 << 20, "{}: safetensors header of {n} bytes in a file of {file_len}", path.display());
        let mut header = vec![0u8; n as usize];
        file.read_exact(&mut header).with_context(|| format!("{}: reading the safetensors header", path.display()))?;
        let entries: BTreeMap<String, serde_json::Value> =
            serde_json::from_slice(&header).with_context(|| format!("{}: parsing the safetensors header", path.display()))?;
        let mut slots = BTreeMap::new();
        for (name, v) in entries {
            if name == "__metadata__" {
                continue;
            }
            let dtype = v.get("dtype").and_then(|d| d.as_str()).unwrap_or_default();
            let kind = match dtype {
                "BF16" => Kind::BFloat16,
                "F16" => Kind::Half,
                "F32" => Kind::Float,
                "F64" => Kind::Double,
                "U8" => Kind::Uint8,
                "I64" => Kind::Int64,
                "I32" => Kind::Int,
                other => bail!("{}: tensor '{name}' has dtype '{other}', which the cache does not use", path.display()),
            };
            let shape: Vec<i64> = serde_json::from_value(v.get("shape").cloned().unwrap_or_default())
                .with_context(|| format!("{}: tensor '{name}': shape", path.display()))?;
            let [start, end]: [u64; 2] = serde_json::from_value(v.get("data_offsets").cloned().unwrap_or_default())
                .with_context(|| format!("{}: tensor '{name}': data_offsets", path.display()))?;
            let bytes = shape.iter().product::<i64>() as u64 * kind.elt_size_in_bytes() as u64;
            ensure!(end >= start && end - start == bytes && 8 + n + end <= file_len, "{}: tensor '{name}' does not fit its byte range", path.display());
            slots.insert(name, Slot { kind, shape, start, end });
        }
        Ok(Self { path: path.to_path_buf(), file, slots, data_start: 8 + n })
    }

    /// Row `row` of tensor `name` (the whole tensor when `row` is None), or None when the file
    /// has no such tensor.
    fn read(&mut self, name: &str, row: Option<usize>) -> Result<Option<Field>> {
        let Some(slot) = self.slots.get(name) else { return Ok(None) };
        let path = self.path.display();
        let (offset, len, shape) = match row {
            None => (0, slot.end - slot.start, slot.shape.clone()),
            Some(row) => {
                ensure!(!slot.shape.is_empty() && (row as i64) < slot.shape[0], "{path}: tensor '{name}' of shape {:?} has no row {row}", slot.shape);
                let row_bytes = (slot.end - slot.start) / slot.shape[0] as u64;
                (row as u64 * row_bytes, row_bytes, slot.shape[1..].to_vec())
            }
        };
        let mut bytes = vec![0u8; len as usize];
        self.file.seek(SeekFrom::Start(self.data_start + slot.start + offset))?;
        self.file.read_exact(&mut bytes).with_context(|| format!("{path}: reading '{name}'"))?;
        Ok(Some(Field { name: name.to_string(), kind: slot.kind, shape, bytes }))
    }
}

/// One clip for a shard, on any device and of any float kind; no latents in a raw cache.
pub struct ShardClip {
    pub entry: ClipEntry,
    pub latents: Option<Tensor>,
    pub actions: Tensor,
    pub frames: Option<Tensor>,
}

pub fn shard_file_name(shard: usize) -> String {
    format!("shard-{shard:05}.safetensors")
}

/// Checks a clip's tensors against the index.
fn check_clip(index: &CacheIndex, c: &ShardClip) -> Result<()> {
    match (&c.latents, index.has_latents) {
        (Some(l), true) => ensure!(l.size() == index.latent_shape, "latents {:?} do not match the cache's {:?}", l.size(), index.latent_shape),
        (None, false) => ensure!(index.has_frames, "a cache of raw clips must keep the pixel frames"),
        (Some(_), false) => bail!("a cache of raw clips takes no latents"),
        (None, true) => bail!("a clip of episode {} has no latents", c.entry.episode),
    }
    ensure!(
        c.actions.size() == index.action_shape(),
        "actions {:?} do not match [{}, {}]",
        c.actions.size(),
        index.pixel_frames,
        index.action_dim
    );
    ensure!(c.entry.frames.len() == index.pixel_frames, "the clip lists {} frame ids, the cache has {} pixel frames", c.entry.frames.len(), index.pixel_frames);
    if index.has_frames {
        let Some(f) = &c.frames else { bail!("this cache keeps pixel frames; a clip of episode {} has none", c.entry.episode) };
        ensure!(f.size() == index.frame_shape(), "pixel frames {:?} do not match {:?}", f.size(), index.frame_shape());
    }
    Ok(())
}

/// Writes `clips` as the shard `dir/name` (see the module doc), whole or not at all: a temporary
/// file of this process, fsynced, then renamed. Returns the clips' index entries.
pub fn write_shard(dir: &Path, index: &CacheIndex, name: &str, clips: &[ShardClip]) -> Result<Vec<ClipEntry>> {
    ensure!(!clips.is_empty(), "shard {name}: no clips");
    for c in clips {
        check_clip(index, c).with_context(|| format!("shard {name}"))?;
    }
    let cpu = |t: &Tensor, kind: Kind| t.to_device(Device::Cpu).to_kind(kind);
    let stack = |f: &dyn Fn(&ShardClip) -> Tensor| Tensor::stack(&clips.iter().map(f).collect::<Vec<_>>(), 0).contiguous();
    let episodes: Vec<i64> = clips.iter().map(|c| c.entry.episode).collect();
    let frame_ids: Vec<i64> = clips.iter().flat_map(|c| c.entry.frames.iter().map(|&f| f as i64)).collect();
    let mut tensors = vec![
        ("actions".to_string(), stack(&|c| cpu(&c.actions, Kind::Float))),
        ("episode".to_string(), Tensor::from_slice(&episodes)),
        ("frame_ids".to_string(), Tensor::from_slice(&frame_ids).view([clips.len() as i64, index.pixel_frames as i64])),
    ];
    if index.has_latents {
        let latents = clips.iter().map(|c| c.latents.as_ref().map(|l| cpu(l, Kind::BFloat16)).context("a clip has no latents")).collect::<Result<Vec<_>>>()?;
        tensors.push(("latents".to_string(), Tensor::stack(&latents, 0).contiguous()));
    }
    if index.has_frames {
        let frames = clips.iter().map(|c| c.frames.as_ref().map(|f| cpu(f, Kind::Uint8)).context("a clip has no pixel frames")).collect::<Result<Vec<_>>>()?;
        tensors.push(("frames".to_string(), Tensor::stack(&frames, 0).contiguous()));
    }
    let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    let written = (|| -> Result<()> {
        Tensor::write_safetensors(&tensors, &tmp)?;
        std::fs::File::open(&tmp)?.sync_all()?;
        std::fs::rename(&tmp, dir.join(name))?;
        Ok(())
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(e.context(format!("writing shard {}", dir.join(name).display())));
    }
    sync_dir(dir);
    Ok(clips.iter().map(|c| ClipEntry { file: name.to_string(), ..c.entry.clone() }).collect())
}

/// Writes a cache in one process: clips are buffered into shards of `clips_per_shard`, each
/// written whole (`write_shard`); the index comes last, so a cache with an index is complete.
pub struct CacheWriter {
    dir: PathBuf,
    index: CacheIndex,
    pub extras: IndexExtras,
    clips_per_shard: usize,
    /// Files named `clip-NNNNNN.safetensors` after their clip (one clip per file), as in
    /// version 1, instead of `shard-NNNNN.safetensors`.
    clip_names: bool,
    pending: Vec<ShardClip>,
    shards: usize,
}

impl CacheWriter {
    /// One clip per file, named after the clip as version 1 named its files (small synthetic
    /// caches whose files are addressed by clip); `with_shard_size` for shards.
    pub fn create(dir: &Path, index: CacheIndex) -> Result<Self> {
        let mut w = Self::with_shard_size(dir, index, 1)?;
        w.clip_names = true;
        Ok(w)
    }

    pub fn with_shard_size(dir: &Path, mut index: CacheIndex, clips_per_shard: usize) -> Result<Self> {
        ensure!(clips_per_shard > 0, "clips per shard must be positive");
        if dir.join(INDEX_FILE).exists() {
            std::fs::remove_file(dir.join(INDEX_FILE)).with_context(|| format!("replacing the cache in {}", dir.display()))?;
        }
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        index.version = CACHE_VERSION;
        index.clips.clear();
        let extras = IndexExtras { clips_per_shard: Some(clips_per_shard), ..Default::default() };
        Ok(Self { dir: dir.to_path_buf(), index, extras, clips_per_shard, clip_names: false, pending: Vec::new(), shards: 0 })
    }

    pub fn add(&mut self, entry: ClipEntry, latents: &Tensor, actions: &Tensor, frames: Option<&Tensor>) -> Result<()> {
        let clip = ShardClip { entry, latents: Some(latents.shallow_clone()), actions: actions.shallow_clone(), frames: frames.map(Tensor::shallow_clone) };
        check_clip(&self.index, &clip).with_context(|| format!("clip {}", self.index.clips.len() + self.pending.len()))?;
        self.pending.push(clip);
        if self.pending.len() == self.clips_per_shard {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<()> {
        if self.pending.is_empty() {
            return Ok(());
        }
        let name = if self.clip_names { format!("clip-{:06}.safetensors", self.index.clips.len()) } else { shard_file_name(self.shards) };
        let entries = write_shard(&self.dir, &self.index, &name, &self.pending)?;
        self.index.clips.extend(entries);
        self.shards += 1;
        self.pending.clear();
        Ok(())
    }

    pub fn finish(mut self) -> Result<CacheIndex> {
        self.flush()?;
        ensure!(!self.index.clips.is_empty(), "no clips were written");
        write_index(&self.dir, INDEX_FILE, &self.index, &self.extras)?;
        Ok(self.index)
    }
}

/// Which clip global sample `index` reads, among `n` training clips.
pub fn clip_for_sample(seed: u64, index: u64, n: usize) -> usize {
    let epoch = index / n as u64;
    permutation(seed, epoch, n)[(index % n as u64) as usize]
}

/// A permutation of 0..n keyed by (seed, epoch): Fisher-Yates over a splitmix64 stream.
pub fn permutation(seed: u64, epoch: u64, n: usize) -> Vec<usize> {
    let mut state = seed ^ epoch.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xD1B5_4A32_D192_ED03;
    let mut next = move || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let mut p: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        let j = (next() % (i as u64 + 1)) as usize;
        p.swap(i, j);
    }
    p
}

/// Global sample index of item `item` of micro-step `micro` on `rank`, for optimizer step
/// `step`: one global batch = grad_accum x world x micro_batch samples, laid out micro-step
/// major, then rank, then item, so batch 2 == batch 1 x accumulation 2 == 2 ranks x batch 1.
pub fn global_sample_index(step: u64, micro: usize, rank: usize, item: usize, micro_batch: usize, grad_accum: usize, world: usize) -> u64 {
    let global_batch = (micro_batch * grad_accum * world) as u64;
    step * global_batch + ((micro * world + rank) * micro_batch + item) as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn permutations_cover_every_clip_and_change_per_epoch() {
        let a = permutation(3, 0, 10);
        let mut s = a.clone();
        s.sort();
        assert_eq!(s, (0..10).collect::<Vec<_>>());
        assert_ne!(a, permutation(3, 1, 10));
        assert_eq!(a, permutation(3, 0, 10));
        assert_eq!(clip_for_sample(3, 12, 10), permutation(3, 1, 10)[2]);
    }

    #[test]
    fn sample_layout_is_the_same_for_batch_accumulation_and_ranks() {
        let batch2: Vec<u64> = (0..2).map(|b| global_sample_index(5, 0, 0, b, 2, 1, 1)).collect();
        let accum2: Vec<u64> = (0..2).map(|m| global_sample_index(5, m, 0, 0, 1, 2, 1)).collect();
        let ranks2: Vec<u64> = (0..2).map(|r| global_sample_index(5, 0, r, 0, 1, 1, 2)).collect();
        assert_eq!(batch2, vec![10, 11]);
        assert_eq!(batch2, accum2);
        assert_eq!(batch2, ranks2);
    }

    fn tmp(tag: &str) -> bwm_testdir::TestDir {
        bwm_testdir::TestDir::new(tag)
    }

    fn index(has_frames: bool) -> CacheIndex {
        CacheIndex { has_frames, ..CacheIndex::new(vec![4, 2, 2, 3], 2, 0, 4, [48, 32], 10.0, "test") }
    }

    #[test]
    fn shards_round_trip_row_by_row_with_bf16_latents() {
        let dir = tmp("shards");
        let mut w = CacheWriter::with_shard_size(&dir, index(true), 2).unwrap();
        let mut written = Vec::new();
        for i in 0..5i64 {
            let latents = Tensor::randn([4, 2, 2, 3], (Kind::Float, Device::Cpu)) * 3.0;
            let actions = Tensor::rand([5, 2], (Kind::Float, Device::Cpu));
            let frames = Tensor::randint(256, [3, 5, 32, 48], (Kind::Uint8, Device::Cpu));
            let entry = ClipEntry { file: String::new(), episode: i / 2, frames: vec![0, 1, 2, 3, 4 + i as usize], task: "t".into() };
            w.add(entry, &latents, &actions, Some(&frames)).unwrap();
            written.push((latents, actions, frames));
        }
        let bad = Tensor::zeros([4, 2, 2, 2], (Kind::Float, Device::Cpu));
        assert!(w.add(ClipEntry { file: String::new(), episode: 9, frames: vec![0; 5], task: String::new() }, &bad, &written[0].1, Some(&written[0].2)).is_err());
        let idx = w.finish().unwrap();
        assert_eq!(idx.version, CACHE_VERSION);
        let files: Vec<&str> = idx.clips.iter().map(|c| c.file.as_str()).collect();
        assert_eq!(files, ["shard-00000.safetensors", "shard-00000.safetensors", "shard-00001.safetensors", "shard-00001.safetensors", "shard-00002.safetensors"]);
        let cache = LatentCache::open(&dir).unwrap();
        assert_eq!(cache.extras.clips_per_shard, Some(2));
        for (i, (l, a, f)) in written.iter().enumerate() {
            let c = cache.load(i, Device::Cpu).unwrap();
            assert_eq!(c.latents.kind(), Kind::Float);
            assert!(c.latents.equal(&l.to_kind(Kind::BFloat16).to_kind(Kind::Float)), "clip {i}: latents are the bf16 rounding of what was written");
            let rel = (&c.latents - l).abs().max().double_value(&[]) / l.abs().max().double_value(&[]);
            assert!(rel <= 1.0 / 256.0, "clip {i}: {rel}");
            assert!(c.actions.equal(a), "clip {i}: actions are stored in f32");
            assert!(c.frames.unwrap().equal(f), "clip {i}: frames");
            let v = cache.load_values(i).unwrap();
            assert_eq!(v.latents, Vec::<f32>::try_from(c.latents.view([-1])).unwrap());
            assert_eq!(v.actions, Vec::<f32>::try_from(c.actions.view([-1])).unwrap());
        }
        let shard = Tensor::read_safetensors(dir.join("shard-00001.safetensors")).unwrap();
        let get = |n: &str| shard.iter().find(|(k, _)| k == n).unwrap().1.shallow_clone();
        assert_eq!(Vec::<i64>::try_from(get("episode")).unwrap(), [1, 1]);
        assert_eq!(Vec::<i64>::try_from(get("frame_ids").narrow(0, 1, 1).view([-1])).unwrap(), [0, 1, 2, 3, 7]);
        assert_eq!(get("latents").kind(), Kind::BFloat16);
        assert!(cache.load(5, Device::Cpu).is_err());
        assert!(!dir.read_dir().unwrap().any(|e| e.unwrap().file_name().to_string_lossy().ends_with(".tmp")));
    }

    #[test]
    fn an_index_whose_frame_counts_disagree_is_refused() {
        let dir = tmp("frame-counts");
        let mut idx = index(false);
        idx.clips.push(ClipEntry { file: "shard-00000.safetensors".into(), episode: 0, frames: vec![0; 5], task: String::new() });
        for (bad, said) in [
            (CacheIndex { pixel_frames: 9, ..idx.clone() }, "pixel_frames 9 must be 1 (x0) + history_frames 0 + future_frames 4"),
            (CacheIndex { latent_shape: vec![4, 0, 2, 3], ..idx.clone() }, "latent_shape [4, 0, 2, 3] must be [C, F, h, w] of positive sizes"),
        ] {
            std::fs::write(dir.join(INDEX_FILE), serde_json::to_string(&bad).unwrap()).unwrap();
            let e = LatentCache::open(&dir).err().expect("a bad index opened").to_string();
            assert!(e.contains(said), "{e}");
        }
    }

    #[test]
    fn version_1_caches_and_indexes_without_extras_still_load() {
        let dir = tmp("v1");
        let latents = Tensor::randn([4, 2, 2, 3], (Kind::Float, Device::Cpu));
        let actions = Tensor::rand([5, 2], (Kind::Float, Device::Cpu));
        Tensor::write_safetensors(&[("latents", &latents), ("actions", &actions)], dir.join("clip-000000.safetensors")).unwrap();
        let mut idx = CacheIndex { version: 1, ..index(false) };
        idx.clips.push(ClipEntry { file: "clip-000000.safetensors".into(), episode: 0, frames: vec![0; 5], task: String::new() });
        std::fs::write(dir.join(INDEX_FILE), serde_json::to_string(&idx).unwrap()).unwrap();
        let cache = LatentCache::open(&dir).unwrap();
        assert_eq!(cache.extras, IndexExtras::default());
        let c = cache.load(0, Device::Cpu).unwrap();
        assert!(c.latents.equal(&latents) && c.actions.equal(&actions));
        assert_eq!(cache.load_values(0).unwrap().latents, Vec::<f32>::try_from(latents.view([-1])).unwrap());

        // Extras sit next to the index's fields and come back; an unknown key is an error.
        let extras = IndexExtras {
            source_resolution: vec![[640, 480]],
            plan_hash: Some("abc".into()),
            plan: Some(serde_json::json!({"stride": 8})),
            clips_per_shard: Some(3),
        };
        let mut keys: Vec<String> = serde_json::to_value(&extras).unwrap().as_object().unwrap().keys().cloned().collect();
        keys.sort();
        let mut expected: Vec<String> = IndexExtras::KEYS.iter().map(|k| k.to_string()).collect();
        expected.sort();
        assert_eq!(keys, expected, "IndexExtras::KEYS lists every field");
        write_index(&dir, INDEX_FILE, &idx, &extras).unwrap();
        assert_eq!(read_index(&dir.join(INDEX_FILE)).unwrap(), (idx.clone(), extras));
        let text = std::fs::read_to_string(dir.join(INDEX_FILE)).unwrap().replacen("\"fps\"", "\"fsp\": 1, \"fps\"", 1);
        std::fs::write(dir.join(INDEX_FILE), text).unwrap();
        assert!(LatentCache::open(&dir).is_err());
    }

    #[test]
    fn index_entries_that_leave_the_cache_folder_are_refused() {
        let dir = tmp("escape");
        let cache = dir.join("cache");
        let mut w = CacheWriter::create(&cache, index(false)).unwrap();
        let entry = ClipEntry { file: String::new(), episode: 0, frames: vec![0; 5], task: String::new() };
        w.add(entry, &Tensor::zeros([4, 2, 2, 3], (Kind::Float, Device::Cpu)), &Tensor::zeros([5, 2], (Kind::Float, Device::Cpu)), None).unwrap();
        w.finish().unwrap();
        // The shard moved out of the cache folder; index entries naming it there are refused.
        let (mut idx, extras) = read_index(&cache.join(INDEX_FILE)).unwrap();
        let outside = dir.join("shard.safetensors");
        std::fs::rename(cache.join(&idx.clips[0].file), &outside).unwrap();
        for file in ["../shard.safetensors".to_string(), outside.display().to_string(), format!("sub/../../{}", "shard.safetensors")] {
            idx.clips[0].file = file.clone();
            write_index(&cache, INDEX_FILE, &idx, &extras).unwrap();
            let e = format!("{:#}", LatentCache::open(&cache).err().unwrap_or_else(|| panic!("{file}: accepted")));
            assert!(e.contains(&file) && e.contains("inside the cache folder"), "{e}");
        }
    }
}
