//! What a person looks at after a run beside the loss curve (drawn by `bwm_metrics::plot` from
//! `run_log`'s losses): a rollout video of a held-out clip with the ground truth on the left and
//! the model's frames on the right.

use std::path::Path;

use anyhow::{Context, Result};
use bwm_data::frames::{frame_strip, tensor_to_frames};
use bwm_metrics::image::psnr;
use bwm_model::vae::WanVae;
use tch::Kind;

use crate::trainer::Trainer;
use crate::validation::rollout_clip;

/// What `rollout_video` wrote and how the rollout compares with holding the last given frame.
#[derive(Debug, Clone)]
pub struct RolloutReport {
    pub path: std::path::PathBuf,
    /// Predicted frames scored (those after x0 and the history).
    pub future_frames: usize,
    /// PSNR (dB) of the model's predicted frames against the ground truth.
    pub model_psnr: f64,
    /// PSNR (dB) of the last given frame, held, against the same ground-truth frames.
    pub copy_last_psnr: f64,
}

/// Rolls out the first held-out clip (the first clip when none is held out) and writes an mp4 of
/// ground truth (left) beside the prediction (right), condition frames included, at the cache's
/// fps (a PNG contact sheet when built without video). Scores the predicted frames against the
/// ground truth next to the copy-last-frame baseline on the same frames.
pub fn rollout_video(trainer: &Trainer, vae_path: &Path, out: &Path) -> Result<RolloutReport> {
    let device = trainer.device;
    let vae = WanVae::load_any(vae_path, Kind::Float, device).with_context(|| format!("VAE {}", vae_path.display()))?;
    let clip_index = if trainer.train_clips < trainer.cache.len() { trainer.train_clips } else { 0 };
    let clip = trainer.clip(clip_index)?;
    let steps = trainer.cfg.validation.sample_steps;
    let predicted = rollout_clip(trainer, &clip.latents.unsqueeze(0), &clip.actions.unsqueeze(0), clip_index as u64, steps)?;
    let pred = tch::no_grad(|| vae.decode(&predicted))?.squeeze_dim(0).clamp(-1.0, 1.0);
    let truth = match &clip.frames {
        Some(f) => f.to_kind(Kind::Float) / 127.5 - 1.0,
        None => tch::no_grad(|| vae.decode(&clip.latents.unsqueeze(0)))?.squeeze_dim(0).clamp(-1.0, 1.0),
    };
    let (truth, pred) = (truth.to_device(tch::Device::Cpu), pred.to_device(tch::Device::Cpu));
    let frames = truth.size()[1].min(pred.size()[1]);
    let given = (1 + trainer.cache.index.history_frames as i64).min(frames - 1).max(1);
    let future = frames - given;
    let real = truth.narrow(1, given, future);
    let model_psnr = psnr(&pred.narrow(1, given, future), &real);
    let copy_last_psnr = psnr(&truth.narrow(1, given - 1, 1).expand_as(&real), &real);
    let (truth, pred) = (tensor_to_frames(&truth)?, tensor_to_frames(&pred)?);
    let frames = truth
        .into_iter()
        .zip(pred)
        .map(|(t, p)| frame_strip(&[vec![t, p]]))
        .collect::<Result<Vec<_>>>()?;
    let path = bwm_data::video::write_mp4_or_sheet(out, &frames, trainer.cache.index.fps, 16)?;
    Ok(RolloutReport { path, future_frames: future as usize, model_psnr, copy_last_psnr })
}
