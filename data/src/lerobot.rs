//! LeRobotDataset v2.x (one parquet and one mp4 per camera per episode, `meta/episodes.jsonl`)
//! and v3.0 (many episodes per parquet / mp4 file, located through `meta/episodes/*/*.parquet`).
//! Video frames are found by timestamp, as LeRobot does: the parquet `timestamp` of a frame, plus
//! the episode's `from_timestamp` in a shared v3 video file.

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use image::RgbImage;
use serde_json::Value;

use crate::actions::ActionSpec;
use crate::defect::{defect, DefectKind};
use crate::source::{check_range, compose, require_file, unreadable_video, video_frame_count, CameraSelection, EpisodeInfo, EpisodeSource};
use crate::{table, video};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LeRobotVersion {
    /// v2.0 / v2.1: one file per episode.
    V2,
    /// v3.0: many episodes per file.
    V3,
}

#[derive(Debug, Clone)]
struct VideoRef {
    path: PathBuf,
    /// Start of the episode in the file (v3), seconds.
    from: f64,
    /// End of the episode in the file (v3), seconds.
    to: Option<f64>,
}

#[derive(Debug, Clone)]
struct Episode {
    data: PathBuf,
    /// The episode's rows in `data` (v3; v2 files hold the episode alone).
    rows: Option<Range<usize>>,
    videos: BTreeMap<String, VideoRef>,
}

pub struct LeRobotDataset {
    pub root: PathBuf,
    pub version: LeRobotVersion,
    /// `codebase_version` as the dataset states it.
    pub codebase_version: String,
    pub fps: f64,
    /// Features of dtype `video`.
    pub video_keys: Vec<String>,
    /// Features of dtype `image` (frames stored inside the parquet files; not readable here).
    pub image_keys: Vec<String>,
    infos: Vec<EpisodeInfo>,
    episodes: Vec<Episode>,
}

impl LeRobotDataset {
    pub fn open(root: &Path) -> Result<Self> {
        let info_path = root.join("meta/info.json");
        let text = std::fs::read_to_string(&info_path).with_context(|| format!("reading {}", info_path.display()))?;
        let info: Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", info_path.display()))?;
        let field = |k: &str| info.get(k).with_context(|| format!("{}: no '{k}'", info_path.display()));
        let codebase_version = field("codebase_version")?.as_str().context("codebase_version is not text")?.to_string();
        let version = match codebase_version.as_str() {
            "v2.0" | "v2.1" => LeRobotVersion::V2,
            "v3.0" => LeRobotVersion::V3,
            v => bail!("{}: LeRobot codebase_version {v} is not supported (v2.0, v2.1, v3.0 are)", info_path.display()),
        };
        let fps = field("fps")?.as_f64().filter(|f| *f > 0.0).with_context(|| format!("{}: fps is not a positive number", info_path.display()))?;
        let data_path = field("data_path")?.as_str().with_context(|| format!("{}: data_path is not text", info_path.display()))?.to_string();
        let video_path = info.get("video_path").and_then(Value::as_str).map(str::to_string);
        let chunks_size = info.get("chunks_size").and_then(Value::as_i64).unwrap_or(1000).max(1);
        let features = field("features")?.as_object().with_context(|| format!("{}: features is not an object", info_path.display()))?;
        let keys_of = |dtype: &str| -> Vec<String> {
            features.iter().filter(|(_, f)| f.get("dtype").and_then(Value::as_str) == Some(dtype)).map(|(k, _)| k.clone()).collect()
        };
        let (video_keys, image_keys) = (keys_of("video"), keys_of("image"));
        if !video_keys.is_empty() {
            ensure!(video_path.is_some(), "{}: video features but no video_path", info_path.display());
        }
        let layout = Layout { root, data_path: &data_path, video_path: video_path.as_deref(), chunks_size, video_keys: &video_keys };
        let (infos, episodes) = match version {
            LeRobotVersion::V2 => layout.v2_episodes()?,
            LeRobotVersion::V3 => layout.v3_episodes()?,
        };
        ensure!(!infos.is_empty(), "{}: the dataset lists no episodes", root.display());
        Ok(Self { root: root.to_path_buf(), version, codebase_version, fps, video_keys, image_keys, infos, episodes })
    }

