//! `train.cuda_graph`: the training step's forward and backward pass recorded once as a CUDA
//! graph and replayed, its inputs copied into the tensors the recording reads. What it computes is
//! `recompute::forward_backward` without recomputation: the gradients are left in the parameters'
//! `.grad`, the optimizer's update stays eager.

use anyhow::{ensure, Context, Result};
use bwm_cuda_graph::CudaGraph;
use bwm_model::bwm::BwmModel;
use tch::{Device, Kind, Tensor};

use crate::config::RunConfig;
use crate::objective::{Objective, Prepared};

/// Eager steps on the graph's stream before the capture (see `CudaGraph::warm_up`).
const WARM_UP_STEPS: u32 = 2;

/// What the recorded step reads and writes.
struct Recorded {
    input: Tensor,
    prepared: Prepared,
    actions: Tensor,
    keep: Option<Tensor>,
    per_sample: Tensor,
}

pub struct StepGraph {
    graph: CudaGraph,
    warm_ups_left: u32,
    recorded: Option<Recorded>,
}

/// One micro-step: the per-sample losses `[B]`, the gradients added to the parameters' `.grad`.
fn forward_backward(model: &BwmModel, objective: &Objective, input: &Tensor, prepared: &Prepared, actions: &Tensor, keep: Option<&Tensor>) -> Result<Tensor> {
    let prediction = model.forward_keeping(input, &prepared.frame_timesteps, actions, keep)?;
    let per_sample = objective.per_sample_loss(&prediction, prepared);
    per_sample.mean(Kind::Float).f_backward()?;
    Ok(per_sample.detach())
}

/// Copies `src` into `dst`, which must have its shape (the recording read `dst`).
fn refill(dst: &Tensor, src: &Tensor, what: &str) -> Result<()> {
    ensure!(dst.size() == src.size(), "train.cuda_graph: the step's {what} is {:?}, the recorded step's {:?}", src.size(), dst.size());
    tch::no_grad(|| dst.shallow_clone().copy_(src));
    Ok(())
}

impl StepGraph {
    /// The graph for a run of `cfg` on `device` with `world` ranks; an error names what the
    /// graph cannot record.
    pub fn new(cfg: &RunConfig, device: Device, world: usize, lora: bool) -> Result<Self> {
        ensure!(world == 1, "train.cuda_graph runs in one process, not in {world} data-parallel ranks");
        ensure!(cfg.train.grad_accum == 1, "train.cuda_graph needs train.grad_accum = 1 (got {})", cfg.train.grad_accum);
        ensure!(!cfg.train.recompute, "train.cuda_graph needs train.recompute = false");
        ensure!(!lora, "train.cuda_graph does not record LoRA training (its dropout masks are reseeded every step)");
        ensure!(!cfg.train.fp8, "train.cuda_graph does not record train.fp8 steps");
        ensure!(device.is_cuda(), "train.cuda_graph needs a CUDA device (run.device = {:?})", cfg.run.device);
        Ok(Self { graph: CudaGraph::new(device)?, warm_ups_left: WARM_UP_STEPS, recorded: None })
    }

    /// One micro-step, eager on the graph's stream during the warm-up, then recorded once and
    /// replayed: the per-sample losses `[B]`, the gradients added to the parameters' `.grad`.
    pub fn step(&mut self, model: &BwmModel, objective: &Objective, input: &Tensor, prepared: &Prepared, actions: &Tensor, keep: Option<&Tensor>) -> Result<Tensor> {
        if self.warm_ups_left > 0 {
            self.warm_ups_left -= 1;
            return self.graph.warm_up(|| forward_backward(model, objective, input, prepared, actions, keep)).context("a warm-up step on the CUDA graph's stream");
        }
        match &self.recorded {
            Some(r) => {
                refill(&r.input, input, "input")?;
                refill(&r.prepared.frame_timesteps, &prepared.frame_timesteps, "timesteps")?;
                refill(&r.prepared.target, &prepared.target, "target")?;
                refill(&r.prepared.weights, &prepared.weights, "loss weights")?;
                refill(&r.actions, actions, "actions")?;
                match (&r.keep, keep) {
                    (Some(dst), Some(src)) => refill(dst, src, "action mask")?,
                    (None, None) => {}
                    _ => anyhow::bail!("train.cuda_graph: the step's action mask came and went between steps"),
                }
            }
            None => {
                let input = input.copy();
                let prepared = Prepared {
                    input: input.shallow_clone(),
                    frame_timesteps: prepared.frame_timesteps.copy(),
                    target: prepared.target.copy(),
                    weights: prepared.weights.copy(),
                    timestep_indices: prepared.timestep_indices.clone(),
                };
                let (actions, keep) = (actions.copy(), keep.map(Tensor::copy));
                let per_sample = self
                    .graph
                    .capture(|| forward_backward(model, objective, &input, &prepared, &actions, keep.as_ref()))
                    .context("recording the training step as a CUDA graph (train.cuda_graph)")?;
                self.recorded = Some(Recorded { input, prepared, actions, keep, per_sample });
            }
        }
        self.graph.replay()?;
        let r = self.recorded.as_ref().context("the recorded step is missing")?;
        // A copy: the next replay overwrites the recorded losses.
        Ok(r.per_sample.copy())
    }
}
