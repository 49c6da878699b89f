//! `bwm train-vae`: fit a small Wan2.2-architecture VAE to a dataset's frames.

use std::path::PathBuf;

use anyhow::{ensure, Context, Result};
use bwm_data::frames::{fit, frames_to_tensor, parse_resize, parse_resolution};
use bwm_data::{open_dataset, CameraSelection, EpisodeSource};
use bwm_data::ResizeMode;
use bwm_model::vae::VaeConfig;
use bwm_trainer::devices::parse_device;
use bwm_trainer::vae_train::{save_trained_vae, train_vae, FrameSets, VaeTrainSettings};
use clap::Args;
use tch::Tensor;

#[derive(Args)]
pub struct TrainVaeArgs {
    /// Dataset in any format `bwm prepare` reads (BWM layout, LeRobot v2.1/v3.0, RoboTwin HDF5).
    #[arg(long, default_value = "../shared/data/bwm-demo")]
    pub data: PathBuf,
    /// Cameras; several are stacked top to bottom (default: the dataset's default camera).
    #[arg(long, value_delimiter = ',')]
    pub camera: Vec<String>,
    /// Use only the first N episodes (default: all).
    #[arg(long)]
    pub max_episodes: Option<usize>,
    /// Output VAE file (safetensors with its config and latent statistics).
    #[arg(long, default_value = "runs/vae/vae.safetensors")]
    pub out: PathBuf,
    /// Frame size WIDTHxHEIGHT, multiples of the spatial stride.
    #[arg(long, default_value = "64x48")]
    pub resolution: String,
    /// How frames of another aspect ratio are fitted: crop (BWM), pad or stretch.
    #[arg(long, default_value = "crop", value_parser = parse_resize)]
    pub resize: ResizeMode,
    /// Encoder and decoder base widths (Wan2.2: 160 and 256).
    #[arg(long, default_value_t = 16)]
    pub dim: i64,
    #[arg(long, default_value_t = 16)]
    pub dec_dim: i64,
    /// Pixels per latent cell along each side: 16 (Wan2.2) or 8 (one stage fewer: a 2x finer
    /// latent grid, for small frames).
    #[arg(long, default_value_t = 16)]
    pub spatial_stride: i64,
    /// Frames per training clip (1+4k).
    #[arg(long, default_value_t = 5)]
    pub clip_frames: usize,
    #[arg(long, default_value_t = 800)]
    pub steps: u64,
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    #[arg(long, default_value_t = 2e-3)]
    pub lr: f64,
    #[arg(long, default_value_t = 1e-6)]
    pub kl_weight: f64,
    /// Whole episodes (by manifest line) held out for the PSNR measurement. Without it, the
    /// last --holdout-tail of every episode's frames is held out instead.
    #[arg(long, value_delimiter = ',')]
    pub holdout: Vec<usize>,
    /// Fraction of each episode's frames (its end) held out when --holdout names no episode.
    #[arg(long, default_value_t = 0.2)]
    pub holdout_tail: f64,
    /// Do not mirror training clips left-right at random (augmentation against memorizing).
    #[arg(long)]
    pub no_flip: bool,
    /// Train on random WIDTHxHEIGHT windows (multiples of the spatial stride) of the frames instead of whole
    /// frames (augmentation against memorizing positions); PSNR is measured on whole frames.
    #[arg(long)]
    pub crop: Option<String>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, default_value = "auto")]
    pub device: String,
    /// Held-out PSNR every N steps (0: only at the end).
    #[arg(long, default_value_t = 0)]
    pub eval_every: u64,
    /// Write the decoded, resized frames (training and held-out episodes) to this safetensors file
    /// and stop: a machine without FFmpeg (the GPU machines) can then train from it with --frames.
    #[arg(long)]
    pub dump_frames: Option<PathBuf>,
    /// Train from frames written by --dump-frames instead of decoding the dataset's videos.
    #[arg(long, conflicts_with = "dump_frames")]
    pub frames: Option<PathBuf>,
}

fn to_u8(t: &Tensor) -> Tensor {
    ((t + 1.0) * 127.5).round().clamp(0.0, 255.0).to_kind(tch::Kind::Uint8)
}

fn write_frame_sets(path: &std::path::Path, data: &FrameSets) -> Result<()> {
    let mut named: Vec<(String, Tensor)> = Vec::new();
    for (split, videos) in [("train", &data.train), ("holdout", &data.holdout)] {
        for (i, v) in videos.iter().enumerate() {
            named.push((format!("{split}.{i:04}"), to_u8(v)));
        }
    }
    Tensor::write_safetensors(&named, path).with_context(|| format!("writing {}", path.display()))
}

fn read_frame_sets(path: &std::path::Path) -> Result<FrameSets> {
    let mut named = Tensor::read_safetensors(path).with_context(|| format!("reading {}", path.display()))?;
    named.sort_by(|a, b| a.0.cmp(&b.0));
    let mut data = FrameSets { train: vec![], holdout: vec![] };
    for (name, t) in named {
        ensure!(t.kind() == tch::Kind::Uint8 && t.dim() == 4 && t.size()[0] == 3, "{}: '{name}' is not a [3, F, H, W] u8 video", path.display());
        let v = t.to_kind(tch::Kind::Float) / 127.5 - 1.0;
        match name.split('.').next() {
            Some("train") => data.train.push(v),
            Some("holdout") => data.holdout.push(v),
            _ => anyhow::bail!("{}: unexpected tensor '{name}' (expected train.N / holdout.N)", path.display()),
        }
    }
    ensure!(!data.train.is_empty() && !data.holdout.is_empty(), "{}: needs training and held-out videos", path.display());
    Ok(data)
}

