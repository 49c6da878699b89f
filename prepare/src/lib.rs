//! The latent cache from a dataset (what `bwm prepare` runs): cut a dataset's episodes (any format `open_dataset` detects) into action-aligned
//! clips, encode them with the VAE, and write the latent cache the trainer reads (layout in
//! `bwm_data::latent_cache`): shards of `--clips-per-shard` clips, each written whole, so an
//! interrupted run leaves only complete shards, and a rerun with the same arguments skips them.
//!
//! Ranks (`--rank R --world W`, default RANK and WORLD_SIZE) encode the shards s with s % W == R
//! into one folder. A process writes only its own files: its shards (temporary name, then rename)
//! and its progress file `progress.rank-R-of-W.json`, rewritten after each shard. The process that
//! finds every shard done writes `index.json` (a single writer, through an exclusive lock file),
//! or `bwm prepare --merge` does.

use std::cell::{Cell, RefCell};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender};
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use bwm_data::clips::{plan_clips, ClipPlan, ClipSpec, EpisodeFrames};
use bwm_data::frames::fit;
use bwm_data::latent_cache::{read_index, shard_file_name, write_atomically, write_index, write_shard, CacheIndex, ClipEntry, IndexExtras, ShardClip, CACHE_VERSION, INDEX_FILE};
use bwm_data::{open_dataset, CameraSelection, EpisodeSource};
use bwm_data::stats::{compute_stats, split_episodes, write_stat_json, SplitSpec, ValidationSize};
use bwm_data::{ActionSpec, ActionStats, ResizeMode};
use bwm_model::vae::WanVae;
use bwm_model::device::parse_device;
use image::RgbImage;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

use bwm_data::frames::parse_resolution;

/// The dataset, VAE, clip geometry and output of one `run` (the flags of `bwm prepare`).
#[derive(Clone, Debug)]
pub struct PrepareOptions {
    /// Dataset: BWM layout, LeRobot v2.1/v3.0 or RoboTwin 2.0 HDF5 (detected from the files).
    pub data: PathBuf,
    /// VAE: a `bwm train-vae` output, or the published Wan2.2_VAE.pth / safetensors (not needed
    /// with --merge).
    pub vae: Option<PathBuf>,
    /// A random full-width Wan2.2 VAE instead of --vae: for timing `prepare` where no weights are
    /// at hand (the latents mean nothing).
    pub random_vae: bool,
    /// VAE weights and activations: auto (bf16 on CUDA, f32 on CPU), bf16 or f32.
    pub dtype: String,
    /// Output folder of the latent cache.
    pub out: PathBuf,
    /// Clip frame size WIDTHxHEIGHT (multiples of 32).
    pub resolution: String,
    /// How frames of another aspect ratio are fitted to --resolution.
    pub resize: ResizeMode,
    /// Encode frames smaller than --resolution (after --resize) anyway; refused by default, since
    /// naively upscaled frames cost quality (re-render at the target size instead).
    pub allow_upscale: bool,
    /// History frames H and future frames K (multiples of 4).
    pub history: usize,
    pub future: usize,
    /// Frames between the starts of consecutive clips of an episode.
    pub stride: usize,
    /// Action vector: a preset (eef_abs, joint_abs, eef_delta, joint_delta, robotwin_eef_abs),
    /// COLUMN:INDICES (e.g. observation.state:0-5,7), or a JSON file holding an action spec.
    /// Default: robotwin_eef_abs for RoboTwin HDF5, eef_abs otherwise.
    pub actions: Option<String>,
    /// Cameras, comma-separated; several are stacked top to bottom. Default: the dataset's camera.
    pub camera: Vec<String>,
    /// stat.json normalizing the actions. Default: the dataset's own stat.json when it has one,
    /// else statistics of the training episodes, written to OUT/stat.json.
    pub stats: Option<PathBuf>,
    /// Fraction of episodes held out for validation (by episode, deterministic in --seed, as
    /// `bwm stats` splits): left out of computed statistics, their clips last in the cache.
    pub validation_fraction: f64,
    pub seed: u64,
    /// A command enhancing each episode's first frame x0 before resizing (e.g. super-resolution):
    /// {in} is replaced by the path of a PNG to read, {out} by the PNG path to write.
    pub enhance_x0: Option<String>,
    /// Keep the clips' pixel frames in the cache (validation against real pixels).
    pub keep_frames: bool,
    /// Raw clips: store the clips' pixel frames (u8) and actions without encoding them; the
    /// trainer encodes each batch as it reads it (set data.vae). --vae is then optional and only
    /// fixes the latent shape (default: the Wan2.2 VAE's).
    pub raw: bool,
    /// Clips per shard file.
    pub clips_per_shard: usize,
    /// Clips encoded by one VAE call.
    pub batch: usize,
    /// This process's rank among --world processes sharing the work (default: RANK, or 0).
    pub rank: Option<usize>,
    /// Processes sharing the work (default: WORLD_SIZE, or 1).
    pub world: Option<usize>,
    /// Replace a cache in --out that was prepared with other arguments.
    pub overwrite: bool,
    /// Only write index.json from the ranks' finished shards (after a multi-process run).
    pub merge: bool,
    pub device: String,
}

/// Changes whenever what a plan means changes, so older caches are not continued by mistake.
const PLAN_FORMAT: u32 = 1;
/// The most frames after x0 read at once from an episode for a group of clips.
const MAX_SPAN: usize = 512;
const LOCK_FILE: &str = ".index.json.lock";

