//! Validation: roll out each held-out clip from its condition latents and actions, and compare
//! the predicted future with the real one: latent MSE always; PSNR, SSIM and a frame strip
//! (ground truth over prediction) when a VAE is configured. Beside it, the action sensitivity:
//! the held-out loss with the clips' own actions, another clip's and zero actions.

use std::ops::Range;
use std::path::PathBuf;

use anyhow::{Context, Result};
use bwm_data::frames::{frame_strip, tensor_to_frames};
use bwm_data::latent_cache::{Clip, LatentCache};
use bwm_metrics::image::{psnr, ssim};
use bwm_model::sampler::{sample_chunk, Eager};
use bwm_model::BwmModel;
use bwm_model::vae::WanVae;
use bwm_model::FlowSchedule;
use tch::{Device, Kind, Tensor};

use crate::config::RunConfig;
use crate::keyed_rng::{self, Purpose};
use crate::objective::Objective;
use crate::tensorboard::EventWriter;

/// What validation reads from the run it validates (`Trainer` is one).
pub trait ValidationRun {
    fn config(&self) -> &RunConfig;
    fn model(&self) -> &BwmModel;
    fn objective(&self) -> &Objective;
    fn device(&self) -> Device;
    fn cache(&self) -> &LatentCache;
    /// Positions in the cache of the held-out clips.
    fn validation_clips(&self) -> Range<usize>;
    /// Clip `i` of the cache with its latents (encoded now for a raw cache).
    fn clip(&self, i: usize) -> Result<Clip>;
    /// Clip `i`'s actions alone (without its latents, or a raw clip's encode).
    fn clip_actions(&self, i: usize) -> Result<Tensor>;
    fn out_path(&self, name: &str) -> PathBuf;
    fn events(&mut self) -> Option<&mut EventWriter>;
}

pub struct ValidationReport {
    pub latent_mse: f64,
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    pub strip: Option<std::path::PathBuf>,
    /// How much the held-out loss depends on the actions.
    pub actions: ActionGap,
}

/// The flow-matching loss of the held-out clips on fixed draws (the same noise and timesteps in
/// each), with their own actions, with another held-out clip's actions, and with zero actions: a
/// model that uses its actions predicts worse with the wrong ones.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct ActionGap {
    pub loss_own_actions: f64,
    pub loss_other_actions: f64,
    pub loss_zero_actions: f64,
}

impl ActionGap {
    /// How much worse other clips' actions make the loss, as a fraction of the loss with the
    /// clips' own (0: the actions are ignored).
    pub fn relative_gap(&self) -> f64 {
        (self.loss_other_actions - self.loss_own_actions) / self.loss_own_actions.max(1e-12)
    }
}

/// Below this relative gap the actions count as unused (`ActionGap::relative_gap`).
pub const NEGLIGIBLE_ACTION_GAP: f64 = 0.01;

/// Keys of the held-out loss draws: apart from every training sample's index.
const VALIDATION_DRAW: u64 = 1 << 62;

/// Summed losses of one batch of held-out clips (`clean` [B, ...] with their `actions`; the batch
/// starts at position `start` of `held_out`) on keyed draws with their own, other and zero
/// actions.
fn action_losses(run: &(impl ValidationRun + ?Sized), held_out: &[usize], start: usize, clean: &Tensor, actions: &Tensor) -> Result<[f64; 3]> {
    let (model, objective) = (run.model(), run.objective());
    let kind = model.store.kind();
    let n = held_out.len();
    let indices = &held_out[start..start + clean.size()[0] as usize];
    // Each clip's stand-in: the held-out clip half the set away (its actions alone are read); a
    // lone clip's own actions reversed in time.
    let others = (0..indices.len())
        .map(|j| match n {
            1 => Ok(actions.get(j as i64).flip([0])),
            _ => run.clip_actions(held_out[(start + j + (n / 2).max(1)) % n]),
        })
        .collect::<Result<Vec<_>>>()?;
    let other_actions = Tensor::stack(&others, 0);
    let shape = clean.size()[1..].to_vec();
    let draws: Vec<_> = indices.iter().map(|&i| objective.draw(VALIDATION_DRAW | i as u64, &shape)).collect();
    let stack = |f: &dyn Fn(&crate::objective::Draw) -> Tensor| Tensor::stack(&draws.iter().map(f).collect::<Vec<_>>(), 0).to_device(clean.device());
    let (noise, history_noise) = (stack(&|d| d.noise.shallow_clone()), stack(&|d| d.history_noise.shallow_clone()));
    let tids: Vec<usize> = draws.iter().map(|d| d.timestep_index).collect();
    let prepared = objective.prepare(&clean, &noise, &history_noise, &tids)?;
    let input = prepared.input.to_kind(kind);
    let loss = |a: &Tensor| -> Result<f64> {
        let prediction = tch::no_grad(|| model.forward(&input, &prepared.frame_timesteps, a))?;
        Ok(objective.per_sample_loss(&prediction, &prepared).sum(Kind::Double).double_value(&[]))
    };
    Ok([loss(actions)?, loss(&other_actions)?, loss(&actions.zeros_like())?])
}