/// Every frame of each episode (positions in `source.episodes()`), resized, as [3, F, H, W] in [-1, 1].
pub fn episode_videos(source: &dyn EpisodeSource, episodes: &[usize], cameras: &CameraSelection, size: (u32, u32), mode: ResizeMode) -> Result<Vec<Tensor>> {
    episodes
        .iter()
        .map(|&i| {
            let length = source.episodes()[i].length;
            let frames = source.frames(i, 0..length, cameras)?;
            let resized: Vec<_> = frames.iter().map(|f| fit(f, size.0, size.1, mode)).collect();
            frames_to_tensor(&resized).with_context(|| format!("episode position {i} of {}", source.describe()))
        })
        .collect()
}

pub fn run(a: TrainVaeArgs) -> Result<()> {
    let cfg = VaeConfig::with_width(a.dim, a.dec_dim).with_spatial_stride(a.spatial_stride).context("--spatial-stride")?;
    let size = parse_resolution(&a.resolution, cfg.spatial_stride() as u32)?;
    let device = parse_device(&a.device)?;
    let data = match &a.frames {
        Some(path) => {
            let data = read_frame_sets(path)?;
            println!("train-vae: {} training and {} held-out videos from {}", data.train.len(), data.holdout.len(), path.display());
            data
        }
        None => decode_frame_sets(&a, size)?,
    };
    if let Some(path) = &a.dump_frames {
        write_frame_sets(path, &data)?;
        println!("train-vae: wrote the frames to {}", path.display());
        return Ok(());
    }
    train(&a, cfg, data, device)
}

fn decode_frame_sets(a: &TrainVaeArgs, size: (u32, u32)) -> Result<FrameSets> {
    let source = open_dataset(&a.data)?;
    let cameras = match a.camera.len() {
        0 => CameraSelection::default(),
        1 => CameraSelection::single(&a.camera[0]),
        _ => CameraSelection::stacked(&a.camera.iter().map(String::as_str).collect::<Vec<_>>()),
    };
    let n = source.episodes().len().min(a.max_episodes.unwrap_or(usize::MAX));
    ensure!(n > 0, "{}: no episodes", source.describe());
    if a.holdout.is_empty() {
        ensure!(a.holdout_tail > 0.0 && a.holdout_tail < 1.0, "--holdout-tail must lie in (0, 1), got {}", a.holdout_tail);
        let all: Vec<usize> = (0..n).collect();
        let videos = episode_videos(source.as_ref(), &all, &cameras, size, a.resize)?;
        let (mut train, mut holdout) = (Vec::new(), Vec::new());
        for v in videos {
            let f = v.size()[1];
            let held = ((f as f64 * a.holdout_tail).round() as i64).clamp(1, f - 1);
            train.push(v.narrow(1, 0, f - held));
            holdout.push(v.narrow(1, f - held, held));
        }
        println!("train-vae: {n} episodes, the last {:.0}% of each held out, frames at {}x{} ({:?})", a.holdout_tail * 100.0, size.0, size.1, a.resize);
        return Ok(FrameSets { train, holdout });
    }
    let holdout = a.holdout.clone();
    ensure!(holdout.iter().all(|&i| i < n), "--holdout {holdout:?}: the dataset has episodes 0..{n}");
    let train: Vec<usize> = (0..n).filter(|i| !holdout.contains(i)).collect();
    ensure!(!train.is_empty(), "every episode is held out; nothing to train on");
    println!("train-vae: {} episodes for training {:?}, held out {:?}, frames at {}x{} ({:?})", train.len(), train, holdout, size.0, size.1, a.resize);
    Ok(FrameSets { train: episode_videos(source.as_ref(), &train, &cameras, size, a.resize)?, holdout: episode_videos(source.as_ref(), &holdout, &cameras, size, a.resize)? })
}

fn train(a: &TrainVaeArgs, cfg: VaeConfig, data: FrameSets, device: tch::Device) -> Result<()> {
    let frames: i64 = data.train.iter().map(|t| t.size()[1]).sum();
    let stride = cfg.spatial_stride();
    println!(
        "train-vae: {frames} training frames; VAE dim {} / dec_dim {} (z {}, spatial stride {stride}), {} steps of {} clips x {} frames on {:?}",
        cfg.dim, cfg.dec_dim, cfg.z_dim, a.steps, a.batch, a.clip_frames, device
    );
    let settings = VaeTrainSettings {
        cfg,
        clip_frames: a.clip_frames,
        batch: a.batch,
        steps: a.steps,
        lr: a.lr,
        kl_weight: a.kl_weight,
        seed: a.seed,
        device,
        eval_every: a.eval_every,
        flip: !a.no_flip,
        crop: a.crop.as_deref().map(|c| parse_resolution(c, stride as u32).map(|(w, h)| (w as i64, h as i64))).transpose().context("--crop")?,
    };
    let trained = train_vae(&data, &settings, &mut |line| println!("  {line}"))?;
    save_trained_vae(&trained, &a.out)?;
    let report = &trained.report;
    println!(
        "train-vae: reconstruction PSNR {:.2} dB on held-out frames, {:.2} dB on training frames ({:.0} s); wrote {}",
        report.holdout_psnr,
        report.train_psnr,
        report.seconds,
        a.out.display()
    );
    Ok(())
}