/// Everything the cache's contents depend on; its hash decides whether a rerun continues a cache.
#[derive(Debug, Serialize)]
struct PlanRecord {
    format: u32,
    dataset: String,
    episodes: usize,
    actions: ActionSpec,
    cameras: CameraSelection,
    resolution: [u32; 2],
    resize: ResizeMode,
    allow_upscale: bool,
    clip: ClipSpec,
    enhance_x0: Option<String>,
    keep_frames: bool,
    /// Absent for encoded caches, so their plan hashes are those of earlier versions.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    raw: bool,
    validation_fraction: f64,
    seed: u64,
    /// Episodes at the end of the cache held out for validation (data.holdout_episodes).
    holdout_episodes: usize,
    stats_from: String,
    stats: ActionStats,
    /// Size and a hash of the start and end of the VAE file.
    vae_fingerprint: String,
    device_type: String,
    batch: usize,
    clips_per_shard: usize,
    source_resolution: Vec<[u32; 2]>,
    clips: usize,
    /// Hash of every planned clip's episode number and frames.
    clip_list: String,
}

/// One process's record of its finished shards.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RankProgress {
    plan_hash: String,
    rank: usize,
    world: usize,
    shards: usize,
    /// The cache's index without clips, and its extras: what `--merge` needs.
    index: CacheIndex,
    extras: IndexExtras,
    finished: BTreeMap<usize, FinishedShard>,
    done: bool,
}

#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct FinishedShard {
    clips: Vec<ClipEntry>,
    skipped: Vec<ShardSkip>,
}

/// Planned clips that could not be read or enhanced, and why.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ShardSkip {
    episode: i64,
    clips: usize,
    reason: String,
}

/// This rank's claim on the output folder, held while the process runs: a second `bwm prepare`
/// of the same rank into the same folder is refused instead of encoding the same shards twice.
pub const LOCK_PREFIX: &str = ".lock.rank-";

fn lock_rank(out: &Path, rank: usize, world: usize) -> Result<std::fs::File> {
    let path = out.join(format!("{LOCK_PREFIX}{rank}-of-{world}"));
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .with_context(|| format!("creating {}", path.display()))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => bail!(
            "{} is being written by another `bwm prepare` (rank {rank} of {world}, lock {}); wait for it to finish or choose another --out",
            out.display(),
            path.display()
        ),
        Err(std::fs::TryLockError::Error(e)) => Err(e).with_context(|| format!("locking {}", path.display())),
    }
}

