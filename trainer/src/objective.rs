//! The BWM flow-matching objective (ARCHITECTURE.md, Training): per sample a timestep from the
//! shifted 1000-step grid; x0's latent clean, history latents (1-s_h) z + s_h e_h, future latents
//! (1-s) z + s e; per-frame timesteps 0 on the condition latents; target v = e - z; loss =
//! `train_weights[t]` * MSE over the future latents, in fp32, averaged over the batch. With
//! `objective.motion_weight` (not in the BWM release) the MSE is weighted per latent cell towards
//! where the clean latents change (`Objective::cell_weights`).

use anyhow::{ensure, Result};
use bwm_model::FlowSchedule;
use tch::{Kind, Tensor};

use crate::config::{ObjectiveSection, TimestepSampling};
use bwm_model::device::upload;
use crate::keyed_rng::{self, Purpose};
use crate::motion;

pub struct Objective {
    pub schedule: FlowSchedule,
    pub history_sigma: f64,
    pub condition_latents: i64,
    pub sampling: TimestepSampling,
    pub seed: u64,
    pub action_dropout: f64,
    pub motion_weight: f64,
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
    /// Per future latent cell `[B, 1, F - P, H, W]` fp32 (`objective.motion_weight`); None: all 1.
    pub cell_weights: Option<Tensor>,
    pub timestep_indices: Vec<usize>,
}

