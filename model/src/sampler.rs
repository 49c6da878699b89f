//! Sampling of one chunk with a fixed condition prefix (clean x0 latent + perturbed history),
//! re-imposed before every step and at the end (BWM inference, without the release's sigma=1 bug),
//! stepped by the schedule's solver (Euler unless chosen otherwise).

use anyhow::{ensure, Result};
use tch::Tensor;

use crate::bwm::{frame_timesteps, BwmModel};
use crate::schedule::FlowSchedule;

/// Samples latents [B, C, F, H, W] from `noise` of that shape. `prefix` [B, C, P, H, W] holds the
/// condition latents (timestep 0); `actions` [B, 1+4k, d_a]. `on_step(i, model_input, velocity)` sees
/// each step.
pub fn sample_chunk(
    model: &BwmModel,
    prefix: &Tensor,
    noise: &Tensor,
    actions: &Tensor,
    schedule: &FlowSchedule,
    on_step: &mut dyn FnMut(usize, &Tensor, &Tensor),
) -> Result<Tensor> {
    let (ps, ns) = (prefix.size(), noise.size());
    ensure!(
        ps.len() == 5 && ns.len() == 5 && ps[0] == ns[0] && ps[1] == ns[1] && ps[3..] == ns[3..] && ps[2] < ns[2],
        "prefix {ps:?} must be [B, C, P, H, W] with fewer frames than the noise {ns:?}"
    );
    let (b, frames, p) = (ns[0], ns[2], ps[2]);
    let future = ns[2] - p;
    let mut latents = noise.shallow_clone();
    let mut stepper = schedule.stepper();
    for i in 0..schedule.len() {
        latents = Tensor::cat(&[prefix.shallow_clone(), latents.narrow(2, p, future)], 2);
        let t = Tensor::full([b], schedule.timesteps[i], (tch::Kind::Float, noise.device()));
        let v = model.forward(&latents, &frame_timesteps(&t, frames, p), actions)?;
        on_step(i, &latents, &v);
        latents = stepper.step(&latents, &v, i);
    }
    Ok(Tensor::cat(&[prefix.shallow_clone(), latents.narrow(2, p, future)], 2))
}
