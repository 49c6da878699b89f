//! One interface over the episode datasets users bring: the BWM release layout, LeRobot v2.1 and
//! v3.0, and RoboTwin 2.0 HDF5 (both variants), detected from the files (`open_dataset`).

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::{bail, ensure, Context, Result};
use image::RgbImage;
use serde::{Deserialize, Serialize};

use crate::actions::ActionSpec;
use crate::bwm_layout::BwmDataset;
use crate::defect::{defect, DefectKind};
use crate::frames::stack_views_vertically;
use crate::{lerobot, robotwin, table, video};

/// One episode as a dataset lists it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct EpisodeInfo {
    /// The dataset's own episode number (BWM / LeRobot `episode_index`, RoboTwin's N of
    /// `episodeN.hdf5`). The `EpisodeSource` methods take the position in `episodes()` instead.
    pub index: i64,
    /// Frames, as the dataset's metadata says.
    pub length: usize,
    /// Task text (instruction), empty when the dataset has none.
    pub task: String,
}

/// How the views of several cameras become one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraLayout {
    /// Exactly one camera.
    #[default]
    Single,
    /// The cameras' views top to bottom, in the listed order (BWM's multi-view layout).
    StackVertically,
}

/// Which cameras make a frame. An empty list means the source's default camera (BWM: the
/// manifest's video; LeRobot: the only video key; RoboTwin: the head camera).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSelection {
    #[serde(default)]
    pub cameras: Vec<String>,
    #[serde(default)]
    pub layout: CameraLayout,
}

impl CameraSelection {
    pub fn single(camera: &str) -> Self {
        Self { cameras: vec![camera.to_string()], layout: CameraLayout::Single }
    }

    /// The cameras a user listed (`--camera A,B`): none is the source's default, several are
    /// stacked top to bottom.
    pub fn from_names(cameras: &[String]) -> Self {
        let layout = if cameras.len() > 1 { CameraLayout::StackVertically } else { CameraLayout::Single };
        Self { cameras: cameras.to_vec(), layout }
    }

    pub fn stacked(cameras: &[&str]) -> Self {
        Self { cameras: cameras.iter().map(|c| c.to_string()).collect(), layout: CameraLayout::StackVertically }
    }

    /// The camera names to read: the listed ones, or `default` when none are listed.
    pub fn resolve(&self, default: impl FnOnce() -> Result<String>) -> Result<Vec<String>> {
        let cameras = if self.cameras.is_empty() { vec![default()?] } else { self.cameras.clone() };
        if self.layout == CameraLayout::Single {
            ensure!(cameras.len() == 1, "layout 'single' takes one camera, {} are listed ({})", cameras.len(), cameras.join(", "));
        }
        Ok(cameras)
    }
}

/// An episode dataset. Episodes are addressed by their position in `episodes()`. Per-episode
/// problems (missing video, NaN, count mismatch, unknown column...) are errors carrying a
/// `Defect`, so callers can skip the episode and count the reason (`defect::classify`).
pub trait EpisodeSource: Send + Sync {
    /// Format, location and size, in one line.
    fn describe(&self) -> String;
    fn episodes(&self) -> &[EpisodeInfo];
    /// Camera names `frames` accepts.
    fn cameras(&self) -> Vec<String>;
    /// The episode's action vectors, one per frame: exactly `episodes()[episode].length` rows.
    fn vectors(&self, episode: usize, spec: &ActionSpec) -> Result<Vec<Vec<f32>>>;
    /// Frames `range` of the episode (0 = its first frame) as RGB, the cameras composed as
    /// `cameras.layout` says.
    fn frames(&self, episode: usize, range: Range<usize>, cameras: &CameraSelection) -> Result<Vec<RgbImage>>;
    /// How many frames of the episode the selected cameras hold, from file headers where they
    /// say it (no full decode). Sources check their own alignment here (e.g. BWM: video frames
    /// against parquet rows).
    fn frame_count(&self, episode: usize, cameras: &CameraSelection) -> Result<usize>;
    /// Frames per second of the episode's video.
    fn fps(&self, episode: usize) -> Result<f64>;
}

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
            Some("hdf5" | "h5") => Ok(Box::new(robotwin::RoboTwinDataset::open(path)?)),
            _ => bail!("{}: not a dataset (expected a directory, a .jsonl manifest or an .hdf5 file)", path.display()),
        };
    }
    if path.join("demo.jsonl").is_file() {
        return Ok(Box::new(BwmSource::open(path)?));
    }
    if path.join("meta/info.json").is_file() {
        return Ok(Box::new(lerobot::LeRobotDataset::open(path)?));
    }
    if robotwin::has_hdf5_files(path)? {
        return Ok(Box::new(robotwin::RoboTwinDataset::open(path)?));
    }
    bail!(
        "{}: no dataset format recognized (looked for demo.jsonl, meta/info.json, and *.hdf5 files here or in data/)",
        path.display()
    )
}

