//! What a person looks at after a run beside the loss curve (drawn by `bwm_metrics::plot` from
//! `run_log`'s losses): a rollout video of a held-out clip with the ground truth on the left and
//! the model's frames on the right.

use std::path::Path;

use anyhow::{Context, Result};
use bwm_data::frames::{frame_strip, tensor_to_frames};
use bwm_model::vae::WanVae;
use tch::{Kind, Tensor};

use crate::trainer::Trainer;
use crate::validation::rollout_clips;

/// What `rollout_video` wrote and how the held-out rollouts compare with holding the last given
/// frame.
#[derive(Debug, Clone)]
pub struct RolloutReport {
    pub path: std::path::PathBuf,
    /// Held-out clips rolled out and scored (all of them; the first clip when none is held out).
    pub clips: usize,
    /// Predicted frames per clip (those after x0 and the history).
    pub future_frames: usize,
    /// Against the VAE's reconstruction of the true frames (what the DiT is trained to produce:
    /// its latents decoded), so that the VAE's own blur does not enter the comparison.
    pub decoded: Scores,
    /// Against the recorded frames (when the cache keeps them, `bwm prepare --keep-frames`).
    pub recorded: Option<Scores>,
    /// The VAE's reconstruction against the recorded frames over the same future frames: the best
    /// PSNR any world model decoding with this VAE can reach there.
    pub vae_ceiling_psnr: Option<f64>,
}

/// PSNR (dB) of the model's predicted future frames and of the last given frame held over them,
/// both against the same ground truth, from the mean squared error over every scored frame.
#[derive(Debug, Clone, Copy)]
pub struct Scores {
    pub model_psnr: f64,
    pub copy_last_psnr: f64,
}

/// Sums of squared errors over the scored frames.
#[derive(Default)]
struct Sse {
    model: f64,
    copy_last: f64,
    values: f64,
}

impl Sse {
    fn add(&mut self, pred: &Tensor, held: &Tensor, truth: &Tensor) {
        let sse = |a: &Tensor| (a - truth).square().sum(Kind::Double).double_value(&[]);
        self.model += sse(pred);
        self.copy_last += sse(held);
        self.values += truth.numel() as f64;
    }

    fn scores(&self) -> Scores {
        let db = |sse: f64| 10.0 * (4.0 / (sse / self.values).max(1e-12)).log10();
        Scores { model_psnr: db(self.model), copy_last_psnr: db(self.copy_last) }
    }
}

