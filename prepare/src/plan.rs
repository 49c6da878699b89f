//! What the cache will hold and where it comes from: the plan's record, whose hash decides whether
//! a rerun continues a cache; the source frame sizes (and the refusal to upscale); the action
//! statistics; the VAE file's fingerprint.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use bwm_data::clips::{ClipPlan, ClipSpec};
use bwm_data::stats::compute_stats;
use bwm_data::{ActionSpec, ActionStats, CameraSelection, EpisodeSource, ResizeMode};
use image::RgbImage;
use serde::Serialize;

use crate::options::PrepareOptions;

/// Changes whenever what a plan means changes, so older caches are not continued by mistake.
pub(crate) const PLAN_FORMAT: u32 = 1;

/// Everything the cache's contents depend on; its hash decides whether a rerun continues a cache.
#[derive(Debug, Serialize)]
pub(crate) struct PlanRecord {
    pub(crate) format: u32,
    pub(crate) dataset: String,
    pub(crate) episodes: usize,
    pub(crate) actions: ActionSpec,
    pub(crate) cameras: CameraSelection,
    pub(crate) resolution: [u32; 2],
    pub(crate) resize: ResizeMode,
    pub(crate) allow_upscale: bool,
    pub(crate) clip: ClipSpec,
    pub(crate) enhance_x0: Option<String>,
    pub(crate) keep_frames: bool,
    /// Absent for encoded caches, so their plan hashes are those of earlier versions.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub(crate) raw: bool,
    pub(crate) validation_fraction: f64,
    pub(crate) seed: u64,
    /// Episodes at the end of the cache held out for validation (data.holdout_episodes).
    pub(crate) holdout_episodes: usize,
    pub(crate) stats_from: String,
    pub(crate) stats: ActionStats,
    /// Size and a hash of the start and end of the VAE file.
    pub(crate) vae_fingerprint: String,
    pub(crate) device_type: String,
    pub(crate) batch: usize,
    pub(crate) clips_per_shard: usize,
    pub(crate) source_resolution: Vec<[u32; 2]>,
    pub(crate) clips: usize,
    /// Hash of every planned clip's episode number and frames.
    pub(crate) clip_list: String,
}

pub(crate) fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

/// The source frame size of each planned episode (from its x0); episodes whose x0 cannot be read
/// are skipped and counted.
pub(crate) fn source_sizes(source: &dyn EpisodeSource, plan: &mut ClipPlan, cameras: &CameraSelection) -> Result<Vec<(u32, u32)>> {
    let mut sizes = Vec::new();
    let mut kept = Vec::new();
    for ep in std::mem::take(&mut plan.episodes) {
        match source.frames(ep.episode, 0..1, cameras).and_then(|f| f.first().map(RgbImage::dimensions).context("no frame 0")) {
            Ok(s) => {
                sizes.push(s);
                kept.push(ep);
            }
            Err(e) => {
                plan.report.skip(ep.episode, &ep.info, &e);
                plan.report.used -= 1;
                plan.report.clips -= ep.windows.len();
            }
        }
    }
    plan.episodes = kept;
    Ok(sizes)
}

/// How much `fit` enlarges a `src` image to reach `dst` (the largest factor along an axis).
pub(crate) fn upscale_factor(src: (u32, u32), dst: (u32, u32), mode: ResizeMode) -> f64 {
    let (sx, sy) = (dst.0 as f64 / src.0.max(1) as f64, dst.1 as f64 / src.1.max(1) as f64);
    match mode {
        ResizeMode::Crop | ResizeMode::Stretch => sx.max(sy),
        ResizeMode::Pad => sx.min(sy),
    }
}

pub(crate) fn check_no_upscale(sizes: &[(u32, u32)], dst: (u32, u32), mode: ResizeMode) -> Result<()> {
    let mut small: BTreeMap<(u32, u32), usize> = BTreeMap::new();
    for &s in sizes {
        if upscale_factor(s, dst, mode) > 1.0 {
            *small.entry(s).or_default() += 1;
        }
    }
    if let Some((&(w, h), _)) = small.iter().next() {
        let n: usize = small.values().sum();
        bail!(
            "{n} episodes have source frames smaller than {}x{} (e.g. {w}x{h}: --resize {mode:?} would upscale {:.2}x); upscaled frames cost quality, so re-render at the target size, pick a smaller --resolution, or pass --allow-upscale",
            dst.0,
            dst.1,
            upscale_factor((w, h), dst, mode)
        );
    }
    Ok(())
}

/// The normalization statistics, where they come from, and whether they were computed here.
pub(crate) fn action_stats(
    a: &PrepareOptions,
    source: &dyn EpisodeSource,
    train: &[usize],
    spec: &ActionSpec,
    cameras: &CameraSelection,
) -> Result<(ActionStats, String, bool)> {
    if let Some(path) = &a.stats {
        return Ok((ActionStats::read(path, &spec.stats_group).context("--stats")?, path.display().to_string(), false));
    }
    let root = if a.data.is_dir() { a.data.clone() } else { a.data.parent().map(Path::to_path_buf).unwrap_or_default() };
    let own = root.join("stat.json");
    if own.is_file() && (a.data.is_file() || a.data.join("demo.jsonl").is_file()) {
        let stats = ActionStats::read(&own, &spec.stats_group).context("the dataset's stat.json (pass --stats to use another)")?;
        return Ok((stats, own.display().to_string(), false));
    }
    let result = compute_stats(source, train, std::slice::from_ref(spec), Some(cameras))?;
    let (_, stats) = result.groups.into_iter().next().context("no statistics were computed")?;
    Ok((stats, format!("computed over {} training episodes ({} frames)", result.report.used, result.frames), true))
}

/// Size plus a hash of the first and last MiB of a file: cheap, and changes when the file does.
pub(crate) fn file_fingerprint(path: &Path) -> Result<String> {
    use std::io::{Read, Seek, SeekFrom};
    let mut f = std::fs::File::open(path).with_context(|| format!("--vae {}", path.display()))?;
    let len = f.metadata()?.len();
    let mut head = vec![0u8; len.min(1 << 20) as usize];
    f.read_exact(&mut head)?;
    let mut tail = vec![0u8; len.min(1 << 20) as usize];
    f.seek(SeekFrom::Start(len - tail.len() as u64))?;
    f.read_exact(&mut tail)?;
    head.extend(tail);
    Ok(format!("{len}:{:016x}", fnv1a(&head)))
}
