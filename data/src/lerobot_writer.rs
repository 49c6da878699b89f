//! Writes a LeRobotDataset v2.1 (what policy trainers read): one parquet per episode with
//! `action`, `observation.state`, `timestamp`, `frame_index`, `episode_index`, `index`,
//! `task_index`, the camera's frames as one mp4 per episode (a `video` feature) or as PNG cells in
//! the parquet (an `image` feature, for builds without video), and `meta/{info.json,
//! episodes.jsonl, tasks.jsonl, episodes_stats.jsonl}`. Each episode's files are written under temporary names
//! and renamed when complete (the parquet and the metadata fsynced before the rename, their folder
//! after it), and the metadata is rewritten after every episode, so an interrupted run (a crash of
//! the machine too) leaves a readable dataset of the finished episodes that `resume` continues.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, ensure, Context, Result};
use arrow_array::builder::{FixedSizeListBuilder, Float32Builder};
use arrow_array::{ArrayRef, BinaryArray, Float32Array, Int64Array, RecordBatch, StringArray, StructArray};
use arrow_schema::{DataType, Field};
use image::RgbImage;
use serde_json::{json, Value};

use crate::video;

pub const CODEBASE_VERSION: &str = "v2.1";
const CHUNKS_SIZE: usize = 1000;
const DATA_PATH: &str = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet";
const VIDEO_PATH: &str = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4";

/// Names of the vector features' dimensions (LeRobot's `names`).
#[derive(Debug, Clone)]
pub struct DatasetFeatures {
    pub action_names: Vec<String>,
    pub state_names: Vec<String>,
    /// e.g. `observation.images.head`.
    pub video_key: String,
    /// Frame width and height.
    pub size: (u32, u32),
    pub fps: f64,
    pub robot_type: String,
    /// How the frames are stored; unset: as the dataset being resumed stores them, else
    /// `FrameStorage::default_for_build`.
    pub storage: Option<FrameStorage>,
}

/// How a dataset stores its camera's frames (LeRobot's feature dtypes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameStorage {
    /// One mp4 per episode (dtype `video`), what LeRobot's own recordings use.
    Video,
    /// Each frame a PNG cell `{bytes, path}` in the episode's parquet (dtype `image`): larger,
    /// lossless, and written by builds without video.
    Image,
}

impl FrameStorage {
    /// Video where this build encodes it, PNG cells otherwise.
    pub fn default_for_build() -> Self {
        if video::AVAILABLE {
            FrameStorage::Video
        } else {
            FrameStorage::Image
        }
    }

    /// LeRobot's dtype for it.
    pub fn dtype(self) -> &'static str {
        match self {
            FrameStorage::Video => "video",
            FrameStorage::Image => "image",
        }
    }
}

impl std::str::FromStr for FrameStorage {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "video" => Ok(FrameStorage::Video),
            "image" => Ok(FrameStorage::Image),
            _ => Err(format!("'{s}': expected video (mp4 files) or image (PNG cells in the parquet)")),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct EpisodeMeta {
    index: usize,
    length: usize,
    task: String,
}

pub struct LeRobotWriter {
    root: PathBuf,
    features: DatasetFeatures,
    episodes: Vec<EpisodeMeta>,
    tasks: Vec<String>,
    stats_lines: Vec<String>,
    storage: FrameStorage,
    /// The mp4 codec (video storage only).
    codec: Option<&'static str>,
}

impl LeRobotWriter {
    /// A new dataset at `root`, which must not hold one already (see `resume`).
    pub fn create(root: &Path, features: DatasetFeatures) -> Result<Self> {
        ensure!(
            !root.join("meta/info.json").exists(),
            "{} already holds a dataset; continue it (resume) or pick another output folder",
            root.display()
        );
        Self::check(&features)?;
        let storage = features.storage.unwrap_or_else(FrameStorage::default_for_build);
        let codec = Self::codec(storage)?;
        std::fs::create_dir_all(root.join("meta")).with_context(|| format!("creating {}", root.display()))?;
        Ok(Self { root: root.to_path_buf(), features, episodes: Vec::new(), tasks: Vec::new(), stats_lines: Vec::new(), storage, codec })
    }

