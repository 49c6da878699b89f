//! Step distillation (`[distill]`): the run's model, the student, learns to take in one Euler step
//! what a frozen teacher takes in `teacher_substeps`, on the student's own grid of
//! `student_steps` points, with BWM's conditioning unchanged (x0's latent clean, the history
//! latents perturbed as in training, the actions).
//!
//! Per sample: noise for the future latents, one segment i of the student's grid (drawn), the
//! teacher's Euler steps from the noise at sigma 1 down its finer grid (`student_steps` x
//! `teacher_substeps` steps, the student's points among them) to sigma_i and on to sigma_{i+1}; the
//! student sees the teacher's state x_i at sigma_i and is trained towards the velocity that carries
//! it to x_{i+1} in one step, (x_{i+1} - x_i) / (sigma_{i+1} - sigma_i). One segment of one step
//! (`student_steps = 1`) is the one-step distillation of InstaFlow (Liu et al. 2023,
//! gnobitab/InstaFlow, read for this): regress the teacher's noise-to-sample map, here as the
//! velocity of one Euler step from the noise. Chosen over DMD2 (a second "fake score" network and
//! a critic, trained against each other: twice the memory of the trained weights and an unstable
//! game) and consistency distillation (a target network and its own parameterisation): it needs
//! the teacher's forward passes only, trains the velocity the sampler already reads, and the
//! futures of a world model conditioned on its history and actions are close to deterministic
//! (the Meta-World model's 4 Euler steps land within 0.04 dB of its 50), where regressing the
//! teacher's map loses little to the averaging a regression does over a multimodal one.

use anyhow::{ensure, Context, Result};
use bwm_model::{BwmModel, FlowSchedule, ModelConfig};
use tch::{Device, Kind, Tensor};

use crate::config::DistillSection;
use crate::keyed_rng::{self, Purpose};
use crate::objective::{Objective, Prepared};
use bwm_model::device::upload;

pub struct Distillation {
    teacher: BwmModel,
    /// The teacher's grid: `student_steps` x `teacher_substeps` sigmas from 1 down (0 excluded).
    fine: Vec<f64>,
    substeps: usize,
    student_steps: usize,
    seed: u64,
}

impl Distillation {
    /// The teacher's weights (any layout `bwm convert` reads) for the run's model, frozen, in
    /// `kind` on `device`; its grid at the run's `shift`.
    pub fn new(cfg: &DistillSection, model_cfg: &ModelConfig, shift: f64, kind: Kind, device: Device, seed: u64) -> Result<Self> {
        let path = cfg.teacher.to_string_lossy();
        let opened = bwm_checkpoints::open::open_any(&path).with_context(|| format!("distill.teacher {path}"))?;
        let (store, teacher_cfg, what) = bwm_checkpoints::open::weight_store(opened, Some(model_cfg), kind, device).with_context(|| format!("distill.teacher {path}"))?;
        ensure!(
            teacher_cfg.dit == model_cfg.dit && teacher_cfg.action == model_cfg.action,
            "distill.teacher {path} is another model than the run's (its DiT or action interface differ); the student learns the teacher's own sampler"
        );
        let teacher = BwmModel::build_converted(&store, &teacher_cfg, &mut |_: &mut BwmModel| Ok(())).with_context(|| format!("building the teacher from {what}"))?;
        Ok(Self::with_teacher(teacher, cfg.student_steps, cfg.teacher_substeps, shift, seed))
    }

    pub fn with_teacher(teacher: BwmModel, student_steps: usize, substeps: usize, shift: f64, seed: u64) -> Self {
        let fine = FlowSchedule::inference(student_steps * substeps, shift).sigmas;
        Self { teacher, fine, substeps, student_steps, seed }
    }

    /// The student's sigma at its grid point `i` (0 past the last).
    fn student_sigma(&self, i: usize) -> f64 {
        self.fine.get(i * self.substeps).copied().unwrap_or(0.0)
    }

    /// The segment of the student's grid that global sample `index` trains.
    pub fn segment(&self, index: u64) -> usize {
        let u = keyed_rng::uniform(self.seed, index, Purpose::Timestep);
        ((u * self.student_steps as f64) as usize).min(self.student_steps - 1)
    }