impl ValidationReport {
    pub fn summary_line(&self, step: u64) -> String {
        let mut s = format!("validation @ step {step}: future latent MSE {:.5}", self.latent_mse);
        if let (Some(p), Some(q)) = (self.psnr, self.ssim) {
            s += &format!("  PSNR {p:.2} dB  SSIM {q:.4}");
        }
        let a = &self.actions;
        s += &format!(
            "  loss with own / other / zero actions {:.5} / {:.5} / {:.5} (gap {:+.1}%)",
            a.loss_own_actions,
            a.loss_other_actions,
            a.loss_zero_actions,
            100.0 * a.relative_gap()
        );
        if let Some(path) = &self.strip {
            s += &format!("  strip {}", path.display());
        }
        s
    }
}

/// Predicted latents of one clip: condition prefix (clean x0, history perturbed with a fixed
/// draw) re-imposed at each of `steps` sampler steps from keyed noise.
pub fn rollout_clip(run: &(impl ValidationRun + ?Sized), clean: &Tensor, actions: &Tensor, key: u64, steps: usize) -> Result<Tensor> {
    rollout_clips(run, clean, actions, &[key], steps)
}

/// `rollout_clip` for a batch of clips [B, ...] in one sampling loop, clip i drawing its noise
/// from `keys[i]` as it would alone.
pub fn rollout_clips(run: &(impl ValidationRun + ?Sized), clean: &Tensor, actions: &Tensor, keys: &[u64], steps: usize) -> Result<Tensor> {
    let p = run.objective().condition_latents;
    let mut shape = clean.size();
    anyhow::ensure!(shape[0] == keys.len() as i64, "{} clips but {} noise keys", shape[0], keys.len());
    shape[0] = 1;
    let seed = run.config().run.seed;
    let draw = |salt: u64| Tensor::cat(&keys.iter().map(|&k| keyed_rng::normal(&shape, seed, k | salt, Purpose::Validation)).collect::<Vec<_>>(), 0).to_device(clean.device());
    let (history_noise, noise) = (draw(0), draw(1 << 63));
    let sh = run.objective().history_sigma;
    let prefix = Tensor::cat(
        &[clean.narrow(2, 0, 1), clean.narrow(2, 1, p - 1) * (1.0 - sh) + history_noise.narrow(2, 1, p - 1) * sh],
        2,
    );
    let schedule = FlowSchedule::inference(steps, run.config().objective.shift).with_solver(run.config().validation.solver);
    let kind = run.model().store.kind();
    let out = tch::no_grad(|| {
        sample_chunk(&mut Eager, run.model(), &prefix.to_kind(kind), &noise.to_kind(kind), actions, &schedule, run.config().validation.guidance, &mut |_, _, _| {})
    })?;
    Ok(out.to_kind(Kind::Float))
}