    fn codec(storage: FrameStorage) -> Result<Option<&'static str>> {
        match storage {
            FrameStorage::Image => Ok(None),
            FrameStorage::Video if !video::AVAILABLE => {
                bail!("this build has no video (FFmpeg): store the frames as PNG cells in the parquet (image storage) or rebuild with the `video` feature")
            }
            FrameStorage::Video => Ok(Some(codec_name(video::Mp4Encoder::best()?))),
        }
    }

    /// Continues a dataset this writer started: the episodes listed in its metadata are kept,
    /// anything else under `root` (an episode cut short) is overwritten when written again.
    pub fn resume(root: &Path, features: DatasetFeatures) -> Result<Self> {
        if !root.join("meta/info.json").exists() {
            return Self::create(root, features);
        }
        Self::check(&features)?;
        let read = |name: &str| -> Result<Vec<Value>> {
            let path = root.join("meta").join(name);
            let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
            text.lines().filter(|l| !l.trim().is_empty()).map(|l| serde_json::from_str(l).with_context(|| format!("{}: bad line", path.display()))).collect()
        };
        let info: Value = serde_json::from_str(&std::fs::read_to_string(root.join("meta/info.json"))?).context("meta/info.json")?;
        let feature = &info["features"][&features.video_key];
        let stored = match feature["dtype"].as_str() {
            Some("video") => FrameStorage::Video,
            Some("image") => FrameStorage::Image,
            _ => bail!("{}: no video or image feature '{}' in meta/info.json", root.display(), features.video_key),
        };
        if let Some(asked) = features.storage {
            ensure!(
                asked == stored,
                "{}: its frames are stored as {} features, this run asks for {}",
                root.display(),
                stored.dtype(),
                asked.dtype()
            );
        }
        let shape = &feature["shape"];
        ensure!(
            shape == &json!([features.size.1, features.size.0, 3]),
            "{}: its frames are {shape}, this run makes {}x{} (HxW) frames",
            root.display(),
            features.size.1,
            features.size.0
        );
        // The episodes written so far are relabelled by the metadata this run writes: their actions'
        // meaning and frame rate must be this run's.
        let fps = info["fps"].as_f64();
        ensure!(
            fps == Some(features.fps),
            "{}: its episodes are at {} fps, this run writes {} fps",
            root.display(),
            fps.map_or("unknown".into(), |f| f.to_string()),
            features.fps
        );
        for (key, asked) in [("action", &features.action_names), ("observation.state", &features.state_names)] {
            let stored = &info["features"][key]["names"];
            ensure!(
                stored == &json!(asked),
                "{}: its '{key}' values are {stored}, this run writes {}",
                root.display(),
                json!(asked)
            );
        }
        let tasks: Vec<String> = read("tasks.jsonl")?.iter().map(|t| t["task"].as_str().unwrap_or_default().to_string()).collect();
        let episodes = read("episodes.jsonl")?
            .iter()
            .enumerate()
            .map(|(i, e)| {
                let task = e["tasks"].get(0).and_then(Value::as_str).unwrap_or_default().to_string();
                let length = e["length"].as_u64().with_context(|| format!("episodes.jsonl line {}: no length", i + 1))? as usize;
                Ok(EpisodeMeta { index: i, length, task })
            })
            .collect::<Result<Vec<_>>>()?;
        let stats_lines = std::fs::read_to_string(root.join("meta/episodes_stats.jsonl"))
            .unwrap_or_default()
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(str::to_string)
            .take(episodes.len())
            .collect();
        let codec = Self::codec(stored)?;
        Ok(Self { root: root.to_path_buf(), features, episodes, tasks, stats_lines, storage: stored, codec })
    }