fn progress_name(rank: usize, world: usize) -> String {
    format!("progress.rank-{rank}-of-{world}.json")
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

/// Encodes this rank's shards of the latent cache `a` describes (or, with `a.merge`, writes the
/// index of a cache whose ranks have all finished).
pub fn run(a: &PrepareOptions) -> Result<()> {
    if a.merge {
        return merge_command(&a.out);
    }
    let start = Instant::now();
    let (rank, world) = rank_and_world(a.rank, a.world)?;
    let vae_path = match (&a.vae, a.random_vae) {
        (Some(p), _) => p.clone(),
        (None, true) => PathBuf::from("random"),
        (None, false) if a.raw => PathBuf::from("none (raw clips; Wan2.2 VAE geometry)"),
        (None, false) => bail!("--vae is required (or --random-vae for timing, or --raw; not needed with --merge)"),
    };
    let clip = ClipSpec { history: a.history, future: a.future, stride: a.stride };
    clip.validate().context("--history/--future/--stride")?;
    let size = parse_resolution(&a.resolution, 32)?;
    ensure!(a.clips_per_shard > 0, "--clips-per-shard must be positive");
    ensure!(a.batch > 0, "--batch must be positive");
    ensure!(
        a.validation_fraction.is_finite() && (0.0..1.0).contains(&a.validation_fraction),
        "--validation-fraction {} must be in [0, 1)",
        a.validation_fraction
    );
    if let Some(cmd) = &a.enhance_x0 {
        ensure!(cmd.contains("{in}") && cmd.contains("{out}"), "--enhance-x0 '{cmd}' must contain the placeholders {{in}} and {{out}}");
    }
    let device = parse_device(&a.device)?;

    let source = open_dataset(&a.data)?;
    let spec = action_spec(a.actions.as_deref(), &a.data)?;
    let cameras = CameraSelection::from_names(&a.camera);
    let split = split_episodes(source.episodes(), &SplitSpec { seed: a.seed, validation: ValidationSize::Fraction(a.validation_fraction) })?;
    let order: Vec<usize> = split.train.iter().chain(&split.validation).copied().collect();
    println!("prepare: {} (rank {rank} of {world})", source.describe());
    let mut plan = plan_clips(source.as_ref(), &order, &spec, &cameras, &clip)?;
    let sizes = source_sizes(source.as_ref(), &mut plan, &cameras)?;
    if plan.episodes.is_empty() {
        bail!("no usable clip in {}: {}", a.data.display(), plan.report);
    }
    let mut source_resolution: Vec<[u32; 2]> = sizes.iter().map(|&(w, h)| [w, h]).collect::<BTreeSet<_>>().into_iter().collect();
    source_resolution.sort();
    if !a.allow_upscale {
        check_no_upscale(&sizes, size, a.resize)?;
    }
    let action_dim = plan.episodes[0].actions.first().map_or(0, Vec::len);
    let (stats, stats_from, computed) = action_stats(&a, source.as_ref(), &split.train, &spec, &cameras)?;
    ensure!(
        stats.dim() == action_dim,
        "{stats_from}: group '{}' has {} dimensions, the action vector {action_dim}",
        spec.stats_group,
        stats.dim()
    );
    let holdout: BTreeSet<usize> = split.validation.iter().copied().collect();
    let holdout_episodes = plan.episodes.iter().filter(|e| holdout.contains(&e.episode)).count();
    let planned: Vec<(usize, usize)> = plan.episodes.iter().enumerate().flat_map(|(i, e)| (0..e.windows.len()).map(move |w| (i, w))).collect();
    let clip_list = planned.iter().fold(String::new(), |mut s, &(e, w)| {
        s.push_str(&format!("{}:{:?};", plan.episodes[e].info.index, plan.episodes[e].windows[w].frames));
        s
    });
    let record = PlanRecord {
        format: PLAN_FORMAT,
        dataset: std::fs::canonicalize(&a.data).unwrap_or_else(|_| a.data.clone()).display().to_string(),
        episodes: source.episodes().len(),
        actions: spec.clone(),
        cameras: cameras.clone(),
        resolution: [size.0, size.1],
        resize: a.resize,
        allow_upscale: a.allow_upscale,
        clip,
        enhance_x0: a.enhance_x0.clone(),
        keep_frames: a.keep_frames,
        raw: a.raw,
        validation_fraction: a.validation_fraction,
        seed: a.seed,
        holdout_episodes,
        stats_from: stats_from.clone(),
        stats: stats.clone(),
        vae_fingerprint: match (&a.vae, a.random_vae) {
            (_, true) => "random Wan2.2 VAE, seed 0".into(),
            (Some(_), false) => file_fingerprint(&vae_path)?,
            (None, false) => "none".into(),
        },
        device_type: if device.is_cuda() { "cuda".into() } else { "cpu".into() },
        batch: a.batch,
        clips_per_shard: a.clips_per_shard,
        source_resolution: source_resolution.clone(),
        clips: planned.len(),
        clip_list: format!("{:016x}", fnv1a(clip_list.as_bytes())),
    };
    let record_json = serde_json::to_value(&record)?;
    let hash = format!("{:016x}", fnv1a(serde_json::to_string(&record_json)?.as_bytes()));
    let shards = planned.len().div_ceil(a.clips_per_shard);
    println!(
        "  {}; {} clips of {} frames in {shards} shards of {}; statistics: {stats_from}",
        plan.report,
        planned.len(),
        clip.frames_per_clip(),
        a.clips_per_shard
    );
    const SHOWN: usize = 20;
    for s in plan.report.skipped.iter().take(SHOWN) {
        println!("  skipped episode {} ({}): {}", s.index, s.kind, s.reason);
    }
    if plan.report.skipped.len() > SHOWN {
        println!("  ... and {} more skipped episodes", plan.report.skipped.len() - SHOWN);
    }
    if holdout_episodes > 0 {
        println!("  the last {holdout_episodes} episodes of the cache are the validation split: set data.holdout_episodes = {holdout_episodes}");
    }

    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let _lock = lock_rank(&a.out, rank, world)?;
    if prepare_folder(&a.out, &hash, &record_json, a.overwrite, rank, world, shards)? {
        println!("prepare: {} already holds this cache, complete; nothing to do", a.out.join(INDEX_FILE).display());
        return Ok(());
    }
    if computed && rank == 0 {
        write_stat_json(&a.out.join("stat.json"), &[(spec.stats_group.clone(), stats.clone())])?;
        println!("  wrote {}", a.out.join("stat.json").display());
    }

    let kind = match a.dtype.as_str() {
        "auto" if device.is_cuda() => Kind::BFloat16,
        "auto" => Kind::Float,
        s => bwm_model::device::parse_kind(s)?,
    };
    let vae = match (&a.vae, a.random_vae) {
        (_, true) => Some(WanVae::random(&bwm_model::vae::VaeConfig::wan22(), kind, device, 0)?.0),
        (Some(_), false) => Some(WanVae::load_any(&vae_path, kind, device).with_context(|| format!("--vae {}", vae_path.display()))?),
        (None, false) => None,
    };
    let vae_cfg = vae.as_ref().map_or_else(bwm_model::vae::VaeConfig::wan22, |v| v.cfg.clone());
    // Raw clips are stored as they are; the VAE only gives the latent shape.
    let encoder_vae = if a.raw { None } else { vae.as_ref() };
    if let Some(w) = encoder_vae.and_then(|v| bwm_model::vae::clip_length_warning(v.trained_clip_frames, clip.frames_per_clip())) {
        println!("prepare: warning: {w}");
    }
    let ts = vae_cfg.temporal_stride() as usize;
    ensure!((clip.frames_per_clip() - 1).is_multiple_of(ts), "clips of 1 + {} frames do not fit the VAE's temporal stride {ts}", a.history + a.future);
    let fps = source.fps(plan.episodes[0].episode).context("the frame rate of the first episode")?;
    let latent_shape = vae_cfg.latent_shape(clip.frames_per_clip() as i64, size.1 as i64, size.0 as i64);
    let index = CacheIndex {
        has_frames: a.keep_frames || a.raw,
        has_latents: !a.raw,
        ..CacheIndex::new(latent_shape, action_dim as i64, a.history, a.future, [size.0, size.1], fps, vae_path.display().to_string())
    };
    let extras = IndexExtras {
        source_resolution,
        plan_hash: Some(hash.clone()),
        plan: Some(record_json),
        clips_per_shard: Some(a.clips_per_shard),
    };

    let (mut progress, done_elsewhere) = load_progress(&a.out, &hash, rank, world)?;
    progress.index = index.clone();
    progress.extras = extras;
    progress.shards = shards;
    progress.done = false;
    let finished_anywhere = |s: usize| {
        progress.finished.get(&s).or_else(|| done_elsewhere.get(&s)).is_some_and(|f| f.clips.is_empty() || a.out.join(shard_file_name(s)).is_file())
    };
    let mine: Vec<usize> = (0..shards).filter(|s| s % world == rank).collect();
    let todo: Vec<usize> = mine.iter().copied().filter(|&s| !finished_anywhere(s)).collect();
    for s in &todo {
        progress.finished.remove(s);
    }
    let jobs: Vec<Vec<(usize, usize)>> = todo
        .iter()
        .map(|&s| planned[s * a.clips_per_shard..((s + 1) * a.clips_per_shard).min(planned.len())].to_vec())
        .collect();
    let todo_clips: usize = jobs.iter().map(Vec::len).sum();
    println!(
        "  rank {rank}: {} of the {shards} shards are this rank's, {} already done; encoding {todo_clips} clips on {device:?}",
        mine.len(),
        mine.len() - todo.len()
    );
    write_progress(&a.out, &progress)?;

    let reader = Reader {
        source: source.as_ref(),
        plan: &plan,
        cameras: &cameras,
        stats: &stats,
        size,
        resize: a.resize,
        allow_upscale: a.allow_upscale,
        enhance_x0: a.enhance_x0.as_deref(),
    };
    let fault_after: Option<usize> = std::env::var("BWM_FAULT_EXIT_AFTER_SHARDS").ok().and_then(|v| v.parse().ok());
    let encode_start = Instant::now();
    let (encoded, skipped) = std::thread::scope(|scope| -> Result<(usize, usize)> {
        let (tx, rx) = sync_channel(4);
        let handle = scope.spawn(|| reader.read(&todo, &jobs, tx));
        let encoder = Encoder { vae: encoder_vae, device, batch: a.batch, keep_frames: a.keep_frames || a.raw, out: &a.out, index: &index, fault_after, staging: RefCell::new([None, None]), batches: Cell::new(0) };
        let result = encoder.run(rx, &mut progress, todo_clips);
        if handle.join().is_err() {
            bail!("the frame reading thread panicked");
        }
        result
    })?;
    let seconds = encode_start.elapsed().as_secs_f64();
    progress.done = true;
    write_progress(&a.out, &progress)?;
    println!(
        "prepare: rank {rank}: {encoded} clips encoded in {seconds:.1} s ({:.2} clips/s){}; {} shards finished",
        encoded as f64 / seconds.max(1e-9),
        if skipped > 0 { format!(", {skipped} planned clips skipped") } else { String::new() },
        todo.len()
    );
    report_skips(&progress.finished);
    match merge(&a.out, &hash, false)? {
        Merged::Written(index) | Merged::Exists(index) => {
            println!(
                "prepare: {} complete: {} clips, {} episodes ({:.1} s in all)",
                a.out.join(INDEX_FILE).display(),
                index.clips.len(),
                index.clips.iter().map(|c| c.episode).collect::<BTreeSet<_>>().len(),
                start.elapsed().as_secs_f64()
            );
        }
        Merged::Missing(missing) => println!(
            "prepare: rank {rank} is done; {} shards of other ranks are not finished yet (the last rank to finish writes index.json, or run `bwm prepare --merge --out {}`)",
            missing.len(),
            a.out.display()
        ),
        Merged::Busy(lock) => println!("prepare: another process is writing index.json (lock {})", lock.display()),
    }
    Ok(())
}

fn rank_and_world(rank: Option<usize>, world: Option<usize>) -> Result<(usize, usize)> {
    let env = |name: &str| -> Result<Option<usize>> {
        match std::env::var(name) {
            Ok(v) => Ok(Some(v.trim().parse().with_context(|| format!("{name}={v} is not a number"))?)),
            Err(_) => Ok(None),
        }
    };
    let rank = match rank {
        Some(r) => r,
        None => env("RANK")?.unwrap_or(0),
    };
    let world = match world {
        Some(w) => w,
        None => env("WORLD_SIZE")?.unwrap_or(1),
    };
    ensure!(world > 0 && rank < world, "--rank {rank} --world {world}: the rank must be below the world size");
    Ok((rank, world))
}

/// `--actions` (see `ActionSpec::parse`); None picks by dataset format.
fn action_spec(arg: Option<&str>, data: &Path) -> Result<ActionSpec> {
    let Some(arg) = arg else {
        let robotwin = !data.join("demo.jsonl").is_file()
            && !data.join("meta/info.json").is_file()
            && (matches!(data.extension().and_then(|e| e.to_str()), Some("hdf5" | "h5")) || (data.is_dir() && bwm_data::robotwin::has_hdf5_files(data)?));
        return Ok(if robotwin { ActionSpec::robotwin_eef_abs() } else { ActionSpec::eef_abs() });
    };
    ActionSpec::parse(arg).context("--actions")
}

/// The source frame size of each planned episode (from its x0); episodes whose x0 cannot be read
/// are skipped and counted.
fn source_sizes(source: &dyn EpisodeSource, plan: &mut ClipPlan, cameras: &CameraSelection) -> Result<Vec<(u32, u32)>> {
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
fn upscale_factor(src: (u32, u32), dst: (u32, u32), mode: ResizeMode) -> f64 {
    let (sx, sy) = (dst.0 as f64 / src.0.max(1) as f64, dst.1 as f64 / src.1.max(1) as f64);
    match mode {
        ResizeMode::Crop | ResizeMode::Stretch => sx.max(sy),
        ResizeMode::Pad => sx.min(sy),
    }
}

fn check_no_upscale(sizes: &[(u32, u32)], dst: (u32, u32), mode: ResizeMode) -> Result<()> {
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
fn action_stats(
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
fn file_fingerprint(path: &Path) -> Result<String> {
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

/// Brings the folder to a state this plan can continue: returns true when index.json already
/// holds this plan's complete cache. A cache of another plan is an error unless `overwrite`;
/// then its files are removed (by their owners, so that concurrent processes never touch the
/// same file: each rank its own progress file and stale temporary files, rank 0 the rest).
fn prepare_folder(out: &Path, hash: &str, record: &serde_json::Value, overwrite: bool, rank: usize, world: usize, shards: usize) -> Result<bool> {
    let differs = |stored: Option<&serde_json::Value>, what: &str| -> anyhow::Error {
        let fields = match stored.and_then(|s| s.as_object()) {
            Some(old) => {
                let new = record.as_object().cloned().unwrap_or_default();
                let mut keys: BTreeSet<&String> = old.keys().collect();
                keys.extend(new.keys());
                let names: Vec<&str> = keys.into_iter().filter(|k| old.get(*k) != new.get(*k)).map(|k| k.as_str()).collect();
                format!(" (differs in: {})", names.join(", "))
            }
            None => String::new(),
        };
        anyhow::anyhow!(
            "{} holds {what} prepared with other arguments{fields}; rerun with the same arguments to continue it, or pass --overwrite to replace it",
            out.display()
        )
    };
    let index_path = out.join(INDEX_FILE);
    if index_path.is_file() {
        let extras = read_index(&index_path).map(|(_, e)| e).unwrap_or_default();
        if extras.plan_hash.as_deref() == Some(hash) {
            return Ok(true);
        }
        if !overwrite {
            return Err(differs(extras.plan.as_ref(), "a cache"));
        }
        remove_if_present(&index_path)?;
    }
    for (path, p) in progress_files(out)? {
        let stored = p.as_ref().ok();
        if stored.is_some_and(|p| p.plan_hash == hash) {
            continue;
        }
        if !overwrite {
            return Err(differs(stored.and_then(|p| p.extras.plan.as_ref()), "a partial cache"));
        }
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let current_world = (0..world).any(|r| name == progress_name(r, world));
        if name == progress_name(rank, world) || (!current_world && rank == 0) {
            remove_if_present(&path)?;
        }
    }
    for entry in std::fs::read_dir(out).with_context(|| format!("listing {}", out.display()))? {
        let name = entry?.file_name().to_string_lossy().into_owned();
        let shard_of = |n: &str| n.strip_prefix("shard-").and_then(|n| n.get(..5)).and_then(|n| n.parse::<usize>().ok());
        let stale = if let Some(tmp) = name.strip_prefix('.').filter(|n| n.ends_with(".tmp")) {
            // A temporary file of a process that died, removed by the rank that would write it.
            shard_of(tmp).map_or(tmp.starts_with(&format!("{}.", progress_name(rank, world))), |s| s % world == rank)
        } else {
            overwrite && rank == 0 && (shard_of(&name).is_some_and(|s| s >= shards) || (name.starts_with("clip-") && name.ends_with(".safetensors")))
        };
        if stale {
            remove_if_present(&out.join(&name))?;
        }
    }
    Ok(false)
}

fn remove_if_present(path: &Path) -> Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e).with_context(|| format!("removing {}", path.display())),
        _ => Ok(()),
    }
}

/// Every progress file of the folder, parsed (or why not).
fn progress_files(out: &Path) -> Result<Vec<(PathBuf, Result<RankProgress>)>> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(out).with_context(|| format!("listing {}", out.display()))? {
        let path = entry?.path();
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        if name.starts_with("progress.rank-") && name.ends_with(".json") {
            let parsed = std::fs::read_to_string(&path)
                .map_err(anyhow::Error::from)
                .and_then(|t| Ok(serde_json::from_str::<RankProgress>(&t)?))
                .with_context(|| format!("reading {}", path.display()));
            files.push((path, parsed));
        }
    }
    files.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(files)
}

/// This rank's progress (fresh when it has none of this plan), and the shards other progress
/// files of this plan record as finished.
fn load_progress(out: &Path, hash: &str, rank: usize, world: usize) -> Result<(RankProgress, BTreeMap<usize, FinishedShard>)> {
    let mine = out.join(progress_name(rank, world));
    let mut own = None;
    let mut elsewhere = BTreeMap::new();
    for (path, p) in progress_files(out)? {
        let Ok(p) = p else { continue };
        if p.plan_hash != hash {
            continue;
        }
        if path == mine {
            own = Some(p);
        } else {
            elsewhere.extend(p.finished);
        }
    }
    let fresh = || RankProgress {
        plan_hash: hash.to_string(),
        rank,
        world,
        shards: 0,
        index: CacheIndex {
            version: CACHE_VERSION,
            latent_shape: vec![],
            action_dim: 0,
            pixel_frames: 0,
            history_frames: 0,
            future_frames: 0,
            resolution: [0, 0],
            fps: 0.0,
            vae: String::new(),
            has_frames: false,
            has_latents: true,
            clips: vec![],
        },
        extras: IndexExtras::default(),
        finished: BTreeMap::new(),
        done: false,
    };
    Ok((own.unwrap_or_else(fresh), elsewhere))
}

fn write_progress(out: &Path, p: &RankProgress) -> Result<()> {
    write_atomically(out, &progress_name(p.rank, p.world), serde_json::to_string(p)?.as_bytes())
}

enum Merged {
    Written(CacheIndex),
    Exists(CacheIndex),
    Missing(Vec<usize>),
    Busy(PathBuf),
}

/// Writes index.json when every shard of plan `hash` is finished (by any progress file); only
/// the process that creates the lock file writes it (`force`: regardless of the lock).
fn merge(out: &Path, hash: &str, force: bool) -> Result<Merged> {
    let index_path = out.join(INDEX_FILE);
    if let Ok((index, extras)) = read_index(&index_path) {
        if extras.plan_hash.as_deref() == Some(hash) {
            return Ok(Merged::Exists(index));
        }
    }
    let progress: Vec<RankProgress> = progress_files(out)?.into_iter().filter_map(|(_, p)| p.ok()).filter(|p| p.plan_hash == hash).collect();
    let Some(first) = progress.iter().find(|p| p.shards > 0) else { bail!("{}: no progress file of this plan", out.display()) };
    let mut finished: BTreeMap<usize, &FinishedShard> = BTreeMap::new();
    for p in &progress {
        finished.extend(p.finished.iter().map(|(&s, f)| (s, f)));
    }
    let missing: Vec<usize> = (0..first.shards)
        .filter(|s| !finished.get(s).is_some_and(|f| f.clips.is_empty() || out.join(shard_file_name(*s)).is_file()))
        .collect();
    if !missing.is_empty() {
        return Ok(Merged::Missing(missing));
    }
    let lock = out.join(LOCK_FILE);
    match std::fs::OpenOptions::new().write(true).create_new(true).open(&lock) {
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && !force => return Ok(Merged::Busy(lock)),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
        Err(e) => return Err(e).with_context(|| format!("creating {}", lock.display())),
    }
    let written = (|| -> Result<CacheIndex> {
        let mut index = first.index.clone();
        index.clips = finished.values().flat_map(|f| f.clips.iter().cloned()).collect();
        ensure!(!index.clips.is_empty(), "every planned clip was skipped; see the reasons above");
        write_index(out, INDEX_FILE, &index, &first.extras)?;
        Ok(index)
    })();
    remove_if_present(&lock)?;
    written.map(Merged::Written)
}

/// `bwm prepare --merge`: index.json from the progress files of the one plan in the folder.
fn merge_command(out: &Path) -> Result<()> {
    let files = progress_files(out)?;
    let hashes: BTreeSet<String> = files.iter().filter_map(|(_, p)| p.as_ref().ok()).map(|p| p.plan_hash.clone()).collect();
    let hash = match hashes.len() {
        0 => bail!("{}: no progress files of `bwm prepare` to merge", out.display()),
        1 => hashes.into_iter().next().unwrap_or_default(),
        n => bail!("{}: progress files of {n} different plans; rerun `bwm prepare` with --overwrite", out.display()),
    };
    let all: BTreeMap<usize, FinishedShard> =
        files.into_iter().filter_map(|(_, p)| p.ok()).filter(|p| p.plan_hash == hash).flat_map(|p| p.finished).collect();
    report_skips(&all);
    match merge(out, &hash, true)? {
        Merged::Written(index) | Merged::Exists(index) => {
            println!("prepare --merge: wrote {} ({} clips)", out.join(INDEX_FILE).display(), index.clips.len());
            Ok(())
        }
        Merged::Missing(m) => bail!(
            "{}: {} shards are not finished yet (e.g. {}); run (or rerun) the ranks that own them",
            out.display(),
            m.len(),
            m.iter().take(8).map(|s| shard_file_name(*s)).collect::<Vec<_>>().join(", ")
        ),
        Merged::Busy(lock) => bail!("{} is held", lock.display()),
    }
}

fn report_skips(finished: &BTreeMap<usize, FinishedShard>) {
    let mut by_episode: BTreeMap<i64, (usize, String)> = BTreeMap::new();
    for s in finished.values().flat_map(|f| &f.skipped) {
        let e = by_episode.entry(s.episode).or_insert((0, s.reason.clone()));
        e.0 += s.clips;
    }
    for (episode, (clips, reason)) in by_episode {
        println!("  skipped {clips} {} of episode {episode}: {reason}", if clips == 1 { "clip" } else { "clips" });
    }
}

/// What the reading thread sends the encoder.
enum Input {
    Clip(ClipInput),
    Skip(ShardSkip),
    /// Every clip of this shard has been sent.
    End(usize),
}

/// A clip as plain bytes and numbers: the reading thread does no tensor work, since torch's
/// OpenMP threads started from a second thread spin on the cores the encoder needs.
struct ClipInput {
    entry: ClipEntry,
    /// [F, H, W, 3] RGB.
    pixels: Vec<u8>,
    /// [F, d_a] normalized, row-major.
    actions: Vec<f32>,
}

/// Reads, resizes and normalizes the clips of the shards to encode, on its own thread.
struct Reader<'a> {
    source: &'a dyn EpisodeSource,
    plan: &'a ClipPlan,
    cameras: &'a CameraSelection,
    stats: &'a ActionStats,
    size: (u32, u32),
    resize: ResizeMode,
    allow_upscale: bool,
    enhance_x0: Option<&'a str>,
}

