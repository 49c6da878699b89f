//! The data engine (`bwm rollout`): drive the world model from each episode's first frame with
//! ground-truth, file or perturbed actions, and write the generated episodes as a LeRobot v2.1
//! dataset (frame t shown while action t was applied; frame 0 is the real x0). With ground-truth
//! actions, also side-by-side videos (real left, generated right) and per-episode PSNR/SSIM.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use bwm_data::frames::{fit, frames_to_tensor, tensor_to_frames};
use bwm_data::lerobot_writer::{DatasetFeatures, FrameStorage, LeRobotWriter};
use bwm_data::open_dataset;
use bwm_metrics::image::{psnr, ssim};
use bwm_model::keyed_rng::{self, Purpose};
use image::RgbImage;
use serde::Deserialize;
use tch::Tensor;

use crate::lanes::Lanes;
use crate::world_model::{EpisodeFlags, EpisodeReading, WorldModel, WorldModelOptions};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Drive {
    /// The episode's own actions.
    Gt,
    /// The episode's actions plus Gaussian noise (--perturb-std, in normalized units), clipped
    /// to [-1, 1]: new trajectories near the recorded ones.
    Perturbed,
    /// Actions read from CSV files (one row per frame, the first row applied to x0).
    File,
}

impl std::str::FromStr for Drive {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "gt" => Ok(Drive::Gt),
            "perturbed" => Ok(Drive::Perturbed),
            "file" => Ok(Drive::File),
            _ => Err(format!("'{s}': expected gt, perturbed or file")),
        }
    }
}

/// What `run` generates, from where, and where it writes it (the flags of `bwm rollout`).
#[derive(Clone, Debug)]
pub struct RolloutOptions {
    /// Dataset whose episodes give x0 (and the actions for --drive gt|perturbed).
    pub data: Option<PathBuf>,
    /// Episode positions to roll out (default: all).
    pub episodes: Vec<usize>,
    /// Instead of a dataset: JSON lines {"x0": image file, "actions": CSV file, "task": text}.
    pub inputs: Option<PathBuf>,
    /// Which actions drive the episodes.
    pub drive: Drive,
    /// --drive file with a dataset: the folder of `episode_<index:06>.csv` files.
    pub actions_dir: Option<PathBuf>,
    /// Standard deviation of the noise of --drive perturbed, in normalized action units.
    pub perturb_std: f64,
    /// Action CSV files hold normalized values (default: raw, normalized with --stats).
    pub normalized: bool,
    /// How the dataset's episodes are read (actions, cameras, frame size); unset: as the
    /// weights' input contract says.
    pub reading: EpisodeFlags,
    /// Longest episode to generate, in frames including x0 (default: the whole episode).
    pub max_frames: Option<usize>,
    /// Frame rate of --inputs episodes (dataset episodes keep theirs).
    pub fps: f64,
    /// Output LeRobot v2.1 dataset folder.
    pub out: PathBuf,
    /// Episodes generated at once, their chunks one batch (each gets what it gets alone); they are
    /// written in order once the group is done.
    pub in_flight: usize,
    /// Lanes the episodes in flight are split into, each on a CUDA stream of its own, taking
    /// turns (`crate::lanes`).
    pub streams: usize,
    /// Continue an interrupted run into --out (finished episodes are kept).
    pub resume: bool,
    /// How the output stores its frames (unset: as a resumed dataset does, else
    /// `FrameStorage::default_for_build`).
    pub frame_storage: Option<FrameStorage>,
}

/// The record of what a rollout's output folder holds (its weights, episodes and settings), which
/// `--resume` compares.
const RUN_KEY_FILE: &str = "rollout.key.json";

