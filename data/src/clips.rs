//! Clip windows over episodes, and the per-episode checks that decide which episodes can give
//! clips: a clip is the episode's first frame x0, H history frames and K future frames, with the
//! action rows of exactly those frames.

use std::collections::BTreeMap;
use std::fmt;
use std::ops::Range;

use anyhow::{bail, ensure, Result};
use image::RgbImage;
use serde::{Deserialize, Serialize};

use crate::actions::ActionSpec;
use crate::defect::{classify, DefectKind};
use crate::source::{CameraSelection, EpisodeInfo, EpisodeSource};

/// Window shape: `history` frames before the future start, `future` frames from it, futures
/// starting every `stride` frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClipSpec {
    pub history: usize,
    pub future: usize,
    pub stride: usize,
}

/// One clip: `frames` = [0 (x0), the `history` frames before `future_start` (frame 0 where the
/// episode has none), `future_start..future_start + future`], 1 + H + K indices.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ClipWindow {
    pub future_start: usize,
    pub frames: Vec<usize>,
}

impl ClipSpec {
    /// H and K multiples of 4 (the VAE encodes x0 + H and the K future frames in groups of 4),
    /// K and the stride positive.
    pub fn validate(&self) -> Result<()> {
        ensure!(self.future > 0 && self.future.is_multiple_of(4), "clip future {} must be a positive multiple of 4", self.future);
        ensure!(self.history.is_multiple_of(4), "clip history {} must be a multiple of 4", self.history);
        ensure!(self.stride > 0, "clip stride must be positive");
        Ok(())
    }

    pub fn frames_per_clip(&self) -> usize {
        1 + self.history + self.future
    }

    /// The shortest episode that gives a clip: x0 and the K future frames after it.
    pub fn min_length(&self) -> usize {
        1 + self.future
    }

    /// The windows of an episode of `length` frames: future starts 1, 1 + stride, ... while the
    /// future fits. None when the episode is shorter than `min_length`.
    pub fn windows(&self, length: usize) -> Vec<ClipWindow> {
        if self.stride == 0 || length < self.min_length() {
            return Vec::new();
        }
        (1..=length - self.future)
            .step_by(self.stride)
            .map(|s| {
                let history = (0..self.history).map(|j| (s + j).saturating_sub(self.history));
                let frames = std::iter::once(0).chain(history).chain(s..s + self.future).collect();
                ClipWindow { future_start: s, frames }
            })
            .collect()
    }
}

/// An episode left out, and why.
#[derive(Debug, Clone, Serialize)]
pub struct Skipped {
    /// Position in `EpisodeSource::episodes()`.
    pub episode: usize,
    /// The dataset's own episode number.
    pub index: i64,
    pub kind: DefectKind,
    /// The error chain, one line.
    pub reason: String,
}

/// What a pass over the episodes used and left out.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SkipReport {
    pub episodes: usize,
    pub used: usize,
    pub clips: usize,
    pub skipped: Vec<Skipped>,
}

impl SkipReport {
    pub fn skip(&mut self, episode: usize, info: &EpisodeInfo, err: &anyhow::Error) {
        self.skipped.push(Skipped { episode, index: info.index, kind: classify(err), reason: format!("{err:#}") });
    }

    /// Skipped episodes per reason.
    pub fn counts(&self) -> BTreeMap<DefectKind, usize> {
        let mut m = BTreeMap::new();
        for s in &self.skipped {
            *m.entry(s.kind).or_insert(0) += 1;
        }
        m
    }

    fn reasons(&self) -> String {
        self.counts().iter().map(|(k, n)| format!("{n} {k}")).collect::<Vec<_>>().join(", ")
    }
}

impl fmt::Display for SkipReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} episodes: {} used ({} clips), {} skipped", self.episodes, self.used, self.clips, self.skipped.len())?;
        if !self.skipped.is_empty() {
            write!(f, " ({})", self.reasons())?;
        }
        Ok(())
    }
}