    fn episode(&self, episode: usize) -> Result<(&EpisodeInfo, &Episode)> {
        match (self.infos.get(episode), self.episodes.get(episode)) {
            (Some(i), Some(e)) => Ok((i, e)),
            _ => bail!("{}: episode {episode} out of range ({} episodes)", self.root.display(), self.infos.len()),
        }
    }

    fn what(&self, episode: usize) -> String {
        let index = self.infos.get(episode).map_or(-1, |e| e.index);
        format!("{} episode {index}", self.root.display())
    }

    /// The feature key a camera name means: the key itself, or its last dotted part
    /// (`top` for `observation.images.top`).
    fn camera_key(&self, name: &str) -> Result<String> {
        if let Some(k) = self.video_keys.iter().chain(&self.image_keys).find(|k| *k == name || k.rsplit('.').next() == Some(name)) {
            return Ok(k.clone());
        }
        let all: Vec<&str> = self.video_keys.iter().chain(&self.image_keys).map(String::as_str).collect();
        bail!("{}: no camera '{name}' (video and image features: {})", self.root.display(), all.join(", "))
    }

    fn camera_keys(&self, cameras: &CameraSelection) -> Result<Vec<String>> {
        let all: Vec<String> = self.video_keys.iter().chain(&self.image_keys).cloned().collect();
        let names = cameras.resolve(|| match all.as_slice() {
            [only] => Ok(only.clone()),
            [] => bail!("{}: the dataset has no video or image features", self.root.display()),
            keys => bail!("{}: several cameras ({}); the selection must name them", self.root.display(), keys.join(", ")),
        })?;
        names.iter().map(|n| self.camera_key(n)).collect()
    }

    fn video<'a>(&self, ep: &'a Episode, key: &str, what: &str) -> Result<&'a VideoRef> {
        ep.videos.get(key).with_context(|| format!("{what}: no video for camera {key} in the episode metadata"))
    }

    /// The episode's rows `range` of the data file.
    fn rows(ep: &Episode, range: &Range<usize>) -> Range<usize> {
        match &ep.rows {
            Some(r) => r.start + range.start..r.start + range.end,
            None => range.clone(),
        }
    }

    /// Frames `range` of an image feature (encoded files inside the parquet, or paths to them).
    fn image_frames(&self, ep: &Episode, key: &str, range: &Range<usize>, what: &str) -> Result<Vec<RgbImage>> {
        let batches = table::read_columns(&ep.data, &[key], Some(Self::rows(ep, range)))?;
        table::image_cells(&batches, key, &ep.data)?
            .into_iter()
            .enumerate()
            .map(|(i, cell)| {
                let frame = range.start + i;
                let decoded = match cell {
                    table::ImageCell::Bytes(b) => image::load_from_memory(&b).map_err(anyhow::Error::from),
                    table::ImageCell::Path(p) => image::open(self.root.join(&p)).with_context(|| format!("image file {p}")),
                };
                match decoded {
                    Ok(img) => Ok(img.to_rgb8()),
                    Err(e) => defect(DefectKind::Unreadable, format!("{what}: camera {key}, frame {frame}: {e:#}")),
                }
            })
            .collect()
    }

    /// The parquet `timestamp`s of frames `range` of the episode.
    fn timestamps(&self, ep: &Episode, range: &Range<usize>) -> Result<Vec<f64>> {
        let batches = table::read_columns(&ep.data, &["timestamp"], Some(Self::rows(ep, range)))?;
        table::floats(&batches, "timestamp", &ep.data)
    }
}

impl EpisodeSource for LeRobotDataset {
    fn describe(&self) -> String {
        format!(
            "LeRobot {} dataset at {} ({} episodes, {} fps, cameras: {})",
            self.codebase_version,
            self.root.display(),
            self.infos.len(),
            self.fps,
            if self.video_keys.is_empty() { "none".to_string() } else { self.video_keys.join(", ") }
        )
    }

    fn episodes(&self) -> &[EpisodeInfo] {
        &self.infos
    }

    fn cameras(&self) -> Vec<String> {
        self.video_keys.clone()
    }