    fn check(f: &DatasetFeatures) -> Result<()> {
        ensure!(f.fps.is_finite() && f.fps > 0.0, "frame rate {} is not a positive number", f.fps);
        ensure!(!f.action_names.is_empty(), "no action dimensions");
        ensure!(f.size.0 > 0 && f.size.1 > 0 && f.size.0 % 2 == 0 && f.size.1 % 2 == 0, "frame size {:?} must be even", f.size);
        ensure!(!f.video_key.is_empty(), "empty video key");
        Ok(())
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// How this dataset stores its frames.
    pub fn storage(&self) -> FrameStorage {
        self.storage
    }

    /// Episodes already in the dataset.
    pub fn len(&self) -> usize {
        self.episodes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.episodes.is_empty()
    }

    /// Appends one episode: `frames[t]` was shown while `actions[t]` was applied and the robot was
    /// in `states[t]`.
    pub fn add_episode(&mut self, frames: &[RgbImage], actions: &[Vec<f32>], states: &[Vec<f32>], task: &str) -> Result<usize> {
        let n = frames.len();
        ensure!(n > 0, "an episode needs at least one frame");
        ensure!(actions.len() == n && states.len() == n, "{n} frames but {} actions and {} states", actions.len(), states.len());
        let (da, ds) = (self.features.action_names.len(), self.features.state_names.len());
        if let Some((t, _)) = actions.iter().enumerate().find(|(_, a)| a.len() != da) {
            bail!("action row {t} has {} values, the dataset declares {da}", actions[t].len());
        }
        if let Some((t, _)) = states.iter().enumerate().find(|(_, s)| s.len() != ds) {
            bail!("state row {t} has {} values, the dataset declares {ds}", states[t].len());
        }
        let (w, h) = self.features.size;
        if let Some((t, f)) = frames.iter().enumerate().find(|(_, f)| f.dimensions() != (w, h)) {
            bail!("frame {t} is {}x{}, the dataset's frames are {w}x{h}", f.width(), f.height());
        }
        let episode = self.episodes.len();
        let task_index = match self.tasks.iter().position(|t| t == task) {
            Some(i) => i,
            None => {
                self.tasks.push(task.to_string());
                self.tasks.len() - 1
            }
        };
        let first_index: usize = self.episodes.iter().map(|e| e.length).sum();
        let fps = self.features.fps;

        let data = self.root.join(fill(DATA_PATH, episode, None));
        std::fs::create_dir_all(data.parent().expect("templated paths have folders"))?;
        let mut columns: Vec<(&str, ArrayRef)> = Vec::new();
        match self.storage {
            FrameStorage::Video => {
                let video_path = self.root.join(fill(VIDEO_PATH, episode, Some(&self.features.video_key)));
                std::fs::create_dir_all(video_path.parent().expect("templated paths have folders"))?;
                video::write_mp4(&video_path, frames, fps)?;
            }
            FrameStorage::Image => columns.push((self.features.video_key.as_str(), png_cells(frames)?)),
        }
        columns.extend([
            ("action", vectors(actions, da)?),
            ("observation.state", vectors(states, ds)?),
            ("timestamp", Arc::new(Float32Array::from_iter_values((0..n).map(|t| (t as f64 / fps) as f32))) as ArrayRef),
            ("frame_index", int_column((0..n).map(|t| t as i64))),
            ("episode_index", int_column((0..n).map(|_| episode as i64))),
            ("index", int_column((0..n).map(|t| (first_index + t) as i64))),
            ("task_index", int_column((0..n).map(|_| task_index as i64))),
        ]);
        let batch = RecordBatch::try_from_iter(columns)?;
        write_parquet(&data, &batch)?;

        self.stats_lines.push(
            json!({
                "episode_index": episode,
                "stats": {
                    "action": vector_stats(actions),
                    "observation.state": vector_stats(states),
                    "frame_index": scalar_stats((0..n).map(|t| t as f64)),
                    "timestamp": scalar_stats((0..n).map(|t| t as f64 / fps)),
                    "episode_index": scalar_stats((0..n).map(|_| episode as f64)),
                    "index": scalar_stats((0..n).map(|t| (first_index + t) as f64)),
                    "task_index": scalar_stats((0..n).map(|_| task_index as f64)),
                    self.features.video_key.clone(): image_stats(frames),
                }
            })
            .to_string(),
        );
        self.episodes.push(EpisodeMeta { index: episode, length: n, task: task.to_string() });
        self.write_meta()?;
        Ok(episode)
    }

    fn write_meta(&self) -> Result<()> {
        let f = &self.features;
        let names = |v: &[String]| json!({ "dtype": "float32", "shape": [v.len()], "names": v });
        let scalar = |dtype: &str| json!({ "dtype": dtype, "shape": [1], "names": null });
        let total_frames: usize = self.episodes.iter().map(|e| e.length).sum();
        let mut camera = json!({
            "dtype": self.storage.dtype(),
            "shape": [f.size.1, f.size.0, 3],
            "names": ["height", "width", "channels"],
        });
        if let Some(codec) = self.codec {
            camera["info"] = json!({
                "video.height": f.size.1, "video.width": f.size.0, "video.codec": codec,
                "video.pix_fmt": "yuv420p", "video.is_depth_map": false, "video.fps": f.fps,
                "video.channels": 3, "has_audio": false
            });
        }
        let info = json!({
            "codebase_version": CODEBASE_VERSION,
            "robot_type": f.robot_type,
            "total_episodes": self.episodes.len(),
            "total_frames": total_frames,
            "total_tasks": self.tasks.len(),
            "total_videos": if self.storage == FrameStorage::Video { self.episodes.len() } else { 0 },
            "total_chunks": self.episodes.len().div_ceil(CHUNKS_SIZE),
            "chunks_size": CHUNKS_SIZE,
            "fps": f.fps,
            "splits": { "train": format!("0:{}", self.episodes.len()) },
            "data_path": DATA_PATH,
            "video_path": if self.storage == FrameStorage::Video { json!(VIDEO_PATH) } else { Value::Null },
            "features": {
                "action": names(&f.action_names),
                "observation.state": names(&f.state_names),
                f.video_key.clone(): camera,
                "timestamp": scalar("float32"),
                "frame_index": scalar("int64"),
                "episode_index": scalar("int64"),
                "index": scalar("int64"),
                "task_index": scalar("int64"),
            }
        });
        let lines = |items: Vec<String>| items.into_iter().map(|l| l + "\n").collect::<String>();
        let episodes = lines(self.episodes.iter().map(|e| json!({"episode_index": e.index, "tasks": [e.task], "length": e.length}).to_string()).collect());
        let tasks = lines(self.tasks.iter().enumerate().map(|(i, t)| json!({"task_index": i, "task": t}).to_string()).collect());
        let meta = self.root.join("meta");
        // info.json last: a reader that finds it finds the episode lists it counts.
        write_atomic(&meta.join("tasks.jsonl"), tasks.as_bytes())?;
        write_atomic(&meta.join("episodes_stats.jsonl"), lines(self.stats_lines.clone()).as_bytes())?;
        write_atomic(&meta.join("episodes.jsonl"), episodes.as_bytes())?;
        write_atomic(&meta.join("info.json"), serde_json::to_string_pretty(&info)?.as_bytes())
    }
}

fn codec_name(e: video::Mp4Encoder) -> &'static str {
    match e {
        video::Mp4Encoder::H264 => "h264",
        video::Mp4Encoder::Mpeg4 => "mpeg4",
    }
}