/// The usable episodes' action rows and clip windows.
#[derive(Debug, Clone)]
pub struct EpisodeClips {
    pub episode: usize,
    pub info: EpisodeInfo,
    /// One action vector per frame of the episode.
    pub actions: Vec<Vec<f32>>,
    pub windows: Vec<ClipWindow>,
}

impl EpisodeClips {
    /// The action rows of a window's frames, in its order.
    pub fn clip_actions(&self, window: &ClipWindow) -> Vec<Vec<f32>> {
        window.frames.iter().map(|&f| self.actions[f].clone()).collect()
    }
}

#[derive(Debug, Clone)]
pub struct ClipPlan {
    pub episodes: Vec<EpisodeClips>,
    pub report: SkipReport,
}

/// Checks the episodes at positions `episodes` (e.g. the training split) and lists their clips.
/// An episode that is too short, or whose actions or video fail (`Defect`s: NaN/inf, missing or
/// unreadable video, frame/row count mismatch, unknown column, anything unreadable) is skipped
/// and counted. A dataset with no usable episode is a one-line error.
pub fn plan_clips(
    source: &dyn EpisodeSource,
    episodes: &[usize],
    spec: &ActionSpec,
    cameras: &CameraSelection,
    clip: &ClipSpec,
) -> Result<ClipPlan> {
    clip.validate()?;
    spec.validate()?;
    let infos = source.episodes();
    let mut report = SkipReport { episodes: episodes.len(), ..Default::default() };
    let mut out = Vec::new();
    for &e in episodes {
        let Some(info) = infos.get(e) else { bail!("{}: episode position {e} out of range ({} episodes)", source.describe(), infos.len()) };
        match episode_clips(source, e, info, spec, cameras, clip) {
            Ok(c) => {
                report.used += 1;
                report.clips += c.windows.len();
                out.push(c);
            }
            Err(err) => report.skip(e, info, &err),
        }
    }
    if out.is_empty() {
        let first = report.skipped.first().map(|s| format!("; first: episode {}: {}", s.index, s.reason)).unwrap_or_default();
        bail!("{}: no usable episode among {} ({}){first}", source.describe(), episodes.len(), report.reasons());
    }
    Ok(ClipPlan { episodes: out, report })
}

fn episode_clips(
    source: &dyn EpisodeSource,
    e: usize,
    info: &EpisodeInfo,
    spec: &ActionSpec,
    cameras: &CameraSelection,
    clip: &ClipSpec,
) -> Result<EpisodeClips> {
    if info.length < clip.min_length() {
        if info.length == 0 {
            // Sources list an episode they cannot read with length 0; its vectors say why.
            source.vectors(e, spec)?;
        }
        return crate::defect::defect(
            DefectKind::TooShort,
            format!("{} frames, a clip needs at least {} (x0 + {} future)", info.length, clip.min_length(), clip.future),
        );
    }
    let actions = source.vectors(e, spec)?;
    let frames = source.frame_count(e, cameras)?;
    if frames != actions.len() {
        return crate::defect::defect(
            DefectKind::CountMismatch,
            format!("the video holds {frames} frames of the episode, the data {} rows", actions.len()),
        );
    }
    Ok(EpisodeClips { episode: e, info: info.clone(), windows: clip.windows(actions.len()), actions })
}

/// The frames of a window, in its order: x0 and the contiguous span from the first history
/// frame to the last future frame are read (two reads), then picked.
pub fn read_clip_frames(source: &dyn EpisodeSource, episode: usize, window: &ClipWindow, cameras: &CameraSelection) -> Result<Vec<RgbImage>> {
    let Some(&last) = window.frames.iter().max() else { return Ok(Vec::new()) };
    let first = window.frames.iter().copied().filter(|&f| f > 0).min().unwrap_or(0);
    let x0 = source.frames(episode, 0..1, cameras)?;
    let span: Range<usize> = first.max(1)..last + 1;
    let body = if span.is_empty() { Vec::new() } else { source.frames(episode, span.clone(), cameras)? };
    window
        .frames
        .iter()
        .map(|&f| {
            let img = if f == 0 { x0.first() } else { body.get(f - span.start) };
            img.cloned().ok_or_else(|| anyhow::anyhow!("frame {f} of the clip was not read"))
        })
        .collect()
}

