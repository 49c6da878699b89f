//! `bwm reconstruct`: a dataset's frames after a round trip through a trained VAE
//! (`bwm_trainer::vae_frames::reconstruct`), the best a world model decoding with it can show.

use std::path::PathBuf;

use anyhow::{ensure, Context, Result};
use bwm_data::frames::{parse_resize, parse_resolution};
use bwm_data::{open_dataset, CameraSelection, ResizeMode};
use bwm_model::vae::WanVae;
use bwm_model::device::parse_device;
use bwm_trainer::vae_frames::{reconstruct, write_reconstructions};
use clap::Args;
use tch::Kind;

#[derive(Args)]
pub struct ReconstructArgs {
    /// Dataset in any format `bwm prepare` reads.
    #[arg(long)]
    pub data: PathBuf,
    /// The VAE (`bwm train-vae` output or the published Wan2.2 VAE).
    #[arg(long)]
    pub vae: PathBuf,
    /// Output safetensors: u8 [3, F, H, W] per episode, named `episode.<episode_index>`.
    #[arg(long)]
    pub out: PathBuf,
    /// Cameras; several are stacked top to bottom (default: the dataset's default camera).
    #[arg(long, value_delimiter = ',')]
    pub camera: Vec<String>,
    /// Only the first N episodes (default: all).
    #[arg(long)]
    pub max_episodes: Option<usize>,
    /// Frame size WIDTHxHEIGHT, multiples of the VAE's spatial stride.
    #[arg(long)]
    pub resolution: String,
    /// How frames of another aspect ratio are fitted: crop (BWM), pad or stretch.
    #[arg(long, default_value = "crop", value_parser = parse_resize)]
    pub resize: ResizeMode,
    #[arg(long, default_value = "auto")]
    pub device: String,
}

pub fn run(a: ReconstructArgs) -> Result<()> {
    let device = parse_device(&a.device)?;
    let vae = WanVae::load_any(&a.vae, Kind::Float, device).with_context(|| format!("--vae {}", a.vae.display()))?;
    let size = parse_resolution(&a.resolution, vae.cfg.spatial_stride() as u32)?;
    let source = open_dataset(&a.data)?;
    let n = source.episodes().len().min(a.max_episodes.unwrap_or(usize::MAX));
    ensure!(n > 0, "{}: no episodes", source.describe());
    let cameras = CameraSelection::from_names(&a.camera);
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let episodes: Vec<usize> = (0..n).collect();
    let every = (n / 10).max(1);
    let out = reconstruct(source.as_ref(), &episodes, &cameras, size, a.resize, &vae, device, &mut |done| {
        if done % every == 0 && done < n {
            println!("reconstruct: {done}/{n} episodes");
        }
    })?;
    write_reconstructions(&a.out, &out)?;
    let mean = out.iter().map(|r| r.psnr).sum::<f64>() / out.len() as f64;
    println!("reconstruct: {n} episodes of {} through {}: PSNR {mean:.2} dB (mean over episodes); wrote {}", source.describe(), a.vae.display(), a.out.display());
    Ok(())
}
