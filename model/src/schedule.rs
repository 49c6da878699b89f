//! Wan flow matching (DiffSynth-Studio's `FlowMatchScheduler("Wan")`): sigmas on a uniform grid
//! from 1 to 0, shifted by sigma' = shift*sigma / (1 + (shift-1)*sigma); timestep = 1000*sigma;
//! a clean latent z is noised as (1-sigma) z + sigma eps and the model predicts v = eps - z.

use tch::Tensor;

pub const NUM_TRAIN_TIMESTEPS: usize = 1000;
pub const DEFAULT_SHIFT: f64 = 5.0;

pub fn shift_sigma(sigma: f64, shift: f64) -> f64 {
    shift * sigma / (1.0 + (shift - 1.0) * sigma)
}

#[derive(Debug, Clone)]
pub struct FlowSchedule {
    pub sigmas: Vec<f64>,
    pub timesteps: Vec<f64>,
    /// Per-timestep loss weights (training schedules only).
    pub weights: Vec<f64>,
}

impl FlowSchedule {
    fn grid(steps: usize, shift: f64) -> (Vec<f64>, Vec<f64>) {
        let sigmas: Vec<f64> =
            (0..steps).map(|i| shift_sigma(1.0 - i as f64 / steps as f64, shift)).collect();
        let timesteps = sigmas.iter().map(|s| s * NUM_TRAIN_TIMESTEPS as f64).collect();
        (sigmas, timesteps)
    }

    /// The training grid (1000 steps) with its Gaussian timestep weights: y = exp(-2((t-500)/1000)^2),
    /// shifted to a minimum of 0 and scaled to mean 1 (the reference rescales other lengths
    /// empirically, reproduced here).
    pub fn training(steps: usize, shift: f64) -> Self {
        let (sigmas, timesteps) = Self::grid(steps, shift);
        let n = NUM_TRAIN_TIMESTEPS as f64;
        let y: Vec<f64> = timesteps.iter().map(|t| (-2.0 * ((t - n / 2.0) / n).powi(2)).exp()).collect();
        let min = y.iter().cloned().fold(f64::INFINITY, f64::min);
        let sum: f64 = y.iter().map(|v| v - min).sum();
        let mut weights: Vec<f64> = y.iter().map(|v| (v - min) * (n / sum)).collect();
        if steps != NUM_TRAIN_TIMESTEPS && steps > 1 {
            let scale = steps as f64 / n;
            weights.iter_mut().for_each(|w| *w *= scale);
            let second = weights[1];
            weights.iter_mut().for_each(|w| *w += second);
        }
        Self { sigmas, timesteps, weights }
    }

    /// The sampling grid: `steps` sigmas from 1 down (0 excluded), shifted.
    pub fn inference(steps: usize, shift: f64) -> Self {
        let (sigmas, timesteps) = Self::grid(steps, shift);
        Self { sigmas, timesteps, weights: Vec::new() }
    }

    /// The history-noise level sigma_h: the training sigma 50 grid steps from the clean end
    /// (0.2083 for 1000 steps at shift 5), as the BWM release computes it.
    pub fn history_sigma(&self) -> f64 {
        self.sigmas[self.sigmas.len().saturating_sub(50)]
    }

    pub fn len(&self) -> usize {
        self.sigmas.len()
    }

    pub fn is_empty(&self) -> bool {
        self.sigmas.is_empty()
    }

    /// One Euler step from grid point `i` to `i+1` (to sigma 0 after the last):
    /// x + v * (sigma_next - sigma).
    pub fn euler_step(&self, sample: &Tensor, velocity: &Tensor, i: usize) -> Tensor {
        let sigma = self.sigmas[i];
        let next = self.sigmas.get(i + 1).copied().unwrap_or(0.0);
        sample + velocity * (next - sigma)
    }

    /// (1 - sigma) z + sigma eps
    pub fn add_noise(clean: &Tensor, noise: &Tensor, sigma: f64) -> Tensor {
        clean * (1.0 - sigma) + noise * sigma
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn history_sigma_is_0_2083() {
        let s = FlowSchedule::training(1000, 5.0);
        assert!((s.history_sigma() - 0.208333).abs() < 1e-5);
        let mean: f64 = s.weights.iter().sum::<f64>() / 1000.0;
        assert!((mean - 1.0).abs() < 1e-9);
    }
}