/// The frames several windows of one episode need, each decoded once: x0, and the contiguous
/// span from the first to the last frame after x0 that any of the windows uses.
#[derive(Debug, Clone)]
pub struct EpisodeFrames {
    pub x0: RgbImage,
    /// Episode frame number of `span[0]`.
    pub first: usize,
    pub span: Vec<RgbImage>,
}

impl EpisodeFrames {
    /// Reads the frames of `windows` (two reads: x0, then the span).
    pub fn read(source: &dyn EpisodeSource, episode: usize, windows: &[ClipWindow], cameras: &CameraSelection) -> Result<Self> {
        let frames = || windows.iter().flat_map(|w| w.frames.iter().copied());
        let Some(last) = frames().max() else { bail!("no windows to read frames for") };
        let first = frames().filter(|&f| f > 0).min().unwrap_or(1).max(1);
        let Some(x0) = source.frames(episode, 0..1, cameras)?.pop() else { bail!("frame 0 of the episode was not read") };
        let span = if last >= first { source.frames(episode, first..last + 1, cameras)? } else { Vec::new() };
        ensure!(span.len() == (last + 1).saturating_sub(first), "read {} frames of {first}..={last}", span.len());
        Ok(Self { x0, first, span })
    }

    /// Frame `f` of the episode (0 = x0).
    pub fn get(&self, f: usize) -> Result<&RgbImage> {
        if f == 0 {
            return Ok(&self.x0);
        }
        f.checked_sub(self.first)
            .and_then(|i| self.span.get(i))
            .ok_or_else(|| anyhow::anyhow!("frame {f} is outside the frames read ({}..{})", self.first, self.first + self.span.len()))
    }

    /// The frames of a window, in its order.
    pub fn window(&self, window: &ClipWindow) -> Result<Vec<&RgbImage>> {
        window.frames.iter().map(|&f| self.get(f)).collect()
    }

    /// Every frame through `f` (e.g. resized), x0 included.
    pub fn map(self, mut f: impl FnMut(&RgbImage) -> RgbImage) -> Self {
        Self { x0: f(&self.x0), first: self.first, span: self.span.iter().map(&mut f).collect() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_pad_history_with_x0_and_step_by_stride() {
        let spec = ClipSpec { history: 4, future: 4, stride: 3 };
        spec.validate().unwrap();
        assert_eq!(spec.frames_per_clip(), 9);
        let w = spec.windows(12);
        // Future starts 1, 4, 7 (7 + 4 <= 12); 10 + 4 > 12.
        assert_eq!(w.iter().map(|w| w.future_start).collect::<Vec<_>>(), [1, 4, 7]);
        assert_eq!(w[0].frames, [0, 0, 0, 0, 0, 1, 2, 3, 4]);
        assert_eq!(w[1].frames, [0, 0, 1, 2, 3, 4, 5, 6, 7]);
        assert_eq!(w[2].frames, [0, 3, 4, 5, 6, 7, 8, 9, 10]);
        assert!(w.iter().all(|w| w.frames.len() == 9 && w.frames.iter().all(|&f| f < 12)));
        // The last possible future start is reached exactly.
        assert_eq!(ClipSpec { history: 0, future: 4, stride: 1 }.windows(6).last().unwrap().future_start, 2);
        assert!(spec.windows(4).is_empty());
        assert_eq!(spec.windows(5).len(), 1);
        assert_eq!(spec.windows(12), spec.windows(12), "deterministic");

        assert!(ClipSpec { history: 3, future: 4, stride: 1 }.validate().is_err());
        assert!(ClipSpec { history: 4, future: 0, stride: 1 }.validate().is_err());
        assert!(ClipSpec { history: 4, future: 4, stride: 0 }.validate().is_err());
        assert!(serde_json::from_str::<ClipSpec>(r#"{"history": 8, "future": 8, "stride": 8, "x": 1}"#).is_err());
    }
}