/// LeRobot's path templates with the values of one episode.
fn fill(template: &str, episode: usize, video_key: Option<&str>) -> String {
    let s = template
        .replace("{episode_chunk:03d}", &format!("{:03}", episode / CHUNKS_SIZE))
        .replace("{episode_index:06d}", &format!("{episode:06}"));
    match video_key {
        Some(k) => s.replace("{video_key}", k),
        None => s,
    }
}

/// Fixed-size float lists: Hugging Face `datasets.Sequence(length=d)`, as LeRobot declares them.
fn vectors(rows: &[Vec<f32>], d: usize) -> Result<ArrayRef> {
    let mut b = FixedSizeListBuilder::new(Float32Builder::new(), i32::try_from(d)?);
    for r in rows {
        b.values().append_slice(r);
        b.append(true);
    }
    Ok(Arc::new(b.finish()))
}

/// Frames as Hugging Face `datasets.Image` cells: structs of PNG `bytes` and a null `path`.
fn png_cells(frames: &[RgbImage]) -> Result<ArrayRef> {
    let mut encoded = Vec::with_capacity(frames.len());
    for (t, frame) in frames.iter().enumerate() {
        let mut bytes = std::io::Cursor::new(Vec::new());
        frame.write_to(&mut bytes, image::ImageFormat::Png).with_context(|| format!("encoding frame {t} as PNG"))?;
        encoded.push(bytes.into_inner());
    }
    let bytes: ArrayRef = Arc::new(BinaryArray::from_iter_values(encoded.iter()));
    let paths: ArrayRef = Arc::new(StringArray::new_null(frames.len()));
    Ok(Arc::new(StructArray::from(vec![
        (Arc::new(Field::new("bytes", DataType::Binary, true)), bytes),
        (Arc::new(Field::new("path", DataType::Utf8, true)), paths),
    ])))
}

