//! `bwm train-light-decoder`: fit a light decoder to a trained VAE's decoder on a dataset's frames
//! (`bwm_trainer::light_decoder_train`); `--light-decoder` of the world-model commands then decodes
//! with it.

use std::path::PathBuf;

use anyhow::{Context, Result};
use bwm_data::frames::parse_resolution;
use bwm_model::device::parse_device;
use bwm_model::light_decoder::LightDecoderConfig;
use bwm_model::vae::WanVae;
use bwm_trainer::light_decoder_train::{save_light_decoder, train_light_decoder, LightDecoderTrainSettings};
use clap::Args;
use tch::Kind;

use crate::train_vae::FrameArgs;

#[derive(Args)]
pub struct TrainLightDecoderArgs {
    /// The VAE whose decoder it learns to reproduce (a `bwm train-vae` output, or Wan2.2's VAE).
    #[arg(long)]
    pub vae: PathBuf,
    #[command(flatten)]
    pub frames: FrameArgs,
    /// Output file (safetensors with its config and held-out agreement in the metadata).
    #[arg(long, default_value = "runs/light-decoder.safetensors")]
    pub out: PathBuf,
    /// Channels of its three stages and of its last convolution (TAEHV's: 256,128,64,64).
    #[arg(long, value_delimiter = ',', default_value = "256,128,64,64")]
    pub widths: Vec<i64>,
    /// Residual blocks per stage.
    #[arg(long, default_value_t = 3)]
    pub blocks: i64,
    /// Frames per training clip (1+4k); default: the clip length the VAE trained on, else 33.
    #[arg(long)]
    pub clip_frames: Option<usize>,
    #[arg(long, default_value_t = 1000)]
    pub steps: u64,
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, default_value = "auto")]
    pub device: String,
    /// Held-out PSNR against the VAE's frames every N steps (0: only at the end).
    #[arg(long, default_value_t = 0)]
    pub eval_every: u64,
}

pub fn run(a: TrainLightDecoderArgs) -> Result<()> {
    let device = parse_device(&a.device)?;
    let widths: [i64; 4] = a.widths.as_slice().try_into().map_err(|_| anyhow::anyhow!("--widths takes 4 numbers (three stages and the last convolution), got {:?}", a.widths))?;
    let vae = WanVae::load_any(&a.vae, Kind::Float, device).with_context(|| format!("--vae {}", a.vae.display()))?;
    let cfg = LightDecoderConfig { widths, blocks: a.blocks, ..LightDecoderConfig::for_vae(&vae.cfg) };
    cfg.validate().context("--widths, --blocks")?;
    let size = parse_resolution(&a.frames.resolution, vae.cfg.spatial_stride() as u32)?;
    let clip_frames = a.clip_frames.or(vae.trained_clip_frames).unwrap_or(33);
    let data = a.frames.load(size, "train-light-decoder")?;
    println!(
        "train-light-decoder: widths {widths:?}, {} blocks per stage, {} steps of {} clips x {clip_frames} frames on {device:?}, against the decoder of {}",
        a.blocks,
        a.steps,
        a.batch,
        a.vae.display()
    );
    let settings = LightDecoderTrainSettings { cfg, clip_frames, batch: a.batch, steps: a.steps, lr: a.lr, seed: a.seed, device, eval_every: a.eval_every };
    let trained = train_light_decoder(&vae, &data, &settings, &mut |line| println!("  {line}"))?;
    save_light_decoder(&trained, &a.vae, &a.out)?;
    let h = trained.holdout;
    println!(
        "train-light-decoder: held-out PSNR against the VAE's decoded frames {:.2} dB; against the real frames {:.2} dB (the VAE's own round trip {:.2} dB) ({:.0} s); wrote {}",
        h.light_vs_vae,
        h.light_vs_frames,
        h.vae_vs_frames,
        trained.seconds,
        a.out.display()
    );
    Ok(())
}