/// Checks that `range` lies inside an episode of `length` frames.
pub(crate) fn check_range(range: &Range<usize>, length: usize, what: &str) -> Result<()> {
    ensure!(range.start <= range.end, "{what}: frame range {}..{} is reversed", range.start, range.end);
    ensure!(range.end <= length, "{what}: frames {}..{} requested but the episode has {length} frames", range.start, range.end);
    Ok(())
}

/// Views per camera ([camera][frame]) composed into frames as the layout says.
pub(crate) fn compose(mut views: Vec<Vec<RgbImage>>, layout: CameraLayout, what: &str) -> Result<Vec<RgbImage>> {
    ensure!(!views.is_empty(), "{what}: no camera selected");
    if views.len() == 1 {
        return Ok(views.pop().unwrap_or_default());
    }
    ensure!(layout == CameraLayout::StackVertically, "{what}: several cameras need layout 'stack_vertically'");
    let n = views[0].len();
    ensure!(views.iter().all(|v| v.len() == n), "{what}: the cameras returned different frame counts");
    (0..n)
        .map(|i| {
            let frame: Vec<RgbImage> = views.iter().map(|v| v[i].clone()).collect();
            stack_views_vertically(&frame).with_context(|| format!("{what}: stacking the views of frame {i}"))
        })
        .collect()
}

/// `MissingVideo` unless `path` is a file.
pub(crate) fn require_file(path: &Path, what: &str) -> Result<()> {
    if !path.is_file() {
        return defect(DefectKind::MissingVideo, format!("{what}: video {} does not exist", path.display()));
    }
    Ok(())
}

/// Errors of an existing video file become `UnreadableVideo` defects.
pub(crate) fn unreadable_video<T>(r: Result<T>) -> Result<T> {
    r.map_err(|e| {
        let kind = crate::defect::classify(&e);
        if kind == DefectKind::Unreadable {
            crate::defect::Defect::new(DefectKind::UnreadableVideo, format!("{e:#}")).into()
        } else {
            e
        }
    })
}

/// The frame count of a video from its header, decoding it only when the container states none.
pub(crate) fn video_frame_count(path: &Path, what: &str) -> Result<usize> {
    require_file(path, what)?;
    unreadable_video((|| {
        let info = video::stream_info(path)?;
        match info.declared_frames {
            Some(n) => Ok(n),
            None => Ok(video::probe(path)?.frames),
        }
    })())
}

/// The BWM release layout (`demo.jsonl`, parquet per episode, one mp4 per episode).
pub struct BwmSource {
    pub dataset: BwmDataset,
    infos: Vec<EpisodeInfo>,
    fps: Vec<OnceLock<f64>>,
}

/// The camera name of the BWM layout's single video.
pub const BWM_CAMERA: &str = "video";

