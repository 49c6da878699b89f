//! Sampling of one chunk with a fixed condition prefix (clean x0 latent + perturbed history),
//! re-imposed before every step and at the end (BWM inference, without the release's sigma=1 bug),
//! stepped by the schedule's solver (Euler unless chosen otherwise).

use anyhow::{ensure, Result};
use tch::{Kind, Tensor};

use crate::bwm::{frame_timesteps, BwmModel};
use crate::schedule::FlowSchedule;

/// Action guidance w must be finite and >= 0 (1: off, 0: the null condition alone).
pub fn validate_guidance(w: f64) -> Result<()> {
    ensure!(w.is_finite() && w >= 0.0, "action guidance {w} must be finite and >= 0");
    Ok(())
}

/// How the sampler evaluates the model at each step. The sampler's own inputs are the same
/// whatever runs them, so a caller may run the forward pass another way (recorded once as a CUDA
/// graph and replayed, by the inference crate) without the model or the sampler knowing.
pub trait Denoiser {
    /// The model's velocity for `latents` at `frame_timesteps` under `actions`, the samples whose
    /// `keep` entry is 0 under the null action condition (`BwmModel::forward_keeping`).
    fn velocity(&mut self, model: &BwmModel, latents: &Tensor, frame_timesteps: &Tensor, actions: &Tensor, keep: Option<&Tensor>) -> Result<Tensor>;
}

/// The model's forward pass as it stands, launched kernel by kernel.
pub struct Eager;

impl Denoiser for Eager {
    fn velocity(&mut self, model: &BwmModel, latents: &Tensor, frame_timesteps: &Tensor, actions: &Tensor, keep: Option<&Tensor>) -> Result<Tensor> {
        model.forward_keeping(latents, frame_timesteps, actions, keep)
    }
}

/// Samples latents [B, C, F, H, W] from `noise` of that shape. `prefix` [B, C, P, H, W] holds the
/// condition latents (timestep 0); `actions` [B, 1+4k, d_a]. `guidance` w is classifier-free
/// guidance by the actions: the velocity is v_null + w (v_actions - v_null), v_null the model's
/// under the null action condition (a model trained with `objective.action_dropout`); 1 is the
/// plain conditional velocity at one model evaluation per step, other values cost two.
/// `denoiser` runs each step's forward pass (`Eager`: the model's own); `on_step(i, model_input,
/// velocity)` sees each step.
#[allow(clippy::too_many_arguments)]
pub fn sample_chunk(
    denoiser: &mut dyn Denoiser,
    model: &BwmModel,
    prefix: &Tensor,
    noise: &Tensor,
    actions: &Tensor,
    schedule: &FlowSchedule,
    guidance: f64,
    on_step: &mut dyn FnMut(usize, &Tensor, &Tensor),
) -> Result<Tensor> {
    validate_guidance(guidance)?;
    let (ps, ns) = (prefix.size(), noise.size());
    ensure!(
        ps.len() == 5 && ns.len() == 5 && ps[0] == ns[0] && ps[1] == ns[1] && ps[3..] == ns[3..] && ps[2] < ns[2],
        "prefix {ps:?} must be [B, C, P, H, W] with fewer frames than the noise {ns:?}"
    );
    let (b, frames, p) = (ns[0], ns[2], ps[2]);
    let future = ns[2] - p;
    let mut latents = noise.shallow_clone();
    let mut stepper = schedule.stepper();
    // Guided steps run one batch of 2B: the conditional half, then the null half.
    let guided = (guidance != 1.0).then(|| {
        let device = noise.device();
        let keep = Tensor::cat(&[Tensor::ones([b], (Kind::Float, device)), Tensor::zeros([b], (Kind::Float, device))], 0);
        (keep, Tensor::cat(&[actions, actions], 0))
    });
    for i in 0..schedule.len() {
        latents = Tensor::cat(&[prefix.shallow_clone(), latents.narrow(2, p, future)], 2);
        let t = Tensor::full([b], schedule.timesteps[i], (tch::Kind::Float, noise.device()));
        let ft = frame_timesteps(&t, frames, p);
        let v = match &guided {
            None => denoiser.velocity(model, &latents, &ft, actions, None)?,
            Some((keep, doubled_actions)) => {
                let both = denoiser.velocity(model, &Tensor::cat(&[&latents, &latents], 0), &Tensor::cat(&[&ft, &ft], 0), doubled_actions, Some(keep))?;
                let (cond, null) = (both.narrow(0, 0, b), both.narrow(0, b, b));
                &null + (&cond - &null) * guidance
            }
        };
        on_step(i, &latents, &v);
        latents = stepper.step(&latents, &v, i);
    }
    Ok(Tensor::cat(&[prefix.shallow_clone(), latents.narrow(2, p, future)], 2))
}
