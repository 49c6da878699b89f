//! One interface over the episode datasets users bring: the BWM release layout, LeRobot v2.1 and
//! v3.0, and RoboTwin 2.0 HDF5 (both variants): the `EpisodeSource` trait and the helpers the
//! sources share; each source lives in its format's module, and `crate::open` picks one by the files.

use std::ops::Range;
use std::path::Path;

use anyhow::{ensure, Context, Result};
use image::RgbImage;
use serde::{Deserialize, Serialize};

use crate::actions::ActionSpec;
use crate::defect::{defect, DefectKind};
use crate::frames::stack_views_vertically;
use crate::video;

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
