//! `bwm train-vae`: fit a small Wan2.2-architecture VAE to a dataset's frames
//! (`bwm_trainer::vae_frames` selects them, `bwm_trainer::vae_train` trains).

use std::path::PathBuf;

use anyhow::{bail, ensure, Context, Result};
use bwm_data::frames::{parse_resize, parse_resolution};
use bwm_data::{open_dataset, CameraSelection, ResizeMode};
use bwm_model::vae::VaeConfig;
use bwm_model::device::{parse_device, parse_kind};
use bwm_trainer::vae_frames::FrameSelection;
use bwm_trainer::vae_train::{save_trained_vae, train_best_vae, FrameSets, ReconLoss, VaeTrainSettings, REMOVED_MOTION_LOSS};
use clap::Args;

#[derive(Args)]
pub struct TrainVaeArgs {
    #[command(flatten)]
    pub frames: FrameArgs,
    /// Output VAE file (safetensors with its config and latent statistics).
    #[arg(long, default_value = "runs/vae/vae.safetensors")]
    pub out: PathBuf,
    /// Encoder and decoder base widths (Wan2.2: 160 and 256).
    #[arg(long, default_value_t = 16)]
    pub dim: i64,
    #[arg(long, default_value_t = 16)]
    pub dec_dim: i64,
    /// Pixels per latent cell along each side: 16 (Wan2.2) or 8 (one stage fewer: a 2x finer
    /// latent grid, for small frames).
    #[arg(long, default_value_t = 16)]
    pub spatial_stride: i64,
    /// Latent channels: 48 (Wan2.2), or fewer for a finer grid (Wan2.1's VAE: 16 at stride 8).
    /// The DiT's `model.dit.in_dim` and `out_dim` must match.
    #[arg(long, default_value_t = 48)]
    pub z_dim: i64,
    /// Frames per training clip (1+4k). Train on clips as long as the ones the VAE will encode
    /// and decode (`bwm prepare`'s 1 + H + K): a VAE reconstructs frames past its training clip
    /// poorly, and `bwm prepare` warns when its clips are longer.
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
    /// Do not mirror training clips left-right at random (augmentation against memorizing).
    #[arg(long)]
    pub no_flip: bool,
    /// Train on random WIDTHxHEIGHT windows (multiples of the spatial stride) of the frames instead of whole
    /// frames (augmentation against memorizing positions); PSNR is measured on whole frames.
    #[arg(long)]
    pub crop: Option<String>,
    /// Initial weights and clip order (the first candidate's with --candidates).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Train this many VAEs, from seeds --seed, --seed + 1, ..., and keep the one with the best
    /// held-out reconstruction PSNR (the file records every candidate's and the step it was
    /// measured at).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub candidates: u64,
    /// With --candidates: train each candidate this many steps, then only the best held-out PSNR
    /// on to --steps (N candidates cost (N - 1) x this many steps more than one VAE). Default (or at
    /// least --steps): every candidate trains all --steps, one after another, and the best at the
    /// end is kept.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub choose_at: Option<u64>,
    #[arg(long, default_value = "auto")]
    pub device: String,
    /// Weights and activations in f32, or bf16 with fp32 master weights in the optimizer (losses
    /// in f32 either way; the file holds f32 weights).
    #[arg(long, default_value = "f32")]
    pub dtype: String,
    /// Reconstruction loss: mse (what PSNR measures) or l1 (as Wan's VAE trains; errs less
    /// towards blurring a small object into its surroundings).
    #[arg(long, default_value = "mse")]
    pub recon_loss: ReconLoss,
    /// Removed with the motion loss it weighed (issue 69): refused, saying why.
    #[arg(long, hide = true, allow_negative_numbers = true)]
    pub motion_weight: Option<String>,
    /// Record the training step (forward and backward) once as a CUDA graph and replay it after
    /// two eager warm-up steps (CUDA only). The small VAE's step is bound by launching its
    /// kernels, which a replay does in one launch; the results are the eager step's.
    #[arg(long)]
    pub cuda_graph: bool,
    /// Held-out PSNR every N steps (0: only at the end).
    #[arg(long, default_value_t = 0)]
    pub eval_every: u64,
    /// Write the decoded, resized frames (training and held-out episodes) to this safetensors file
    /// and stop: a machine without FFmpeg (the GPU machines) can then train from it with --frames.
    #[arg(long, conflicts_with = "frames_file")]
    pub dump_frames: Option<PathBuf>,
}