/// One episode to generate.
struct Job {
    name: String,
    task: String,
    x0: RgbImage,
    /// Raw driving actions, one per frame (row 0 belongs to x0).
    raw: Option<Vec<Vec<f32>>>,
    /// Normalized driving actions [T, d].
    normalized: Tensor,
    /// The real frames (ground-truth drive only).
    truth: Option<Vec<RgbImage>>,
    fps: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct InputLine {
    x0: PathBuf,
    actions: PathBuf,
    #[serde(default)]
    task: String,
}

/// Rolls the world model that `options` opens out over the episodes `a` names and writes them as a
/// LeRobot v2.1 dataset (with comparisons against the real frames under the ground-truth drive).
pub fn run(options: &WorldModelOptions, a: &RolloutOptions) -> Result<()> {
    let options = options.with_stats_beside(a.data.as_deref());
    match (a.drive, &a.inputs, &a.actions_dir) {
        (Drive::File, None, None) => bail!("--drive file needs --actions-dir (with --data) or --inputs"),
        (Drive::Gt | Drive::Perturbed, Some(_), _) => bail!("--inputs gives no recorded actions to replay: use --drive file"),
        _ => {}
    }
    ensure!(a.perturb_std >= 0.0 && a.perturb_std.is_finite(), "--perturb-std must be a non-negative number");
    ensure!(a.in_flight >= 1, "episodes in flight must be at least 1");
    crate::lanes::check(a.in_flight, a.streams)?;
    let wm = options.load()?;
    let reading = wm.episode_reading(&a.reading, 32)?;
    let size = reading.size;
    // Before any frame is resized to it: an impossible size is named, not an aborted allocation.
    wm.check_frame_size(&format!("frames of {}x{} (--resolution)", size.0, size.1), size.1 as i64, size.0 as i64, a.in_flight)?;
    let lanes = wm.lanes(a.streams)?;
    println!(
        "rollout: {} on {:?}; chunks of {} frames, {} history frames, {} sampler steps, {} episode(s) in flight in {} stream(s)",
        if options.checkpoint.is_some() { "trained model" } else { "random weights" },
        wm.device,
        wm.spec.future,
        wm.spec.history,
        wm.spec.steps,
        a.in_flight,
        a.streams
    );
    let jobs = plan(a, options.seed, &wm, &reading)?;
    ensure!(!jobs.is_empty(), "nothing to roll out");
    let d = wm.action_dim();
    // The values' meanings where the weights' contract names them.
    let named = wm.contract.actions.as_ref().map(|c| c.components.clone()).filter(|c| c.len() == d);
    let names: Vec<String> = named.unwrap_or_else(|| (0..d).map(|j| format!("a{j}")).collect());
    let features = DatasetFeatures {
        action_names: names.clone(),
        state_names: names,
        video_key: "observation.images.generated".into(),
        size,
        fps: jobs[0].fps,
        robot_type: "bwm_world_model".into(),
        storage: a.frame_storage,
    };
    // What the episodes in `out` are, in order: a resumed run continues where its list of
    // episodes begins with those written, from the same weights and settings.
    let run_key = serde_json::json!({
        "settings": {
            "model": options.identity(&wm.spec),
            "drive": format!("{:?}", a.drive),
            "perturb_std": a.perturb_std,
            "normalized": a.normalized,
            "reading": format!("{:?}", a.reading),
        },
        "episodes": jobs.iter().map(|j| serde_json::json!([j.name, j.task, j.normalized.size()[0]])).collect::<Vec<_>>(),
    });
    let mut writer = if a.resume { LeRobotWriter::resume(&a.out, features)? } else { LeRobotWriter::create(&a.out, features)? };
    println!("rollout: frames stored as {} features", writer.storage().dtype());
    let done = writer.len();
    if done > 0 {
        let key_path = a.out.join(RUN_KEY_FILE);
        let earlier = std::fs::read_to_string(&key_path).ok().and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok());
        let written = |key: &serde_json::Value| key["episodes"].as_array().filter(|e| e.len() >= done).map(|e| e[..done].to_vec());
        let same = earlier.as_ref().is_some_and(|e| e["settings"] == run_key["settings"] && written(e).is_some() && written(e) == written(&run_key));
        ensure!(
            same,
            "{}: its {done} episodes were rolled out {} (compare {}); remove the folder or choose another --out",
            a.out.display(),
            if earlier.is_some() {
                "from other weights or settings than this run's, or are not the first episodes this run lists"
            } else {
                "by a run that left no record of its settings"
            },
            key_path.display()
        );
        println!("rollout: {} episodes already in {}; continuing", done, a.out.display());
    }
    bwm_data::latent_cache::write_atomically(&a.out, RUN_KEY_FILE, serde_json::to_string_pretty(&run_key)?.as_bytes())?;
    let compare_dir = a.out.join("compare");
    let start = Instant::now();
    let mut metrics = Vec::new();
    for group in jobs[done.min(jobs.len())..].chunks(a.in_flight) {
        let t0 = Instant::now();
        let names: Vec<&str> = group.iter().map(|j| j.name.as_str()).collect();
        let inputs: Vec<(&RgbImage, Tensor)> = group.iter().map(|j| (&j.x0, j.normalized.shallow_clone())).collect();
        let generated = generate_frames_together(&wm, &lanes, &inputs, &mut |chunk, total, made| {
            print!("\r  {}: chunk {chunk} ({made}/{total} frames, {:.1} s)   ", names.join(", "), t0.elapsed().as_secs_f64());
            let _ = std::io::stdout().flush();
        })?;
        println!();
        for (job, frames) in group.iter().zip(generated) {
            let raw = match &job.raw {
                Some(r) => r.clone(),
                None => wm.denormalize(&job.normalized)?,
            };
            let episode = writer.add_episode(&frames, &raw, &raw, &job.task)?;
            if let Some(truth) = &job.truth {
                std::fs::create_dir_all(&compare_dir)?;
                let (p, s) = compare(&frames, truth, wm.device)?;
                let side: Vec<RgbImage> = truth.iter().zip(&frames).map(|(t, g)| side_by_side(t, g)).collect();
                bwm_data::video::write_mp4_or_sheet(&compare_dir.join(format!("episode_{episode:06}.mp4")), &side, job.fps, 16)?;
                metrics.push(serde_json::json!({ "episode_index": episode, "source": job.name, "frames": frames.len(), "psnr": p, "ssim": s }));
                println!("  {}: episode {episode}, {} frames, PSNR {p:.2} dB, SSIM {s:.4} ({:.1} s)", job.name, frames.len(), t0.elapsed().as_secs_f64());
            } else {
                println!("  {}: episode {episode}, {} frames ({:.1} s)", job.name, frames.len(), t0.elapsed().as_secs_f64());
            }
        }
    }
    if !metrics.is_empty() {
        let lines: String = metrics.iter().map(|m| m.to_string() + "\n").collect();
        let path = compare_dir.join("metrics.jsonl");
        let mut f = std::fs::OpenOptions::new().create(true).append(true).open(&path).with_context(|| format!("opening {}", path.display()))?;
        f.write_all(lines.as_bytes())?;
        let mean = |k: &str| metrics.iter().filter_map(|m| m[k].as_f64()).sum::<f64>() / metrics.len() as f64;
        println!("rollout: mean PSNR {:.2} dB, mean SSIM {:.4} over {} episodes ({})", mean("psnr"), mean("ssim"), metrics.len(), path.display());
    }
    println!(
        "rollout: {} episodes in {} ({} new) in {:.1} s",
        writer.len(),
        a.out.display(),
        writer.len() - done,
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Episodes generated from their `x0` driven by `normalized` actions [T, d_a] each (row 0 belongs
/// to x0): x0, then one frame per action after the first. All are advanced chunk by chunk, each
/// lane's share as one batch (those with actions left), the lanes in turn; each gets what it
/// would alone. `progress(chunk, frames asked in all, frames made in all)`.
pub fn generate_frames_together(
    wm: &WorldModel,
    lanes: &Lanes,
    episodes: &[(&RgbImage, Tensor)],
    progress: &mut dyn FnMut(usize, usize, usize),
) -> Result<Vec<Vec<RgbImage>>> {
    let mut sizes: Vec<String> = episodes.iter().map(|(x0, _)| format!("{}x{}", x0.height(), x0.width())).collect();
    sizes.dedup();
    let what = || format!("generating {} episode(s) of {} (HxW) frames", episodes.len(), sizes.join(", "));
    crate::fallible::guarded(what, || generate_together(wm, lanes, episodes, progress))
}

fn generate_together(wm: &WorldModel, lanes: &Lanes, episodes: &[(&RgbImage, Tensor)], progress: &mut dyn FnMut(usize, usize, usize)) -> Result<Vec<Vec<RgbImage>>> {
    let mut rollouts = Vec::with_capacity(episodes.len());
    let mut after_x0 = Vec::with_capacity(episodes.len());
    for (x0, normalized) in episodes {
        let rows = normalized.size().first().copied().unwrap_or(0);
        ensure!(rows >= 1, "an episode needs at least x0's action");
        let x0_t = frames_to_tensor(std::slice::from_ref(*x0))?.squeeze_dim(1);
        rollouts.push(wm.rollout(&x0_t, &normalized.get(0))?);
        after_x0.push(normalized.narrow(0, 1, rows - 1));
    }
    let mut frames: Vec<Vec<RgbImage>> = episodes.iter().map(|(x0, _)| vec![(*x0).clone()]).collect();
    let total: usize = episodes.iter().map(|(_, a)| a.size()[0] as usize).sum();
    let mut made = frames.len();
    crate::lanes::run_together(lanes, &mut rollouts.iter_mut().collect::<Vec<_>>(), &after_x0, &mut |i, chunk| {
        frames[i].extend(tensor_to_frames(&chunk.frames)?);
        made += chunk.actions.size()[0] as usize;
        progress(chunk.index, total, made);
        Ok(())
    })?;
    Ok(frames)
}

fn plan(a: &RolloutOptions, seed: u64, wm: &WorldModel, reading: &EpisodeReading) -> Result<Vec<Job>> {
    let size = reading.size;
    let cap = |n: usize| a.max_frames.map_or(n, |m| n.min(m.max(1)));
    let mut jobs = Vec::new();
    if let Some(list) = &a.inputs {
        let text = std::fs::read_to_string(list).with_context(|| format!("reading {}", list.display()))?;
        let base = list.parent().unwrap_or(Path::new("."));
        for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let at = || format!("{} line {}", list.display(), n + 1);
            let input: InputLine = serde_json::from_str(line).with_context(at)?;
            let x0_path = base.join(&input.x0);
            let x0 = image::open(&x0_path).with_context(|| format!("{}: reading {}", at(), x0_path.display()))?.to_rgb8();
            let rows = read_csv(&base.join(&input.actions)).with_context(at)?;
            let rows = rows[..cap(rows.len())].to_vec();
            let (raw, normalized) = driving(wm, rows, a.normalized)?;
            jobs.push(Job { name: format!("input {}", n + 1), task: input.task, x0: fit(&x0, size.0, size.1, reading.resize), raw, normalized, truth: None, fps: a.fps });
        }
        return Ok(jobs);
    }
    let data = a.data.as_ref().context("--data or --inputs")?;
    let source = open_dataset(data)?;
    let (spec, cameras) = (&reading.actions, &reading.cameras);
    let episodes: Vec<usize> = if a.episodes.is_empty() { (0..source.episodes().len()).collect() } else { a.episodes.clone() };
    println!("rollout: {} ({} episodes selected)", source.describe(), episodes.len());
    for &e in &episodes {
        let info = source.episodes().get(e).with_context(|| format!("--episodes {e}: the dataset has {} episodes", source.episodes().len()))?;
        let length = cap(info.length);
        let name = format!("episode {}", info.index);
        let recorded = || -> Result<Vec<Vec<f32>>> { Ok(source.vectors(e, spec)?[..length].to_vec()) };
        let (raw, normalized) = match a.drive {
            Drive::Gt => driving(wm, recorded()?, false)?,
            Drive::Perturbed => {
                let clean = wm.normalize(&recorded()?)?;
                let noise = keyed_rng::normal(&clean.size(), seed, info.index as u64, Purpose::Augment);
                (None, (clean + noise * a.perturb_std).clamp(-1.0, 1.0))
            }
            Drive::File => {
                let dir = a.actions_dir.as_ref().context("--drive file needs --actions-dir")?;
                let rows = read_csv(&dir.join(format!("episode_{:06}.csv", info.index))).with_context(|| name.clone())?;
                let rows = rows[..cap(rows.len())].to_vec();
                driving(wm, rows, a.normalized)?
            }
        };
        let frames_needed = if a.drive == Drive::Gt { length } else { 1 };
        let frames = source.frames(e, 0..frames_needed, cameras).with_context(|| name.clone())?;
        let frames: Vec<RgbImage> = frames.iter().map(|f| fit(f, size.0, size.1, reading.resize)).collect();
        let truth = (a.drive == Drive::Gt).then(|| frames.clone());
        jobs.push(Job { name, task: info.task.clone(), x0: frames[0].clone(), raw, normalized, truth, fps: source.fps(e)? });
    }
    Ok(jobs)
}

/// (raw rows when known, normalized tensor) from rows in raw or normalized units.
fn driving(wm: &WorldModel, rows: Vec<Vec<f32>>, normalized: bool) -> Result<(Option<Vec<Vec<f32>>>, Tensor)> {
    ensure!(!rows.is_empty(), "no action rows");
    if let Some((t, _)) = rows.iter().enumerate().find(|(_, r)| r.iter().any(|v| !v.is_finite())) {
        bail!("action row {t} holds NaN or infinite values");
    }
    if normalized {
        let t = wm.rows_to_tensor(rows)?;
        ensure!(t.abs().max().double_value(&[]) <= 1.0 + 1e-6, "normalized actions must lie in [-1, 1]");
        Ok((None, t))
    } else {
        let t = wm.normalize(&rows)?;
        Ok((Some(rows), t))
    }
}

/// Rows of numbers; a first line that does not parse as numbers is a header.
fn read_csv(path: &Path) -> Result<Vec<Vec<f32>>> {
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .trim(csv::Trim::All)
        .from_path(path)
        .with_context(|| format!("opening {}", path.display()))?;
    let mut rows = Vec::new();
    for (i, record) in reader.records().enumerate() {
        let record = record.with_context(|| format!("{}: line {}", path.display(), i + 1))?;
        let parsed: std::result::Result<Vec<f32>, _> = record.iter().map(str::parse::<f32>).collect();
        match parsed {
            Ok(r) => rows.push(r),
            Err(_) if i == 0 => continue,
            Err(e) => bail!("{}: line {}: {e}", path.display(), i + 1),
        }
    }
    ensure!(!rows.is_empty(), "{}: no action rows", path.display());
    Ok(rows)
}

/// Mean PSNR and SSIM of the generated frames after x0 against the real ones, computed on `device`
/// (a batch of episodes in flight would otherwise spend their CPU scoring one after the other).
fn compare(generated: &[RgbImage], truth: &[RgbImage], device: tch::Device) -> Result<(f64, f64)> {
    ensure!(generated.len() == truth.len(), "{} generated frames, {} real", generated.len(), truth.len());
    if generated.len() < 2 {
        return Ok((f64::NAN, f64::NAN));
    }
    let (g, t) = (after_x0(generated, device)?, after_x0(truth, device)?);
    Ok((psnr(&g, &t), ssim(&g, &t)))
}

pub fn side_by_side(left: &RgbImage, right: &RgbImage) -> RgbImage {
    let (w, h) = left.dimensions();
    let mut out = RgbImage::new(w * 2, h);
    image::imageops::replace(&mut out, left, 0, 0);
    image::imageops::replace(&mut out, right, i64::from(w), 0);
    out
}

/// An episode's frames after x0 as one video tensor on `device`, where its scores are computed
/// (the model's: on a CPU an episode's SSIM takes about a second, spent while the accelerator waits).
pub(crate) fn after_x0(frames: &[RgbImage], device: tch::Device) -> Result<Tensor> {
    Ok(frames_to_tensor(&frames[1..])?.to_device(device))
}