impl Reader<'_> {
    fn read(&self, shards: &[usize], jobs: &[Vec<(usize, usize)>], tx: SyncSender<Input>) {
        let mut x0: Option<(usize, std::result::Result<RgbImage, String>)> = None;
        for (&shard, clips) in shards.iter().zip(jobs) {
            for group in groups(self.plan, clips) {
                let (e, _) = group[0];
                let ep = &self.plan.episodes[e];
                if x0.as_ref().is_none_or(|(i, _)| *i != e) {
                    x0 = Some((e, self.x0(e).map_err(|err| format!("{err:#}"))));
                }
                let read = match x0.as_ref().map(|(_, r)| r) {
                    Some(Ok(first)) => self.read_group(e, &group).map(|frames| (first, frames)).map_err(|err| format!("{err:#}")),
                    Some(Err(reason)) => Err(reason.clone()),
                    None => return,
                };
                let skip = |clips: usize, reason: String| Input::Skip(ShardSkip { episode: ep.info.index, clips, reason });
                let sent = match read {
                    Ok((first, frames)) => group.iter().all(|&(_, w)| match self.clip(e, w, first, &frames) {
                        Ok(c) => tx.send(Input::Clip(c)).is_ok(),
                        Err(err) => tx.send(skip(1, format!("{err:#}"))).is_ok(),
                    }),
                    Err(reason) => tx.send(skip(group.len(), reason)).is_ok(),
                };
                if !sent {
                    return;
                }
            }
            if tx.send(Input::End(shard)).is_err() {
                return;
            }
        }
    }

    /// The episode's x0 at the target size, enhanced first when asked.
    fn x0(&self, e: usize) -> Result<RgbImage> {
        let ep = &self.plan.episodes[e];
        let x0 = self.source.frames(ep.episode, 0..1, self.cameras)?.pop().context("frame 0 was not read")?;
        let Some(cmd) = self.enhance_x0 else { return Ok(fit(&x0, self.size.0, self.size.1, self.resize)) };
        let enhanced = enhance(cmd, &x0, ep.episode).context("--enhance-x0")?;
        let (w, h) = enhanced.dimensions();
        if !self.allow_upscale && upscale_factor((w, h), self.size, self.resize) > 1.0 {
            bail!("--enhance-x0 returned {w}x{h}, smaller than the target {}x{} (pass --allow-upscale to accept)", self.size.0, self.size.1);
        }
        Ok(fit(&enhanced, self.size.0, self.size.1, self.resize))
    }

    /// The frames of a group of windows of one episode, resized (x0 is taken from `x0`).
    fn read_group(&self, e: usize, group: &[(usize, usize)]) -> Result<EpisodeFrames> {
        let ep = &self.plan.episodes[e];
        let windows: Vec<_> = group.iter().map(|&(_, w)| ep.windows[w].clone()).collect();
        let frames = EpisodeFrames::read(self.source, ep.episode, &windows, self.cameras)?;
        Ok(frames.map(|f| fit(f, self.size.0, self.size.1, self.resize)))
    }

    fn clip(&self, e: usize, w: usize, x0: &RgbImage, frames: &EpisodeFrames) -> Result<ClipInput> {
        let ep = &self.plan.episodes[e];
        let window = &ep.windows[w];
        let images = window.frames.iter().map(|&f| if f == 0 { Ok(x0) } else { frames.get(f) }).collect::<Result<Vec<_>>>()?;
        let (width, height) = self.size;
        let mut bytes = Vec::with_capacity(images.len() * (width * height * 3) as usize);
        for img in &images {
            ensure!(img.dimensions() == self.size, "a frame is {}x{} after resizing", img.width(), img.height());
            bytes.extend_from_slice(img.as_raw());
        }
        let actions: Vec<f32> = window.frames.iter().flat_map(|&i| self.stats.normalize(&ep.actions[i])).collect();
        Ok(ClipInput {
            entry: ClipEntry { file: String::new(), episode: ep.info.index, frames: window.frames.clone(), task: ep.info.task.clone() },
            pixels: bytes,
            actions,
        })
    }
}