/// Where the training and held-out frames come from: a dataset's episodes (decoded and resized),
/// or a file of frames `bwm train-vae --dump-frames` wrote. Shared with `bwm train-light-decoder`.
#[derive(Args)]
pub struct FrameArgs {
    /// Dataset in any format `bwm prepare` reads (BWM layout, LeRobot v2.1/v3.0, RoboTwin HDF5).
    #[arg(long, default_value = "data/bwm-demo")]
    pub data: PathBuf,
    /// Cameras; several are stacked top to bottom (default: the dataset's default camera).
    #[arg(long, value_delimiter = ',')]
    pub camera: Vec<String>,
    /// Use only the first N episodes (default: all).
    #[arg(long)]
    pub max_episodes: Option<usize>,
    /// Frame size WIDTHxHEIGHT, multiples of the spatial stride.
    #[arg(long, default_value = "64x48")]
    pub resolution: String,
    /// How frames of another aspect ratio are fitted: crop (BWM), pad or stretch.
    #[arg(long, default_value = "crop", value_parser = parse_resize)]
    pub resize: ResizeMode,
    /// Whole episodes (by manifest line) held out for the PSNR measurement. Without it, the
    /// last --holdout-tail of every episode's frames is held out instead.
    #[arg(long, value_delimiter = ',')]
    pub holdout: Vec<usize>,
    /// Fraction of each episode's frames (its end) held out when --holdout names no episode.
    #[arg(long, default_value_t = 0.2)]
    pub holdout_tail: f64,
    /// Train from frames written by `bwm train-vae --dump-frames` instead of decoding the dataset's
    /// videos (their size must be --resolution).
    #[arg(long = "frames", id = "frames_file", value_name = "FILE")]
    pub file: Option<PathBuf>,
}

impl FrameArgs {
    /// The frame sets at `size` (width, height), from the file or the dataset; `who` names the
    /// command in what it prints.
    pub fn load(&self, size: (u32, u32), who: &str) -> Result<FrameSets> {
        match &self.file {
            Some(path) => {
                let data = FrameSets::read(path)?;
                ensure!(
                    data.size() == size,
                    "{}: its frames are {}x{}, --resolution asks for {}x{}",
                    path.display(),
                    data.size().0,
                    data.size().1,
                    size.0,
                    size.1
                );
                println!("{who}: {} training and {} held-out videos from {}", data.train.len(), data.holdout.len(), path.display());
                Ok(data)
            }
            None => {
                let source = open_dataset(&self.data)?;
                let cameras = CameraSelection::from_names(&self.camera);
                let selection = FrameSelection { cameras, max_episodes: self.max_episodes, holdout: self.holdout.clone(), holdout_tail: self.holdout_tail, size, resize: self.resize };
                FrameSets::from_dataset(source.as_ref(), &selection)
            }
        }
    }
}

pub fn run(a: TrainVaeArgs) -> Result<()> {
    if a.motion_weight.is_some() {
        bail!("--motion-weight was removed with the motion loss it weighed (--recon-loss motion, issue 69) because {REMOVED_MOTION_LOSS}");
    }
    let cfg = VaeConfig { z_dim: a.z_dim, ..VaeConfig::with_width(a.dim, a.dec_dim) };
    let cfg = cfg.with_spatial_stride(a.spatial_stride).context("--spatial-stride")?;
    cfg.validate().context("--dim, --dec-dim, --z-dim")?;
    let size = parse_resolution(&a.frames.resolution, cfg.spatial_stride() as u32)?;
    let device = parse_device(&a.device)?;
    let dtype = parse_kind(&a.dtype).context("--dtype")?;
    let data = a.frames.load(size, "train-vae")?;
    if let Some(path) = &a.dump_frames {
        data.write(path)?;
        println!("train-vae: wrote the frames to {}", path.display());
        return Ok(());
    }
    train(&a, cfg, data, device, dtype)
}

fn train(a: &TrainVaeArgs, cfg: VaeConfig, data: FrameSets, device: tch::Device, dtype: tch::Kind) -> Result<()> {
    let frames: i64 = data.train.iter().map(|t| t.size()[1]).sum();
    let stride = cfg.spatial_stride();
    println!(
        "train-vae: {frames} training frames; VAE dim {} / dec_dim {} (z {}, spatial stride {stride}), {} steps of {} clips x {} frames on {:?} in {}, {} loss",
        cfg.dim, cfg.dec_dim, cfg.z_dim, a.steps, a.batch, a.clip_frames, device, a.dtype, a.recon_loss
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
        dtype,
        recon_loss: a.recon_loss,
        cuda_graph: a.cuda_graph,
    };
    let end = a.seed.checked_add(a.candidates).with_context(|| format!("--seed {} + --candidates {} is past the largest seed", a.seed, a.candidates))?;
    let seeds: Vec<u64> = (a.seed..end).collect();
    let trained = train_best_vae(&data, &settings, &seeds, a.choose_at, &mut |line| println!("  {line}"))?;
    save_trained_vae(&trained, &a.out)?;
    let report = &trained.report;
    let kept = if seeds.len() > 1 { format!("the best of {} seeds, seed {}: ", seeds.len(), report.seed) } else { String::new() };
    println!(
        "train-vae: {kept}reconstruction PSNR {:.2} dB on held-out frames, {:.2} dB on training frames ({:.0} s); wrote {}",
        report.holdout_psnr,
        report.train_psnr,
        report.seconds,
        a.out.display()
    );
    Ok(())
}
