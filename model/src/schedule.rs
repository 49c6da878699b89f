//! Wan flow matching (DiffSynth-Studio's `FlowMatchScheduler("Wan")`): sigmas on a uniform grid
//! from 1 to 0, shifted by sigma' = shift*sigma / (1 + (shift-1)*sigma); timestep = 1000*sigma;
//! a clean latent z is noised as (1-sigma) z + sigma eps and the model predicts v = eps - z.
//! Sampling steps down the grid with a [`Solver`]: Euler (the reference's) or DPM-Solver++(2M).

use std::str::FromStr;

use serde::{Deserialize, Serialize};
use tch::Tensor;

pub const NUM_TRAIN_TIMESTEPS: usize = 1000;
pub const DEFAULT_SHIFT: f64 = 5.0;

pub fn shift_sigma(sigma: f64, shift: f64) -> f64 {
    shift * sigma / (1.0 + (shift - 1.0) * sigma)
}

/// How a sampling loop steps from one grid sigma to the next. Named in configs and on the
/// command line as [`Solver::name`] gives it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(into = "String", try_from = "String")]
pub enum Solver {
    /// First order: x + v (sigma_next - sigma), as DiffSynth-Studio and the Wan code sample.
    #[default]
    Euler,
    /// DPM-Solver++(2M) (Lu et al. 2022) in its flow-matching form: second-order multistep on the
    /// data prediction z = x - sigma v with alpha = 1 - sigma; the first step (from sigma 1, where
    /// lambda = ln(alpha/sigma) is -inf) is Euler's, and the last (into sigma 0, lambda +inf) is
    /// second-order Adams-Bashforth on the velocity in sigma. One model evaluation per step.
    DpmPp2M,
}

impl Solver {
    pub const ALL: [Solver; 2] = [Solver::Euler, Solver::DpmPp2M];

    pub fn name(self) -> &'static str {
        match self {
            Solver::Euler => "euler",
            Solver::DpmPp2M => "dpm++2m",
        }
    }
}

impl FromStr for Solver {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        Self::ALL.into_iter().find(|solver| solver.name() == s).ok_or_else(|| {
            let known: Vec<_> = Self::ALL.iter().map(|solver| solver.name()).collect();
            anyhow::anyhow!("unknown solver '{s}' (known: {})", known.join(", "))
        })
    }
}

/// The solvers' names as the config reference lists them (serde writes a solver as its name).
impl schemars::JsonSchema for Solver {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "Solver".into()
    }
    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        let names: Vec<&str> = Self::ALL.iter().map(|solver| solver.name()).collect();
        schemars::json_schema!({ "type": "string", "enum": names })
    }
}

impl TryFrom<String> for Solver {
    type Error = anyhow::Error;
    fn try_from(s: String) -> anyhow::Result<Self> {
        s.parse()
    }
}

impl From<Solver> for String {
    fn from(solver: Solver) -> String {
        solver.name().to_string()
    }
}

impl std::fmt::Display for Solver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One sampling pass down a [`FlowSchedule`] with a [`Solver`]: call [`Stepper::step`] for grid
/// points 0, 1, ... in order (a multistep solver keeps the previous step's predictions).
pub struct Stepper<'a> {
    schedule: &'a FlowSchedule,
    solver: Solver,
    /// The previous step's data prediction, velocity and sigma.
    previous: Option<(Tensor, Tensor, f64)>,
}

fn lambda(sigma: f64) -> f64 {
    ((1.0 - sigma) / sigma).ln()
}

impl Stepper<'_> {
    /// From grid point `i` to `i+1` (to sigma 0 after the last), given the velocity there.
    pub fn step(&mut self, sample: &Tensor, velocity: &Tensor, i: usize) -> Tensor {
        match self.solver {
            Solver::Euler => self.schedule.euler_step(sample, velocity, i),
            Solver::DpmPp2M => self.dpmpp_2m(sample, velocity, i),
        }
    }

    fn dpmpp_2m(&mut self, sample: &Tensor, velocity: &Tensor, i: usize) -> Tensor {
        let sigma = self.schedule.sigmas[i];
        let next = self.schedule.sigmas.get(i + 1).copied().unwrap_or(0.0);
        let data = sample - velocity * sigma;
        let out = match self.previous.take() {
            Some((prev_data, _, prev_sigma)) if prev_sigma < 1.0 && next > 0.0 => {
                let (l_prev, l, l_next) = (lambda(prev_sigma), lambda(sigma), lambda(next));
                let (h, h_prev) = (l_next - l, l - l_prev);
                let d = &data + (&data - prev_data) * (0.5 * h / h_prev);
                sample * (next / sigma) - d * ((1.0 - next) * ((-h).exp() - 1.0))
            }
            Some((_, prev_v, prev_sigma)) if next == 0.0 => {
                let k = (next - sigma) / (2.0 * (sigma - prev_sigma));
                sample + (velocity * (1.0 + k) - prev_v * k) * (next - sigma)
            }
            _ => self.schedule.euler_step(sample, velocity, i),
        };
        self.previous = Some((data, velocity.shallow_clone(), sigma));
        out
    }
}