fn int_column(v: impl Iterator<Item = i64>) -> ArrayRef {
    Arc::new(Int64Array::from_iter_values(v))
}

/// Writes the episode's parquet under a temporary name, fsynced, then renamed into place and the
/// rename made durable: a crash leaves the complete file or none.
fn write_parquet(path: &Path, batch: &RecordBatch) -> Result<()> {
    let tmp = path.with_extension("parquet.tmp");
    let write = || -> Result<()> {
        let file = std::fs::File::create(&tmp)?;
        let mut w = parquet::arrow::ArrowWriter::try_new(file, batch.schema(), None)?;
        w.write(batch)?;
        w.close()?;
        std::fs::File::open(&tmp)?.sync_all()?;
        std::fs::rename(&tmp, path)?;
        crate::latent_cache::sync_dir(path.parent().context("a file path has a folder")?);
        Ok(())
    };
    write().with_context(|| format!("writing {}", path.display()))
}

/// Writes a metadata file whole or not at all (temporary file, fsync, rename, folder synced).
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let (dir, name) = (path.parent().context("a file path has a folder")?, path.file_name().context("a file path has a name")?);
    crate::latent_cache::write_atomically(dir, &name.to_string_lossy(), bytes)
}

fn moments(values: impl Iterator<Item = f64>) -> (f64, f64, f64, f64, usize) {
    let (mut min, mut max, mut sum, mut sq, mut n) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0.0, 0usize);
    for v in values {
        min = min.min(v);
        max = max.max(v);
        sum += v;
        sq += v * v;
        n += 1;
    }
    let mean = sum / n.max(1) as f64;
    (min, max, mean, (sq / n.max(1) as f64 - mean * mean).max(0.0).sqrt(), n)
}

fn scalar_stats(values: impl Iterator<Item = f64>) -> Value {
    let (min, max, mean, std, n) = moments(values);
    json!({ "min": [min], "max": [max], "mean": [mean], "std": [std], "count": [n] })
}

fn vector_stats(rows: &[Vec<f32>]) -> Value {
    let d = rows.first().map_or(0, Vec::len);
    let per: Vec<_> = (0..d).map(|j| moments(rows.iter().map(|r| f64::from(r[j])))).collect();
    json!({
        "min": per.iter().map(|m| m.0).collect::<Vec<_>>(),
        "max": per.iter().map(|m| m.1).collect::<Vec<_>>(),
        "mean": per.iter().map(|m| m.2).collect::<Vec<_>>(),
        "std": per.iter().map(|m| m.3).collect::<Vec<_>>(),
        "count": [rows.len()],
    })
}

