//! One `bwm prepare`: the plan, the output folder brought to it, this rank's shards read on one
//! thread and encoded on this one, and the index once every shard is done.

use std::cell::{Cell, RefCell};
use std::collections::BTreeSet;
use std::path::PathBuf;
use std::sync::mpsc::sync_channel;
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use bwm_data::clips::{plan_clips, ClipSpec};
use bwm_data::frames::parse_resolution;
use bwm_data::latent_cache::{shard_file_name, CacheIndex, IndexExtras, INDEX_FILE};
use bwm_data::stats::{split_episodes, write_stat_json, SplitSpec, ValidationSize};
use bwm_data::{open_dataset, CameraSelection};
use bwm_model::device::parse_device;
use bwm_model::vae::WanVae;
use tch::Kind;

use crate::encode::Encoder;
use crate::folder::{load_progress, lock_rank, merge, merge_command, prepare_folder, report_skips, write_progress, Merged};
use crate::options::{action_spec, rank_and_world, PrepareOptions};
use crate::plan::{action_stats, check_no_upscale, file_fingerprint, fnv1a, source_sizes, PlanRecord, PLAN_FORMAT};
use crate::read::Reader;

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
    // One frame rate for the cache (and the weights' contract): episodes at another would be
    // trained on as if they were at it.
    let fps = source.fps(plan.episodes[0].episode).context("the frame rate of the first episode")?;
    for e in &plan.episodes[1..] {
        let other = source.fps(e.episode).with_context(|| format!("the frame rate of episode {}", e.info.index))?;
        ensure!(
            (other - fps).abs() <= 1e-6 * fps.abs().max(1.0),
            "episode {} is at {other} fps, episode {} at {fps}: a cache holds episodes of one frame rate (prepare the episodes of each rate into a cache of their own)",
            e.info.index,
            plan.episodes[0].info.index
        );
    }
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