    fn vectors(&self, episode: usize, spec: &ActionSpec) -> Result<Vec<Vec<f32>>> {
        let what = self.what(episode);
        let (info, ep) = self.episode(episode)?;
        require_data(&ep.data, &what)?;
        let rows = match self.version {
            LeRobotVersion::V2 => {
                let batches = table::read_columns(&ep.data, &[&spec.column], None).with_context(|| what.clone())?;
                table::vectors(&batches, &spec.column, &ep.data)?
            }
            LeRobotVersion::V3 => {
                let batches = table::read_columns(&ep.data, &[&spec.column, "episode_index"], ep.rows.clone()).with_context(|| what.clone())?;
                let owners = table::ints(&batches, "episode_index", &ep.data)?;
                if let Some(r) = owners.iter().position(|&o| o != info.index) {
                    return defect(
                        DefectKind::CountMismatch,
                        format!("{what}: row {r} of the episode's rows in {} belongs to episode {}", ep.data.display(), owners[r]),
                    );
                }
                table::vectors(&batches, &spec.column, &ep.data)?
            }
        };
        if rows.len() != info.length {
            return defect(
                DefectKind::CountMismatch,
                format!("{what}: {} has {} rows for the episode, the metadata says {} frames", ep.data.display(), rows.len(), info.length),
            );
        }
        spec.apply(&rows, &format!("{what} ({})", ep.data.display()))
    }

    fn frames(&self, episode: usize, range: Range<usize>, cameras: &CameraSelection) -> Result<Vec<RgbImage>> {
        let what = self.what(episode);
        let (info, ep) = self.episode(episode)?;
        check_range(&range, info.length, &what)?;
        let keys = self.camera_keys(cameras)?;
        require_data(&ep.data, &what)?;
        let mut stamps = None;
        let tolerance = 0.25 / self.fps;
        let mut views = Vec::with_capacity(keys.len());
        for key in &keys {
            if self.image_keys.contains(key) {
                views.push(self.image_frames(ep, key, &range, &what)?);
                continue;
            }
            if stamps.is_none() {
                stamps = Some(self.timestamps(ep, &range).with_context(|| what.clone())?);
            }
            let stamps = stamps.as_ref().expect("read above");
            let v = self.video(ep, key, &what)?;
            require_file(&v.path, &what)?;
            let times: Vec<f64> = stamps.iter().map(|t| v.from + t).collect();
            let frames = unreadable_video(video::read_frames_at(&v.path, &times, tolerance))
                .with_context(|| format!("{what}: camera {key}, frames {}..{}", range.start, range.end))?;
            views.push(frames);
        }
        compose(views, cameras.layout, &what)
    }

    fn frame_count(&self, episode: usize, cameras: &CameraSelection) -> Result<usize> {
        let what = self.what(episode);
        let (_, ep) = self.episode(episode)?;
        let mut count: Option<(usize, String)> = None;
        for key in self.camera_keys(cameras)? {
            if self.image_keys.contains(&key) {
                let n = match &ep.rows {
                    Some(r) => r.len(),
                    None => table::num_rows(&ep.data)?,
                };
                match &count {
                    Some((m, other)) if *m != n => {
                        return defect(DefectKind::CountMismatch, format!("{what}: camera {key} has {n} frames, camera {other} {m}"));
                    }
                    _ => count = Some((n, key)),
                }
                continue;
            }
            let v = self.video(ep, &key, &what)?;
            let n = match v.to {
                None => video_frame_count(&v.path, &what)?,
                Some(to) => {
                    require_file(&v.path, &what)?;
                    let info = unreadable_video(video::stream_info(&v.path))?;
                    if let Some(d) = info.duration_s {
                        if to > d + 0.5 / self.fps {
                            return defect(
                                DefectKind::CountMismatch,
                                format!("{what}: camera {key} ends at {to:.3} s but {} lasts {d:.3} s", v.path.display()),
                            );
                        }
                    }
                    ((to - v.from) * self.fps).round().max(0.0) as usize
                }
            };
            match &count {
                Some((m, other)) if *m != n => {
                    return defect(DefectKind::CountMismatch, format!("{what}: camera {key} has {n} frames, camera {other} {m}"));
                }
                _ => count = Some((n, key)),
            }
        }
        count.map(|(n, _)| n).with_context(|| format!("{what}: no camera selected"))
    }