impl Objective {
    pub fn new(cfg: &ObjectiveSection, seed: u64) -> Self {
        let schedule = FlowSchedule::training(bwm_model::schedule::NUM_TRAIN_TIMESTEPS, cfg.shift);
        let history_sigma = cfg.history_sigma.unwrap_or_else(|| schedule.history_sigma());
        Self { schedule, history_sigma, condition_latents: cfg.condition_latents, sampling: cfg.timestep_sampling, seed, action_dropout: cfg.action_dropout, motion_weight: cfg.motion_weight }
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
                let sigma = 1.0 / (1.0 + (-z).exp());
                (0..n)
                    .min_by(|&a, &b| {
                        (self.schedule.sigmas[a] - sigma).abs().total_cmp(&(self.schedule.sigmas[b] - sigma).abs())
                    })
                    .unwrap_or(0)
            }
        }
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
        let sh = self.history_sigma;
        let x0 = clean.narrow(2, 0, 1);
        let history = clean.narrow(2, 1, p - 1) * (1.0 - sh) + history_noise.narrow(2, 1, p - 1).to_kind(Kind::Float) * sh;
        let future = clean.narrow(2, p, f - p);
        let future_noise = noise.narrow(2, p, f - p).to_kind(Kind::Float);
        let noised = &future * (1.0 - &sigma) + &future_noise * &sigma;
        let input = Tensor::cat(&[x0, history, noised], 2);
        let t: Vec<f32> = tids.iter().map(|&i| self.schedule.timesteps[i] as f32).collect();
        let t = upload(&Tensor::from_slice(&t), clean.device());
        let frame_timesteps = bwm_model::frame_timesteps(&t, f, p);
        let w: Vec<f32> = tids.iter().map(|&i| self.schedule.weights[i] as f32).collect();
        Ok(Prepared {
            input,
            frame_timesteps,
            target: future_noise - future,
            weights: upload(&Tensor::from_slice(&w), clean.device()),
            cell_weights: (self.motion_weight > 0.0).then(|| self.cell_weights(&clean)),
            timestep_indices: tids.to_vec(),
        })
    }

    /// Weights of the future latent cells of `clean` `[B, C, F, H, W]` fp32 (`motion::from_change`):
    /// towards the cells that changed from the latent frame before and their 8 neighbours.
    pub fn cell_weights(&self, clean: &Tensor) -> Tensor {
        let (f, p) = (clean.size()[2], self.condition_latents);
        let change = tch::no_grad(|| motion::change(&clean.narrow(2, p - 1, f - p), &clean.narrow(2, p, f - p)));
        motion::from_change(&change, self.motion_weight, 1)
    }

    /// Per-sample weighted MSE `[B]` over the future latents of `prediction` `[B, C, F, H, W]`.
    pub fn per_sample_loss(&self, prediction: &Tensor, prepared: &Prepared) -> Tensor {
        let f = prediction.size()[2];
        let p = self.condition_latents;
        let diff = prediction.narrow(2, p, f - p).to_kind(Kind::Float) - &prepared.target;
        let mse = match &prepared.cell_weights {
            None => diff.square().mean_dim(&[1i64, 2, 3, 4][..], false, Kind::Float),
            Some(w) => motion::weighted_mean(&diff.square(), w),
        };
        mse * &prepared.weights
    }

    /// The batch loss: mean of the per-sample losses.
    pub fn loss(&self, prediction: &Tensor, prepared: &Prepared) -> Tensor {
        self.per_sample_loss(prediction, prepared).mean(Kind::Float)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    fn objective(motion_weight: f64) -> Objective {
        Objective::new(&ObjectiveSection { motion_weight, ..ObjectiveSection::default() }, 0)
    }

    /// Five latent frames of 6x6 (three condition, two future), still but for one cell that
    /// changes between the last condition frame and the first future one.
    fn one_cell_changes() -> Tensor {
        let clean = Tensor::ones([1, 4, 5, 6, 6], (Kind::Float, Device::Cpu));
        let _ = clean.narrow(2, 3, 2).narrow(3, 2, 1).narrow(4, 2, 1).fill_(3.0);
        clean
    }

    #[test]
    fn cell_weights_follow_the_change_and_the_cells_beside_it() {
        let w = objective(4.0).cell_weights(&one_cell_changes());
        assert_eq!(w.size(), [1, 1, 2, 6, 6]);
        let at = |f: i64, y: i64, x: i64| w.double_value(&[0, 0, f, y, x]);
        assert!(at(0, 2, 2) > 1.0 && at(0, 1, 3) > 1.0 && at(0, 3, 1) > 1.0, "the changed cell and its neighbours");
        assert_eq!(at(0, 4, 4), 1.0);
        assert_eq!(at(0, 0, 5), 1.0);
        assert!(w.narrow(2, 1, 1).equal(&Tensor::ones([1, 1, 1, 6, 6], (Kind::Float, Device::Cpu))), "the second future frame did not change");
        assert!((w.mean(Kind::Float).double_value(&[]) - 5.0).abs() < 1e-5, "mean weight 1 + 4");
        let still = Tensor::ones([2, 4, 5, 6, 6], (Kind::Float, Device::Cpu));
        assert!(objective(4.0).cell_weights(&still).equal(&Tensor::ones([2, 1, 2, 6, 6], (Kind::Float, Device::Cpu))));
    }

    #[test]
    fn the_motion_weighted_loss_counts_an_error_where_the_clip_changes_more() {
        let clean = one_cell_changes();
        let noise = Tensor::zeros_like(&clean);
        let loss_of = |o: &Objective, cell: (i64, i64)| {
            let p = o.prepare(&clean, &noise, &noise, &[500]).unwrap();
            // The exact prediction but for one future cell, off by 1 in every channel.
            let pred = Tensor::cat(&[Tensor::zeros([1, 4, 3, 6, 6], (Kind::Float, Device::Cpu)), p.target.copy()], 2);
            let _ = pred.narrow(2, 3, 1).narrow(3, cell.0, 1).narrow(4, cell.1, 1).g_add_scalar_(1.0);
            o.per_sample_loss(&pred, &p).double_value(&[0])
        };
        let (plain, weighted) = (objective(0.0), objective(4.0));
        assert!(plain.prepare(&clean, &noise, &noise, &[500]).unwrap().cell_weights.is_none(), "weight 0 is the release's plain MSE");
        assert_eq!(loss_of(&plain, (2, 2)), loss_of(&plain, (4, 4)));
        let (moving, still) = (loss_of(&weighted, (2, 2)), loss_of(&weighted, (4, 4)));
        assert!(moving > 5.0 * still, "the changed cell {moving}, a still one {still}");
        // The weights average out: over every cell at once the weighted loss is the plain one.
        let p = weighted.prepare(&clean, &noise, &noise, &[500]).unwrap();
        let pred = Tensor::cat(&[Tensor::zeros([1, 4, 3, 6, 6], (Kind::Float, Device::Cpu)), &p.target + 1.0], 2);
        let (a, b) = (weighted.per_sample_loss(&pred, &p).double_value(&[0]), plain.per_sample_loss(&pred, &plain.prepare(&clean, &noise, &noise, &[500]).unwrap()).double_value(&[0]));
        assert!((a - b).abs() < 1e-6 * b, "{a} vs {b}");
    }
}
