//! The BWM release layout (the embedded default dataset): a `demo.jsonl` manifest with one line
//! per episode naming its parquet file (per-frame `observation.state` / `action` lists) and its mp4.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::{ensure, Context, Result};
use image::RgbImage;
use serde::Deserialize;

pub use crate::actions::ActionSpec;
use crate::defect::{defect, DefectKind};
use crate::source::{check_range, require_file, unreadable_video, video_frame_count, CameraSelection, EpisodeInfo, EpisodeSource};
use crate::{table, video};

/// One manifest line.
#[derive(Debug, Clone, Deserialize)]
pub struct Episode {
    pub episode_index: i64,
    pub length: usize,
    /// First frame of the episode in its video and parquet rows (both indexed from the file start).
    #[serde(default)]
    pub start_frame: usize,
    /// Last frame (inclusive); when given it must equal `start_frame + length - 1`.
    #[serde(default)]
    pub end_frame: Option<usize>,
    pub video: String,
    pub action: String,
    #[serde(default)]
    pub prompt: String,
    #[serde(default)]
    pub task: String,
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

    /// The action vectors of one episode, `[frames][d_a]`: parquet rows
    /// `start_frame..start_frame + length`, selected and converted as `spec` says.
    pub fn actions(&self, episode: &Episode, spec: &ActionSpec) -> Result<Vec<Vec<f32>>> {
        let path = self.root.join(&episode.action);
        let window = episode.window()?;
        let rows = read_list_column(&path, &spec.column)?;
        if rows.len() < window.end {
            return defect(
                DefectKind::CountMismatch,
                format!(
                    "{}: {} rows but the manifest says frames {}..{} ({} frames from frame {})",
                    path.display(),
                    rows.len(),
                    window.start,
                    window.end,
                    episode.length,
                    episode.start_frame
                ),
            );
        }
        spec.apply(&rows[window], &path.display().to_string())
    }
}

impl Episode {
    /// The episode's frames in its video / parquet rows, checked against `end_frame`.
    pub fn window(&self) -> Result<Range<usize>> {
        let end = self.start_frame + self.length;
        if let Some(last) = self.end_frame {
            if last + 1 != end {
                return defect(
                    DefectKind::CountMismatch,
                    format!(
                        "manifest entry of episode {}: start_frame {} + length {} does not end at end_frame {last}",
                        self.episode_index,
                        self.start_frame,
                        self.length
                    ),
                );
            }
        }
        Ok(self.start_frame..end)
    }
}

/// Reads a `list<float>` column of a parquet file, one Vec per row (list, large-list or
/// fixed-size-list columns of any numbers; a scalar column gives 1-wide rows).
pub fn read_list_column(path: &Path, column: &str) -> Result<Vec<Vec<f32>>> {
    let batches = table::read_columns(path, &[column], None)?;
    table::vectors(&batches, column, path)
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