    fn fps(&self, _episode: usize) -> Result<f64> {
        Ok(self.fps)
    }
}

fn require_data(path: &Path, what: &str) -> Result<()> {
    ensure!(path.is_file(), "{what}: data file {} does not exist", path.display());
    Ok(())
}

struct Layout<'a> {
    root: &'a Path,
    data_path: &'a str,
    video_path: Option<&'a str>,
    chunks_size: i64,
    video_keys: &'a [String],
}

impl Layout<'_> {
    fn v2_episodes(&self) -> Result<(Vec<EpisodeInfo>, Vec<Episode>)> {
        let path = self.root.join("meta/episodes.jsonl");
        let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
        let mut infos = Vec::new();
        let mut episodes = Vec::new();
        for (line_no, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let at = || format!("{}: line {}", path.display(), line_no + 1);
            let v: Value = serde_json::from_str(line).with_context(at)?;
            let index = v.get("episode_index").and_then(Value::as_i64).with_context(|| format!("{}: no episode_index", at()))?;
            let length = v.get("length").and_then(Value::as_u64).with_context(|| format!("{}: no length", at()))?;
            let tasks: Vec<&str> = v.get("tasks").and_then(Value::as_array).map(|a| a.iter().filter_map(Value::as_str).collect()).unwrap_or_default();
            let chunk = index / self.chunks_size;
            let vars = |key: &str| -> Vec<(&str, Var)> {
                vec![("episode_chunk", Var::Int(chunk)), ("episode_index", Var::Int(index)), ("video_key", Var::Text(key.to_string()))]
            };
            let data = self.root.join(fill(self.data_path, &vars("")).with_context(|| format!("{}: data_path", at()))?);
            let mut videos = BTreeMap::new();
            for key in self.video_keys {
                let template = self.video_path.unwrap_or_default();
                let p = self.root.join(fill(template, &vars(key)).with_context(|| format!("{}: video_path", at()))?);
                videos.insert(key.clone(), VideoRef { path: p, from: 0.0, to: None });
            }
            infos.push(EpisodeInfo { index, length: usize::try_from(length)?, task: tasks.join("; ") });
            episodes.push(Episode { data, rows: None, videos });
        }
        Ok((infos, episodes))
    }

    fn v3_episodes(&self) -> Result<(Vec<EpisodeInfo>, Vec<Episode>)> {
        let dir = self.root.join("meta/episodes");
        let mut files = Vec::new();
        collect_parquet(&dir, &mut files).with_context(|| format!("listing {}", dir.display()))?;
        files.sort();
        ensure!(!files.is_empty(), "{}: no episode metadata files (*.parquet)", dir.display());

        struct Row {
            index: i64,
            length: usize,
            task: String,
            data: (i64, i64),
            from: i64,
            to: i64,
            videos: BTreeMap<String, (i64, i64, f64, f64)>,
        }
        let mut rows = Vec::new();
        for file in &files {
            let video_cols: Vec<[String; 4]> = self
                .video_keys
                .iter()
                .map(|k| ["chunk_index", "file_index", "from_timestamp", "to_timestamp"].map(|c| format!("videos/{k}/{c}")))
                .collect();
            let mut names = vec!["episode_index", "length", "data/chunk_index", "data/file_index", "dataset_from_index", "dataset_to_index"];
            names.extend(video_cols.iter().flatten().map(String::as_str));
            let batches = table::read_columns(file, &names, None)?;
            let ints = |c: &str| table::ints(&batches, c, file);
            let (index, length, chunk, fidx, from, to) =
                (ints("episode_index")?, ints("length")?, ints("data/chunk_index")?, ints("data/file_index")?, ints("dataset_from_index")?, ints("dataset_to_index")?);
            let tasks = match table::read_columns(file, &["tasks"], None) {
                Ok(b) => table::string_lists(&b, "tasks", file)?,
                Err(_) => vec![Vec::new(); index.len()],
            };
            let mut per_key = Vec::new();
            for cols in &video_cols {
                per_key.push((ints(&cols[0])?, ints(&cols[1])?, table::floats(&batches, &cols[2], file)?, table::floats(&batches, &cols[3], file)?));
            }
            for i in 0..index.len() {
                let videos = self.video_keys.iter().zip(&per_key).map(|(k, c)| (k.clone(), (c.0[i], c.1[i], c.2[i], c.3[i]))).collect();
                rows.push(Row {
                    index: index[i],
                    length: usize::try_from(length[i]).with_context(|| format!("{}: negative length", file.display()))?,
                    task: tasks.get(i).map(|t| t.join("; ")).unwrap_or_default(),
                    data: (chunk[i], fidx[i]),
                    from: from[i],
                    to: to[i],
                    videos,
                });
            }
        }
        rows.sort_by_key(|r| r.index);
        // Rows of a data file are consecutive global frame indices: the file starts at the
        // smallest `dataset_from_index` of its episodes.
        let mut file_start: BTreeMap<(i64, i64), i64> = BTreeMap::new();
        for r in &rows {
            let e = file_start.entry(r.data).or_insert(r.from);
            *e = (*e).min(r.from);
        }
        let mut infos = Vec::new();
        let mut episodes = Vec::new();
        for r in rows {
            let vars = |key: &str, (c, f): (i64, i64)| -> Vec<(&str, Var)> {
                vec![("chunk_index", Var::Int(c)), ("file_index", Var::Int(f)), ("video_key", Var::Text(key.to_string()))]
            };
            let data = self.root.join(fill(self.data_path, &vars("", r.data)).context("data_path")?);
            let start = usize::try_from(r.from - file_start[&r.data]).context("dataset_from_index")?;
            let end = usize::try_from(r.to - file_start[&r.data]).context("dataset_to_index")?;
            ensure!(end >= start, "{}: episode {} ends before it starts", dir.display(), r.index);
            let mut videos = BTreeMap::new();
            for (key, (c, f, from, to)) in r.videos {
                let template = self.video_path.unwrap_or_default();
                let path = self.root.join(fill(template, &vars(&key, (c, f))).context("video_path")?);
                videos.insert(key, VideoRef { path, from, to: Some(to) });
            }
            infos.push(EpisodeInfo { index: r.index, length: r.length, task: r.task });
            episodes.push(Episode { data, rows: Some(start..end), videos });
        }
        Ok((infos, episodes))
    }
}

