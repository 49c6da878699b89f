//! The BWM flow-matching objective (docs/architecture.md, Training): per sample a timestep from the
//! shifted 1000-step grid; x0's latent clean, history latents (1-s_h) z + s_h e_h, future latents
//! (1-s) z + s e; per-frame timesteps 0 on the condition latents; target v = e - z; loss =
//! `train_weights[t]` * MSE over the future latents, in fp32, averaged over the batch.

use anyhow::{ensure, Result};
use bwm_model::FlowSchedule;
use tch::{Kind, Tensor};

use crate::config::{ObjectiveSection, TimestepSampling};
use bwm_model::device::upload;
use crate::keyed_rng::{self, Purpose};

pub struct Objective {
    pub schedule: FlowSchedule,
    pub history_sigma: f64,
    pub condition_latents: i64,
    pub sampling: TimestepSampling,
    pub seed: u64,
    pub action_dropout: f64,
}

/// Everything random about one sample.
pub struct Draw {
    pub timestep_index: usize,
    pub noise: Tensor,
    pub history_noise: Tensor,
    /// Whether the sample sees its actions (false: the null condition, `objective.action_dropout`).
    pub keep_actions: bool,
}

/// A batch ready for the model.
pub struct Prepared {
    pub input: Tensor,
    pub frame_timesteps: Tensor,
    pub target: Tensor,
    /// `train_weights[t]` per sample, `[B]` fp32.
    pub weights: Tensor,
    pub timestep_indices: Vec<usize>,
}

impl Objective {
    pub fn new(cfg: &ObjectiveSection, seed: u64) -> Self {
        let schedule = FlowSchedule::training(bwm_model::schedule::NUM_TRAIN_TIMESTEPS, cfg.shift);
        let history_sigma = cfg.history_sigma.unwrap_or_else(|| schedule.history_sigma());
        Self { schedule, history_sigma, condition_latents: cfg.condition_latents, sampling: cfg.timestep_sampling, seed, action_dropout: cfg.action_dropout }
    }

    /// The grid index of sample `index`'s timestep.
    pub fn timestep_index(&self, index: u64) -> usize {
        let n = self.schedule.len();
        match self.sampling {
            TimestepSampling::Uniform => {
                ((keyed_rng::uniform(self.seed, index, Purpose::Timestep) * n as f64) as usize).min(n - 1)
            }
            TimestepSampling::LogitNormal { mean, std } => {
                let z = mean + std * keyed_rng::standard_normal(self.seed, index, Purpose::Timestep);
                self.nearest_index(1.0 / (1.0 + (-z).exp()))
            }
        }
    }

    /// The grid index whose sigma is nearest `sigma`.
    pub fn nearest_index(&self, sigma: f64) -> usize {
        let sigmas = &self.schedule.sigmas;
        (0..sigmas.len()).min_by(|&a, &b| (sigmas[a] - sigma).abs().total_cmp(&(sigmas[b] - sigma).abs())).unwrap_or(0)
    }

    /// The condition latents [B, P, ...] of clean latents [B, C, F, H, W] (fp32): x0's clean, the
    /// history's perturbed (1 - s_h) z + s_h e_h by `history_noise` of the latents' shape.
    pub fn condition_prefix(&self, clean: &Tensor, history_noise: &Tensor) -> Tensor {
        let (p, sh) = (self.condition_latents, self.history_sigma);
        let clean = clean.to_kind(Kind::Float);
        let history = clean.narrow(2, 1, p - 1) * (1.0 - sh) + history_noise.narrow(2, 1, p - 1).to_kind(Kind::Float) * sh;
        Tensor::cat(&[clean.narrow(2, 0, 1), history], 2)
    }

    /// The draws of global sample `index` for a clip of latent shape [C, F, H, W].
    pub fn draw(&self, index: u64, latent_shape: &[i64]) -> Draw {
        Draw {
            timestep_index: self.timestep_index(index),
            noise: keyed_rng::normal(latent_shape, self.seed, index, Purpose::Noise),
            history_noise: keyed_rng::normal(latent_shape, self.seed, index, Purpose::HistoryNoise),
            keep_actions: self.action_dropout == 0.0 || keyed_rng::uniform(self.seed, index, Purpose::ActionDropout) >= self.action_dropout,
        }
    }

    /// Builds model input, per-frame timesteps and target from clean latents [B, C, F, H, W] and
    /// the per-sample draws (noise tensors [B, C, F, H, W] on the same device).
    pub fn prepare(&self, clean: &Tensor, noise: &Tensor, history_noise: &Tensor, tids: &[usize]) -> Result<Prepared> {
        let s = clean.size();
        ensure!(s.len() == 5, "clean latents must be [B, C, F, H, W], got {s:?}");
        let (b, f, p) = (s[0], s[2], self.condition_latents);
        ensure!(tids.len() as i64 == b, "{} timesteps for a batch of {b}", tids.len());
        ensure!(f > p, "clips have {f} latent frames; the objective needs more than the {p} condition latents");
        ensure!(noise.size() == s && history_noise.size() == s, "noise must have the latents' shape {s:?}");
        let clean = clean.to_kind(Kind::Float);
        let sigmas: Vec<f32> = tids.iter().map(|&i| self.schedule.sigmas[i] as f32).collect();
        let sigma = upload(&Tensor::from_slice(&sigmas), clean.device()).view([b, 1, 1, 1, 1]);
        let prefix = self.condition_prefix(&clean, history_noise);
        let future = clean.narrow(2, p, f - p);
        let future_noise = noise.narrow(2, p, f - p).to_kind(Kind::Float);
        let noised = &future * (1.0 - &sigma) + &future_noise * &sigma;
        let input = Tensor::cat(&[prefix, noised], 2);
        let t: Vec<f32> = tids.iter().map(|&i| self.schedule.timesteps[i] as f32).collect();
        let t = upload(&Tensor::from_slice(&t), clean.device());
        let frame_timesteps = bwm_model::frame_timesteps(&t, f, p);
        let w: Vec<f32> = tids.iter().map(|&i| self.schedule.weights[i] as f32).collect();
        Ok(Prepared {
            input,
            frame_timesteps,
            target: future_noise - future,
            weights: upload(&Tensor::from_slice(&w), clean.device()),
            timestep_indices: tids.to_vec(),
        })
    }

    /// Per-sample weighted MSE `[B]` over the future latents of `prediction` `[B, C, F, H, W]`.
    pub fn per_sample_loss(&self, prediction: &Tensor, prepared: &Prepared) -> Tensor {
        let f = prediction.size()[2];
        let p = self.condition_latents;
        let diff = prediction.narrow(2, p, f - p).to_kind(Kind::Float) - &prepared.target;
        diff.square().mean_dim(&[1i64, 2, 3, 4][..], false, Kind::Float) * &prepared.weights
    }

    /// The batch loss: mean of the per-sample losses.
    pub fn loss(&self, prediction: &Tensor, prepared: &Prepared) -> Tensor {
        self.per_sample_loss(prediction, prepared).mean(Kind::Float)
    }
}