/// Rolls out every held-out clip (the first clip when none is held out), in batches, and scores
/// the predicted frames against the ground truth next to the copy-last-frame baseline on the same
/// frames. Writes an mp4 (a PNG contact sheet when built without video) at the cache's fps of the
/// held-out clip whose true frames move most after the last given frame (so that the video shows
/// the predicted motion following the actions): ground truth left, the VAE's reconstruction of it
/// in the middle, the prediction right, condition frames included. The clip shown is chosen by the
/// true frames alone, never by the model's output.
pub fn rollout_video(trainer: &Trainer, vae_path: &Path, out: &Path) -> Result<RolloutReport> {
    const BATCH: usize = 8;
    let device = trainer.device;
    let vae = WanVae::load_any(vae_path, Kind::Float, device).with_context(|| format!("VAE {}", vae_path.display()))?;
    let first = if trainer.train_clips < trainer.cache.len() { trainer.train_clips } else { 0 };
    let last = if trainer.train_clips < trainer.cache.len() { trainer.cache.len() } else { 1 };
    let steps = trainer.cfg.validation.sample_steps;
    let given = 1 + trainer.cache.index.history_frames as i64;
    let (mut decoded, mut recorded, mut ceiling) = (Sse::default(), Sse::default(), 0.0f64);
    let mut shown: Option<(f64, Tensor, Tensor, Option<Tensor>)> = None;
    let mut future = 0;
    let mut start = first;
    while start < last {
        let indices: Vec<usize> = (start..last.min(start + BATCH)).collect();
        start += indices.len();
        let clips = indices.iter().map(|&i| trainer.clip(i)).collect::<Result<Vec<_>>>()?;
        let latents = Tensor::stack(&clips.iter().map(|c| c.latents.shallow_clone()).collect::<Vec<_>>(), 0);
        let actions = Tensor::stack(&clips.iter().map(|c| c.actions.shallow_clone()).collect::<Vec<_>>(), 0);
        let keys: Vec<u64> = indices.iter().map(|&i| i as u64).collect();
        let predicted = rollout_clips(trainer, &latents, &actions, &keys, steps)?;
        let pred = tch::no_grad(|| vae.decode(&predicted))?.clamp(-1.0, 1.0).to_device(tch::Device::Cpu);
        let recon = tch::no_grad(|| vae.decode(&latents))?.clamp(-1.0, 1.0).to_device(tch::Device::Cpu);
        for (j, clip) in clips.iter().enumerate() {
            let (pred, recon) = (pred.get(j as i64), recon.get(j as i64));
            let frames = recon.size()[1].min(pred.size()[1]);
            anyhow::ensure!(frames > given, "clip {} has {frames} frames, none after the {given} given", indices[j]);
            future = frames - given;
            let scored = |t: &Tensor| t.narrow(1, given, future);
            let held = |t: &Tensor| t.narrow(1, given - 1, 1).expand_as(&scored(t));
            decoded.add(&scored(&pred), &held(&recon), &scored(&recon));
            let real = clip.frames.as_ref().map(|f| f.to_device(tch::Device::Cpu).to_kind(Kind::Float) / 127.5 - 1.0);
            let motion = match &real {
                Some(real) => {
                    recorded.add(&scored(&pred), &held(real), &scored(real));
                    ceiling += (scored(&recon) - scored(real)).square().sum(Kind::Double).double_value(&[]);
                    (scored(real) - held(real)).abs().mean(Kind::Double).double_value(&[])
                }
                None => (scored(&recon) - held(&recon)).abs().mean(Kind::Double).double_value(&[]),
            };
            if shown.as_ref().is_none_or(|(m, ..)| motion > *m) {
                shown = Some((motion, recon.narrow(1, 0, frames), pred.narrow(1, 0, frames), real.map(|r| r.narrow(1, 0, frames))));
            }
        }
    }
    let (_, recon, pred, real) = shown.context("no clip to roll out")?;
    let columns: Vec<Tensor> = real.into_iter().chain([recon, pred]).collect();
    let columns = columns.iter().map(tensor_to_frames).collect::<Result<Vec<_>>>()?;
    let frames = (0..columns[0].len())
        .map(|f| frame_strip(&[columns.iter().map(|c| c[f].clone()).collect()]))
        .collect::<Result<Vec<_>>>()?;
    let path = bwm_data::video::write_mp4_or_sheet(out, &frames, trainer.cache.index.fps, 16)?;
    let has_real = recorded.values > 0.0;
    Ok(RolloutReport {
        path,
        clips: last - first,
        future_frames: future as usize,
        decoded: decoded.scores(),
        recorded: has_real.then(|| recorded.scores()),
        vae_ceiling_psnr: has_real.then(|| 10.0 * (4.0 / (ceiling / recorded.values).max(1e-12)).log10()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The scores pool the squared error over every scored value of every clip (not an average of
    /// per-clip dB, which a static clip's near-perfect baseline would dominate), and a held frame
    /// that equals the truth scores the cap of a perfect match (MSE floored at 1e-12).
    #[test]
    fn scores_pool_the_error_over_all_clips() {
        let mut sse = Sse::default();
        let truth = Tensor::zeros([3, 2, 4, 4], (Kind::Float, tch::Device::Cpu));
        // Clip 1: the model off by 0.2 everywhere, the baseline exact.
        sse.add(&(&truth + 0.2), &truth, &truth);
        // Clip 2: the model exact, the baseline off by 0.4 everywhere.
        sse.add(&truth, &(&truth + 0.4), &truth);
        let s = sse.scores();
        let db = |mse: f64| 10.0 * (4.0 / mse).log10();
        assert!((s.model_psnr - db(0.04 / 2.0)).abs() < 1e-5, "{s:?}");
        assert!((s.copy_last_psnr - db(0.16 / 2.0)).abs() < 1e-5, "{s:?}");
        let mut exact = Sse::default();
        exact.add(&(&truth + 0.1), &truth, &truth);
        assert!((exact.scores().copy_last_psnr - 10.0 * 4e12f64.log10()).abs() < 1e-9);
    }
}