fn collect_parquet(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    for entry in std::fs::read_dir(dir)? {
        let path = entry?.path();
        if path.is_dir() {
            collect_parquet(&path, out)?;
        } else if path.extension().is_some_and(|e| e == "parquet") {
            out.push(path);
        }
    }
    Ok(())
}

enum Var {
    Int(i64),
    Text(String),
}

/// Fills a Python format template as LeRobot writes them: `{name}` and `{name:0Nd}`.
fn fill(template: &str, vars: &[(&str, Var)]) -> Result<String> {
    let mut out = String::with_capacity(template.len() + 16);
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        out.push_str(&rest[..open]);
        let close = rest[open..].find('}').with_context(|| format!("unclosed '{{' in path template '{template}'"))? + open;
        let field = &rest[open + 1..close];
        let (name, spec) = field.split_once(':').unwrap_or((field, ""));
        let value = vars.iter().find(|(n, _)| *n == name).map(|(_, v)| v).with_context(|| format!("path template '{template}' uses an unknown field '{name}'"))?;
        match value {
            Var::Text(s) => out.push_str(s),
            Var::Int(i) => {
                let width = spec.strip_suffix('d').unwrap_or(spec).trim_start_matches('0');
                let width: usize = if width.is_empty() { 0 } else { width.parse().with_context(|| format!("format '{spec}' in '{template}'"))? };
                out.push_str(&format!("{i:0width$}"));
            }
        }
        rest = &rest[close + 1..];
    }
    out.push_str(rest);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fills_lerobot_path_templates() {
        let vars = [("episode_chunk", Var::Int(0)), ("episode_index", Var::Int(42)), ("video_key", Var::Text("observation.images.top".into()))];
        assert_eq!(fill("data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet", &vars).unwrap(), "data/chunk-000/episode_000042.parquet");
        assert_eq!(
            fill("videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4", &vars).unwrap(),
            "videos/chunk-000/observation.images.top/episode_000042.mp4"
        );
        assert!(fill("x/{nope}.parquet", &vars).is_err());
        assert!(fill("x/{episode_index", &vars).is_err());
    }
}