impl BwmSource {
    pub fn open(path: &Path) -> Result<Self> {
        Ok(Self::new(BwmDataset::open(path)?))
    }

    pub fn new(dataset: BwmDataset) -> Self {
        let infos = dataset
            .episodes
            .iter()
            .map(|e| EpisodeInfo { index: e.episode_index, length: e.length, task: e.task.clone() })
            .collect();
        let fps = dataset.episodes.iter().map(|_| OnceLock::new()).collect();
        Self { dataset, infos, fps }
    }

    fn episode(&self, episode: usize) -> Result<&crate::bwm_layout::Episode> {
        self.dataset
            .episodes
            .get(episode)
            .with_context(|| format!("{}: episode {episode} out of range ({} episodes)", self.dataset.root.display(), self.dataset.episodes.len()))
    }

    fn video_path(&self, episode: usize) -> Result<PathBuf> {
        Ok(self.dataset.root.join(&self.episode(episode)?.video))
    }

    fn check_cameras(&self, cameras: &CameraSelection) -> Result<()> {
        let names = cameras.resolve(|| Ok(BWM_CAMERA.to_string()))?;
        ensure!(
            names.iter().all(|c| c == BWM_CAMERA),
            "{}: the BWM layout has one camera, '{BWM_CAMERA}' (asked for {})",
            self.dataset.root.display(),
            names.join(", ")
        );
        Ok(())
    }

    fn what(&self, episode: usize) -> String {
        let index = self.infos.get(episode).map_or(-1, |e| e.index);
        format!("{} episode {index}", self.dataset.root.display())
    }
}

impl EpisodeSource for BwmSource {
    fn describe(&self) -> String {
        format!("BWM layout at {} ({} episodes)", self.dataset.root.display(), self.infos.len())
    }

    fn episodes(&self) -> &[EpisodeInfo] {
        &self.infos
    }

    fn cameras(&self) -> Vec<String> {
        vec![BWM_CAMERA.to_string()]
    }

    fn vectors(&self, episode: usize, spec: &ActionSpec) -> Result<Vec<Vec<f32>>> {
        let ep = self.episode(episode)?;
        self.dataset.actions(ep, spec).with_context(|| self.what(episode))
    }

    fn frames(&self, episode: usize, range: Range<usize>, cameras: &CameraSelection) -> Result<Vec<RgbImage>> {
        let what = self.what(episode);
        self.check_cameras(cameras)?;
        let ep = self.episode(episode)?;
        check_range(&range, ep.length, &what)?;
        let window = ep.window().with_context(|| what.clone())?;
        let path = self.video_path(episode)?;
        require_file(&path, &what)?;
        unreadable_video(video::read_frames(&path, window.start + range.start..window.start + range.end)).with_context(|| what)
    }

    fn frame_count(&self, episode: usize, cameras: &CameraSelection) -> Result<usize> {
        let what = self.what(episode);
        self.check_cameras(cameras)?;
        let ep = self.episode(episode)?;
        let window = ep.window().with_context(|| what.clone())?;
        let video = video_frame_count(&self.video_path(episode)?, &what)?;
        let parquet = self.dataset.root.join(&ep.action);
        let rows = table::num_rows(&parquet).with_context(|| what.clone())?;
        if video != rows {
            return defect(
                DefectKind::CountMismatch,
                format!("{what}: the video has {video} frames but {} has {rows} rows", parquet.display()),
            );
        }
        Ok(video.saturating_sub(window.start).min(ep.length))
    }

    fn fps(&self, episode: usize) -> Result<f64> {
        if let Some(&fps) = self.fps.get(episode).and_then(OnceLock::get) {
            return Ok(fps);
        }
        let path = self.video_path(episode)?;
        let fps = video::stream_info(&path).with_context(|| self.what(episode))?.fps;
        if let Some(slot) = self.fps.get(episode) {
            let _ = slot.set(fps);
        }
        Ok(fps)
    }
}