/// Consecutive clips of one episode whose frames after x0 span at most `MAX_SPAN` frames.
fn groups(plan: &ClipPlan, clips: &[(usize, usize)]) -> Vec<Vec<(usize, usize)>> {
    let bounds = |e: usize, w: usize| {
        let frames = &plan.episodes[e].windows[w].frames;
        let lo = frames.iter().copied().filter(|&f| f > 0).min().unwrap_or(1);
        (lo, frames.iter().copied().max().unwrap_or(0))
    };
    let mut out: Vec<Vec<(usize, usize)>> = Vec::new();
    let mut span = (0, 0);
    for &(e, w) in clips {
        let (lo, hi) = bounds(e, w);
        match out.last_mut() {
            Some(g) if g[0].0 == e && hi.max(span.1) + 1 - lo.min(span.0) <= MAX_SPAN => {
                g.push((e, w));
                span = (lo.min(span.0), hi.max(span.1));
            }
            _ => {
                out.push(vec![(e, w)]);
                span = (lo, hi);
            }
        }
    }
    out
}

/// Runs the x0 enhancement command on one image (files in a temporary folder, removed after).
fn enhance(cmd: &str, x0: &RgbImage, episode: usize) -> Result<RgbImage> {
    let dir = tempfile::Builder::new()
        .prefix(&format!("bwm-enhance-x0-{episode}-"))
        .tempdir()
        .context("creating a temporary folder for the x0 enhancement")?;
    let (input, output) = (dir.path().join("in.png"), dir.path().join("out.png"));
    let quote = |p: &Path| format!("'{}'", p.display().to_string().replace('\'', "'\\''"));
    let line = cmd.replace("{in}", &quote(&input)).replace("{out}", &quote(&output));
    x0.save(&input).with_context(|| format!("writing {}", input.display()))?;
    let run = std::process::Command::new("sh").arg("-c").arg(&line).output().with_context(|| format!("running `{line}`"))?;
    if !run.status.success() {
        let stderr = String::from_utf8_lossy(&run.stderr);
        let tail: String = stderr.trim().lines().last().unwrap_or_default().chars().take(300).collect();
        bail!("`{line}` failed ({}): {tail}", run.status);
    }
    Ok(image::open(&output).with_context(|| format!("reading the enhanced x0 {}", output.display()))?.to_rgb8())
}