    /// The batch for the student: clean latents [B, C, F, H, W] and their draws as
    /// `Objective::prepare` takes them, `actions` [B, rows, d_a], and each sample's segment.
    pub fn prepare(&self, objective: &Objective, clean: &Tensor, noise: &Tensor, history_noise: &Tensor, actions: &Tensor, segments: &[usize]) -> Result<Prepared> {
        let s = clean.size();
        ensure!(s.len() == 5 && noise.size() == s && history_noise.size() == s, "clean latents and noise must be [B, C, F, H, W] of one shape");
        let (b, f, p) = (s[0], s[2], objective.condition_latents);
        ensure!(segments.len() as i64 == b, "{} segments for a batch of {b}", segments.len());
        ensure!(segments.iter().all(|&i| i < self.student_steps), "a segment past the student's {} steps", self.student_steps);
        ensure!(f > p, "clips have {f} latent frames; distillation needs more than the {p} condition latents");
        let device = clean.device();
        let kind = self.teacher.store.kind();
        let prefix = objective.condition_prefix(clean, history_noise);
        let last = *segments.iter().max().unwrap_or(&0);
        // The teacher's state at each of the student's points up to the last one needed.
        let mut states = vec![noise.narrow(2, p, f - p).to_kind(Kind::Float)];
        tch::no_grad(|| -> Result<()> {
            let mut x = states[0].shallow_clone();
            for step in 0..(last + 1) * self.substeps {
                let (sigma, next) = (self.fine[step], self.fine.get(step + 1).copied().unwrap_or(0.0));
                let t = Tensor::full([b], sigma * bwm_model::schedule::NUM_TRAIN_TIMESTEPS as f64, (Kind::Float, device));
                let input = Tensor::cat(&[&prefix, &x], 2).to_kind(kind);
                let v = self.teacher.forward_keeping(&input, &bwm_model::frame_timesteps(&t, f, p), actions, None)?;
                x = &x + v.narrow(2, p, f - p).to_kind(Kind::Float) * (next - sigma);
                if (step + 1) % self.substeps == 0 {
                    states.push(x.shallow_clone());
                }
            }
            Ok(())
        })?;
        let pick = |k: usize, i: usize| states[i].narrow(0, k as i64, 1);
        let start = Tensor::cat(&segments.iter().enumerate().map(|(k, &i)| pick(k, i)).collect::<Vec<_>>(), 0);
        let end = Tensor::cat(&segments.iter().enumerate().map(|(k, &i)| pick(k, i + 1)).collect::<Vec<_>>(), 0);
        let span: Vec<f32> = segments.iter().map(|&i| (self.student_sigma(i + 1) - self.student_sigma(i)) as f32).collect();
        let span = upload(&Tensor::from_slice(&span), device).view([b, 1, 1, 1, 1]);
        let t: Vec<f32> = segments.iter().map(|&i| (self.student_sigma(i) * bwm_model::schedule::NUM_TRAIN_TIMESTEPS as f64) as f32).collect();
        let t = upload(&Tensor::from_slice(&t), device);
        Ok(Prepared {
            input: Tensor::cat(&[prefix, start.shallow_clone()], 2),
            frame_timesteps: bwm_model::frame_timesteps(&t, f, p),
            target: (end - start) / span,
            weights: Tensor::ones([b], (Kind::Float, device)),
            // For the step's loss curve: the training grid's point nearest each segment's sigma.
            timestep_indices: segments.iter().map(|&i| objective.nearest_index(self.student_sigma(i))).collect(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ObjectiveSection;

    fn teacher() -> BwmModel {
        BwmModel::random(&ModelConfig::preset("tiny").unwrap(), Kind::Float, Device::Cpu, 7).unwrap()
    }

    fn batch(model: &BwmModel, b: i64) -> (Tensor, Tensor, Tensor, Tensor) {
        let c = model.cfg.dit.in_dim;
        let draw = |shape: &[i64], key: u64| keyed_rng::normal(shape, 3, key, Purpose::Augment);
        let shape = [b, c, 3, 4, 4];
        let actions = draw(&[b, 9, model.cfg.action.action_dim], 4).tanh();
        (draw(&shape, 0), draw(&shape, 1), draw(&shape, 2), actions)
    }

    /// A student that is the teacher, distilled over one teacher step per student step, already
    /// gives the target (loss 0): the target is the teacher's own velocity at the student's
    /// input. Over more teacher steps it is not, and the segments start where the teacher's
    /// steps reached.
    #[test]
    fn the_target_is_the_teachers_step_and_the_input_its_state() {
        let model = teacher();
        let objective = Objective::new(&ObjectiveSection { condition_latents: 2, ..ObjectiveSection::default() }, 0);
        let (clean, noise, history_noise, actions) = batch(&model, 2);
        let one = Distillation::with_teacher(teacher(), 2, 1, 5.0, 0);
        let prepared = one.prepare(&objective, &clean, &noise, &history_noise, &actions, &[0, 1]).unwrap();
        let v = tch::no_grad(|| model.forward_keeping(&prepared.input, &prepared.frame_timesteps, &actions, None)).unwrap();
        let loss = objective.per_sample_loss(&v, &prepared);
        assert!(loss.abs().max().double_value(&[]) < 1e-8, "{loss}");
        // Sample 0 starts at the noise; sample 1 where one teacher step from its noise reached.
        assert!(prepared.input.get(0).narrow(1, 2, 1).allclose(&noise.get(0).narrow(1, 2, 1), 1e-6, 1e-6, false));
        assert!(!prepared.input.get(1).narrow(1, 2, 1).allclose(&noise.get(1).narrow(1, 2, 1), 1e-3, 1e-3, false));
        // The condition is as in training: x0 clean.
        assert!(prepared.input.narrow(2, 0, 1).allclose(&clean.narrow(2, 0, 1), 1e-6, 1e-6, false));

        let four = Distillation::with_teacher(teacher(), 2, 4, 5.0, 0);
        let prepared = four.prepare(&objective, &clean, &noise, &history_noise, &actions, &[0, 1]).unwrap();
        let v = tch::no_grad(|| model.forward_keeping(&prepared.input, &prepared.frame_timesteps, &actions, None)).unwrap();
        assert!(objective.per_sample_loss(&v, &prepared).min().double_value(&[]) > 1e-6, "four teacher steps are not one");
        assert!(four.prepare(&objective, &clean, &noise, &history_noise, &actions, &[0, 2]).is_err(), "past the student's grid");
    }

    #[test]
    fn segments_cover_the_students_grid() {
        let d = Distillation::with_teacher(teacher(), 2, 4, 5.0, 9);
        let seen: std::collections::BTreeSet<usize> = (0..64).map(|i| d.segment(i)).collect();
        assert_eq!(seen.into_iter().collect::<Vec<_>>(), [0, 1]);
        // The student's grid is the teacher's every fourth point: 1, then the sigma 4 of 8 down.
        assert_eq!(d.student_sigma(0), 1.0);
        assert_eq!(d.student_sigma(1), FlowSchedule::inference(8, 5.0).sigmas[4]);
        assert_eq!(d.student_sigma(2), 0.0);
    }
}