/// Per-channel statistics of pixel values in [0, 1], shaped [3, 1, 1] as LeRobot stores them.
fn image_stats(frames: &[RgbImage]) -> Value {
    let per: Vec<_> = (0..3)
        .map(|c| moments(frames.iter().flat_map(|f| f.pixels().map(move |p| f64::from(p.0[c]) / 255.0))))
        .collect();
    let wrap = |f: fn(&(f64, f64, f64, f64, usize)) -> f64| per.iter().map(|m| vec![vec![f(m)]]).collect::<Vec<_>>();
    json!({
        "min": wrap(|m| m.0), "max": wrap(|m| m.1), "mean": wrap(|m| m.2), "std": wrap(|m| m.3),
        "count": [frames.len()],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fsync_log::synced_in;
    use crate::source::CameraSelection;

    fn features(storage: Option<FrameStorage>) -> DatasetFeatures {
        DatasetFeatures {
            action_names: vec!["x".into(), "g".into()],
            state_names: vec!["x".into(), "g".into()],
            video_key: "observation.images.generated".into(),
            size: (6, 4),
            fps: 10.0,
            robot_type: "test".into(),
            storage,
        }
    }

    #[test]
    fn image_storage_keeps_every_frame_exactly_and_a_resume_holds_to_it() {
        let dir = bwm_testdir::TestDir::new("lerobot-png");
        let root = dir.join("out");
        let frames: Vec<RgbImage> = (0..3u8).map(|t| RgbImage::from_fn(6, 4, |x, y| image::Rgb([t * 40 + x as u8, y as u8 * 9, 200 - t]))).collect();
        let rows: Vec<Vec<f32>> = (0..3).map(|t| vec![t as f32 * 0.5, -1.0]).collect();
        let mut w = LeRobotWriter::create(&root, features(Some(FrameStorage::Image))).unwrap();
        w.add_episode(&frames, &rows, &rows, "open").unwrap();
        drop(w);
        // Asked for video, the dataset's image features are named; left unset, they are kept.
        let err = LeRobotWriter::resume(&root, features(Some(FrameStorage::Video))).err().expect("video storage accepted on an image dataset");
        assert!(err.to_string().contains("stored as image features"), "{err:#}");
        // Another frame rate or other actions would relabel the episodes written: refused.
        let err = LeRobotWriter::resume(&root, DatasetFeatures { fps: 20.0, ..features(None) }).err().expect("another frame rate accepted");
        assert!(err.to_string().contains("at 10 fps, this run writes 20 fps"), "{err:#}");
        let other = DatasetFeatures { action_names: vec!["y".into(), "g".into()], ..features(None) };
        let err = LeRobotWriter::resume(&root, other).err().expect("other action names accepted");
        assert!(err.to_string().contains(r#"its 'action' values are ["x","g"], this run writes ["y","g"]"#), "{err:#}");
        let mut w = LeRobotWriter::resume(&root, features(None)).unwrap();
        assert_eq!(w.storage(), FrameStorage::Image);
        w.add_episode(&frames[..2], &rows[..2], &rows[..2], "open").unwrap();

        assert!(!root.join("videos").exists(), "image storage wrote videos");
        let info: Value = serde_json::from_str(&std::fs::read_to_string(root.join("meta/info.json")).unwrap()).unwrap();
        assert_eq!(info["features"]["observation.images.generated"]["dtype"], "image");
        assert_eq!(info["total_videos"], 0);
        let source = crate::open_dataset(&root).unwrap();
        assert_eq!(source.episodes().len(), 2);
        let read = source.frames(0, 0..3, &CameraSelection::default()).unwrap();
        assert_eq!(read, frames, "PNG cells changed the frames");
        assert_eq!(source.frames(1, 0..2, &CameraSelection::default()).unwrap(), frames[..2]);
        let spec = crate::actions::ActionSpec::parse("action:0-1").unwrap();
        assert_eq!(source.vectors(0, &spec).unwrap(), rows);
    }

    #[test]
    fn metadata_and_episode_data_are_synced_under_their_temporary_name_then_their_folder() {
        let dir = bwm_testdir::TestDir::new("lerobot-sync");
        let dir = dir.canonicalize().unwrap();
        let meta = dir.join("meta");
        std::fs::create_dir_all(&meta).unwrap();
        let info = meta.join("info.json");
        write_atomic(&info, b"{}").unwrap();
        assert_eq!(std::fs::read(&info).unwrap(), b"{}");
        let synced = synced_in(&meta);
        // The bytes under the temporary name (before the rename), then the folder (the rename).
        let file = synced.iter().position(|p| p.parent() == Some(meta.as_path()) && p != &info);
        let folder = synced.iter().rposition(|p| p == &meta);
        assert!(file.is_some() && folder.is_some() && file < folder, "fsyncs in {}: {synced:?}", meta.display());

        let data = dir.join("data");
        std::fs::create_dir_all(&data).unwrap();
        let parquet = data.join("episode_000000.parquet");
        let batch = RecordBatch::try_from_iter([("index", int_column(0..4))]).unwrap();
        write_parquet(&parquet, &batch).unwrap();
        assert!(parquet.is_file());
        let synced = synced_in(&data);
        let file = synced.iter().position(|p| p.parent() == Some(data.as_path()) && p != &parquet);
        let folder = synced.iter().rposition(|p| p == &data);
        assert!(file.is_some() && folder.is_some() && file < folder, "fsyncs in {}: {synced:?}", data.display());
    }
}