/// Validates `run` at `step` over its held-out clips; writes the strip and the TensorBoard scalars.
pub fn run(run: &mut (impl ValidationRun + ?Sized), step: u64) -> Result<ValidationReport> {
    let device = run.device();
    let cfg = run.config().validation.clone();
    let vae = match &cfg.vae {
        Some(path) => Some(WanVae::load_any(path, Kind::Float, device).with_context(|| format!("validation.vae {}", path.display()))?),
        None => None,
    };
    let p = run.objective().condition_latents;
    let future_frames = run.cache().index.future_frames;
    let condition_pixels = run.cache().index.pixel_frames - future_frames;
    let (mut mse_sum, mut psnr_sum, mut ssim_sum, mut n) = (0.0, 0.0, 0.0, 0usize);
    let mut strip_rows = Vec::new();
    // Held-out clips go through the sampler a training micro-batch at a time: one clip per loop
    // made validation cost more than the training between two validations on small models.
    let batch = run.config().train.micro_batch.max(1);
    let held_out: Vec<usize> = run.validation_clips().collect();
    // Each clip is read once: its loss with own, other and zero actions, and its rollout.
    let mut losses = [0.0; 3];
    for (start, indices) in (0..).step_by(batch).zip(held_out.chunks(batch)) {
        let clips = indices.iter().map(|&i| run.clip(i)).collect::<Result<Vec<_>>>()?;
        let clean = Tensor::stack(&clips.iter().map(|c| c.latents.shallow_clone()).collect::<Vec<_>>(), 0);
        let actions = Tensor::stack(&clips.iter().map(|c| c.actions.shallow_clone()).collect::<Vec<_>>(), 0);
        for (sum, l) in losses.iter_mut().zip(action_losses(run, &held_out, start, &clean, &actions)?) {
            *sum += l;
        }
        let keys: Vec<u64> = indices.iter().map(|&i| i as u64).collect();
        let predicted = rollout_clips(run, &clean, &actions, &keys, cfg.sample_steps)?;
        let f = clean.size()[2];
        let err = (predicted.narrow(2, p, f - p) - clean.narrow(2, p, f - p)).square();
        mse_sum += err.flatten(1, -1).mean_dim(1, false, Kind::Double).sum(Kind::Double).double_value(&[]);
        n += clips.len();
        if let Some(vae) = &vae {
            let decoded = tch::no_grad(|| vae.decode(&predicted))?.clamp(-1.0, 1.0);
            for (j, clip) in clips.iter().enumerate() {
                let pred_px = decoded.get(j as i64);
                let truth_px = match &clip.frames {
                    Some(frames) => frames.to_kind(Kind::Float) / 127.5 - 1.0,
                    None => tch::no_grad(|| vae.decode(&clean.narrow(0, j as i64, 1)))?.squeeze_dim(0).clamp(-1.0, 1.0),
                };
                let future = |t: &Tensor| t.narrow(1, condition_pixels as i64, future_frames as i64);
                let (pf, tf) = (future(&pred_px), future(&truth_px));
                psnr_sum += psnr(&pf, &tf);
                ssim_sum += ssim(&pf, &tf);
                if strip_rows.is_empty() {
                    let pick = |t: &Tensor| -> Result<Vec<image::RgbImage>> {
                        let frames = tensor_to_frames(&t.to_device(Device::Cpu))?;
                        let stride = (frames.len() / 8).max(1);
                        Ok(frames.into_iter().step_by(stride).take(8).collect())
                    };
                    strip_rows = vec![pick(&tf)?, pick(&pf)?];
                }
            }
        }
    }
    let held = held_out.len().max(1) as f64;
    let actions = ActionGap { loss_own_actions: losses[0] / held, loss_other_actions: losses[1] / held, loss_zero_actions: losses[2] / held };
    let mut report = ValidationReport { latent_mse: mse_sum / n as f64, psnr: None, ssim: None, strip: None, actions };
    if vae.is_some() {
        report.psnr = Some(psnr_sum / n as f64);
        report.ssim = Some(ssim_sum / n as f64);
        let strip = frame_strip(&strip_rows)?;
        let dir = run.out_path("validation");
        std::fs::create_dir_all(&dir)?;
        let path = dir.join(format!("step-{step:08}.png"));
        strip.save(&path).with_context(|| format!("writing {}", path.display()))?;
        if let Some(ev) = run.events() {
            ev.image_rgb("validation/truth_over_prediction", &strip, step)?;
        }
        report.strip = Some(path);
    }
    if let Some(ev) = run.events() {
        ev.scalar("validation/latent_mse", report.latent_mse, step)?;
        ev.scalar("validation/loss_own_actions", report.actions.loss_own_actions, step)?;
        ev.scalar("validation/loss_other_actions", report.actions.loss_other_actions, step)?;
        ev.scalar("validation/loss_zero_actions", report.actions.loss_zero_actions, step)?;
        ev.scalar("validation/action_gap", report.actions.relative_gap(), step)?;
        if let (Some(p), Some(s)) = (report.psnr, report.ssim) {
            ev.scalar("validation/psnr", p, step)?;
            ev.scalar("validation/ssim", s, step)?;
        }
        ev.flush()?;
    }
    Ok(report)
}