#[derive(Debug, Clone)]
pub struct FlowSchedule {
    pub sigmas: Vec<f64>,
    pub timesteps: Vec<f64>,
    /// Per-timestep loss weights (training schedules only).
    pub weights: Vec<f64>,
    /// How sampling steps down the grid (inference schedules).
    pub solver: Solver,
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
        Self { sigmas, timesteps, weights, solver: Solver::Euler }
    }

    /// The sampling grid: `steps` sigmas from 1 down (0 excluded), shifted.
    pub fn inference(steps: usize, shift: f64) -> Self {
        let (sigmas, timesteps) = Self::grid(steps, shift);
        Self { sigmas, timesteps, weights: Vec::new(), solver: Solver::Euler }
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

    /// This grid sampled with `solver`.
    pub fn with_solver(mut self, solver: Solver) -> Self {
        self.solver = solver;
        self
    }

    /// A sampling pass down this grid with its solver.
    pub fn stepper(&self) -> Stepper<'_> {
        Stepper { schedule: self, solver: self.solver, previous: None }
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

    /// The exact probability-flow ODE of Gaussian data z ~ N(mu, s^2) noised as (1-sigma) z +
    /// sigma eps carries noise eps at sigma 1 to mu + s eps at sigma 0; its velocity is
    /// (x - E[z | x]) / sigma.
    fn gaussian_error(solver: Solver, steps: usize) -> f64 {
        let (mu, s) = (0.7, 0.3);
        let schedule = FlowSchedule::inference(steps, DEFAULT_SHIFT).with_solver(solver);
        let eps = Tensor::from_slice(&[-2.0, -0.5, 0.0, 0.8, 1.9]);
        let mut x = eps.shallow_clone();
        let mut stepper = schedule.stepper();
        for i in 0..steps {
            let sigma = schedule.sigmas[i];
            let a = 1.0 - sigma;
            let mean_z = (&x - a * mu) * (a * s * s / (a * a * s * s + sigma * sigma)) + mu;
            let v = (&x - mean_z) / sigma;
            x = stepper.step(&x, &v, i);
        }
        (x - (eps * s + mu)).abs().max().double_value(&[])
    }

    #[test]
    fn dpm_solver_2m_converges_faster_than_euler() {
        for steps in [12, 16, 20, 30, 50] {
            let (euler, dpm) = (gaussian_error(Solver::Euler, steps), gaussian_error(Solver::DpmPp2M, steps));
            assert!(dpm < euler / 1.7, "{steps} steps: dpm++2m error {dpm} against euler {euler}");
        }
        // Second order: doubling the steps divides the error by about 4 or more (Euler's by 2).
        let ratio = gaussian_error(Solver::DpmPp2M, 16) / gaussian_error(Solver::DpmPp2M, 32);
        assert!(ratio > 3.0, "dpm++2m error ratio from 16 to 32 steps: {ratio}");
        assert!(gaussian_error(Solver::DpmPp2M, 20) < gaussian_error(Solver::Euler, 50));
    }

    #[test]
    fn solver_names_round_trip() {
        for solver in Solver::ALL {
            assert_eq!(solver.to_string().parse::<Solver>().unwrap(), solver);
            let json = serde_json::to_string(&solver).unwrap();
            assert_eq!(json, format!("\"{}\"", solver.name()));
            assert_eq!(serde_json::from_str::<Solver>(&json).unwrap(), solver);
        }
        let err = "unipc".parse::<Solver>().unwrap_err().to_string();
        assert!(err.contains("unipc") && err.contains("dpm++2m"), "{err}");
        let err = serde_json::from_str::<Solver>("\"unipc\"").unwrap_err().to_string();
        assert!(err.contains("unipc") && err.contains("dpm++2m"), "{err}");
    }

    #[test]
    fn history_sigma_is_0_2083() {
        let s = FlowSchedule::training(1000, 5.0);
        assert!((s.history_sigma() - 0.208333).abs() < 1e-5);
        let mean: f64 = s.weights.iter().sum::<f64>() / 1000.0;
        assert!((mean - 1.0).abs() < 1e-9);
    }
}