/// Encodes the clips the reader sends, writes each finished shard and this rank's progress.
struct Encoder<'a> {
    /// None: raw clips, stored without encoding.
    vae: Option<&'a WanVae>,
    device: Device,
    batch: usize,
    keep_frames: bool,
    out: &'a Path,
    index: &'a CacheIndex,
    fault_after: Option<usize>,
    /// Page-locked batch buffers on CUDA, used in turn, and the batches started so far.
    staging: RefCell<[Option<Tensor>; 2]>,
    batches: Cell<usize>,
}

impl Encoder<'_> {
    /// Returns (clips encoded, planned clips skipped).
    fn run(&self, rx: Receiver<Input>, progress: &mut RankProgress, total: usize) -> Result<(usize, usize)> {
        let bar = std::io::IsTerminal::is_terminal(&std::io::stderr()).then(|| {
            let bar = ProgressBar::new(total as u64);
            if let Ok(style) = ProgressStyle::with_template("{bar:40} {pos}/{len} clips  {per_sec}  {elapsed_precise} elapsed, ETA {eta_precise}") {
                bar.set_style(style);
            }
            bar
        });
        let start = Instant::now();
        let (mut encoded, mut skipped, mut shards_written) = (0usize, 0usize, 0usize);
        let mut pending: Vec<ClipInput> = Vec::new();
        // The batch whose encoding is queued on the device: its latents are read back only after
        // the next batch is assembled and queued, so that the host work overlaps the encoding.
        let mut in_flight: Option<Batch> = None;
        let mut clips: Vec<ShardClip> = Vec::new();
        let mut skips: Vec<ShardSkip> = Vec::new();
        for input in rx {
            match input {
                Input::Clip(c) => {
                    pending.push(c);
                    if pending.len() == self.batch {
                        let queued = self.start(&mut pending)?;
                        if let Some(done) = std::mem::replace(&mut in_flight, queued) {
                            clips.extend(self.finish(done)?);
                        }
                    }
                }
                Input::Skip(s) => {
                    skipped += s.clips;
                    skips.push(s);
                }
                Input::End(shard) => {
                    let last = self.start(&mut pending)?;
                    for done in [in_flight.take(), last].into_iter().flatten() {
                        clips.extend(self.finish(done)?);
                    }
                    let name = shard_file_name(shard);
                    let entries = if clips.is_empty() { Vec::new() } else { write_shard(self.out, self.index, &name, &clips)? };
                    encoded += entries.len();
                    progress.finished.insert(shard, FinishedShard { clips: entries, skipped: std::mem::take(&mut skips) });
                    write_progress(self.out, progress)?;
                    shards_written += 1;
                    match &bar {
                        Some(bar) => bar.inc(clips.len() as u64),
                        None => println!(
                            "  {name}: {} clips ({encoded}/{total}, {:.2} clips/s)",
                            clips.len(),
                            encoded as f64 / start.elapsed().as_secs_f64().max(1e-9)
                        ),
                    }
                    clips.clear();
                    if self.fault_after.is_some_and(|n| shards_written >= n) {
                        // Fault injection for the resumption test: stop as a killed process would.
                        eprintln!("BWM_FAULT_EXIT_AFTER_SHARDS: exiting after {shards_written} shards");
                        std::process::exit(3);
                    }
                }
            }
        }
        if let Some(bar) = bar {
            bar.finish_and_clear();
        }
        Ok((encoded, skipped))
    }

    /// Assembles the pending clips into one batch and queues its encoding on the device (no
    /// wait for the device); `None` when nothing is pending.
    fn start(&self, pending: &mut Vec<ClipInput>) -> Result<Option<Batch>> {
        if pending.is_empty() {
            return Ok(None);
        }
        let [w, h] = self.index.resolution;
        let f = self.index.pixel_frames as i64;
        let clip_bytes = (f * h as i64 * w as i64 * 3) as usize;
        if let Some(c) = pending.iter().find(|c| c.pixels.len() != clip_bytes) {
            bail!("clip pixels ({} bytes) do not match {f} frames of {w}x{h}", c.pixels.len());
        }
        let shape = [self.batch.max(pending.len()) as i64, f, h as i64, w as i64, 3];
        let host = if self.vae.is_some() && self.device.is_cuda() {
            // Page-locked, so that the copy to the device is queued rather than waited for. Two
            // buffers in turn: the one refilled now fed the batch before last, whose latents have
            // been read back, so its copy is done.
            let turn = self.batches.get() % 2;
            self.batches.set(self.batches.get() + 1);
            let mut staging = self.staging.borrow_mut();
            if staging[turn].as_ref().is_none_or(|t| t.size() != shape) {
                staging[turn] = Some(Tensor::empty(shape, (Kind::Uint8, Device::Cpu)).pin_memory(self.device));
            }
            staging[turn].as_ref().map(Tensor::shallow_clone).context("no staging buffer")?
        } else {
            Tensor::empty(shape, (Kind::Uint8, Device::Cpu))
        }
        .narrow(0, 0, pending.len() as i64);
        ensure!(host.is_contiguous() && host.numel() == pending.len() * clip_bytes, "the batch buffer is not one contiguous block");
        // SAFETY: `host` is a contiguous u8 CPU tensor of exactly this many bytes (checked above)
        // that no queued copy reads any more (see the staging buffers) and no other code touches
        // while the slice lives.
        let buffer = unsafe { std::slice::from_raw_parts_mut(host.data_ptr() as *mut u8, host.numel()) };
        for (dst, c) in buffer.chunks_exact_mut(clip_bytes).zip(pending.iter()) {
            dst.copy_from_slice(&c.pixels);
        }
        // Channels move to the front on the encoding device (a strided copy of 75 MB per 81-frame
        // 640x480 clip, slow on the host); raw clips stay on the host.
        let pixels = match self.vae {
            Some(_) => host.to_device_(self.device, Kind::Uint8, true, false),
            None => host,
        }
        .permute([0, 4, 1, 2, 3]);
        let latents = match self.vae {
            Some(vae) => Some(vae.encode_u8(&pixels)?),
            None => None,
        };
        Ok(Some(Batch { clips: std::mem::take(pending), pixels, latents }))
    }

    /// Waits for a batch's latents and turns it into shard clips.
    fn finish(&self, batch: Batch) -> Result<Vec<ShardClip>> {
        let (f, d) = (self.index.pixel_frames as i64, self.index.action_dim);
        let latents = batch.latents.map(|l| l.to_device(Device::Cpu));
        Ok(batch
            .clips
            .into_iter()
            .enumerate()
            .map(|(i, c)| ShardClip {
                entry: c.entry,
                latents: latents.as_ref().map(|l| l.get(i as i64)),
                actions: Tensor::from_slice(&c.actions).view([f, d]),
                frames: self.keep_frames.then(|| batch.pixels.get(i as i64)),
            })
            .collect())
    }
}

/// Clips whose encoding is queued: their pixels [B, 3, F, H, W] (on the device when encoding)
/// and latents (on the device, not yet read back).
struct Batch {
    clips: Vec<ClipInput>,
    pixels: Tensor,
    latents: Option<Tensor>,
}
