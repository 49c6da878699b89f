//! `train.cuda_graph`: the training step's forward and backward pass recorded once as a CUDA
//! graph and replayed, its inputs copied into the tensors the recording reads. What it records is
//! `recompute::forward_backward_per_sample` without recomputation: the gradients are left in the
//! parameters' `.grad`, the optimizer's update stays eager.

use anyhow::{ensure, Context, Result};
use bwm_cuda_graph::GraphedStep;
use bwm_model::bwm::BwmModel;
use tch::{Device, Tensor};

use crate::config::RunConfig;
use crate::objective::{Objective, Prepared};
use crate::recompute::{forward_backward_per_sample, GradsInParams, Recompute};

/// Eager steps on the graph's stream before the capture (see `CudaGraph::warm_up`).
const WARM_UP_STEPS: u32 = 2;

pub struct StepGraph {
    step: GraphedStep,
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
        Ok(Self { step: GraphedStep::new(device, WARM_UP_STEPS)? })
    }

    /// One micro-step, eager during the warm-up, then recorded once and replayed: the per-sample
    /// losses `[B]`, the gradients added to the parameters' `.grad`.
    pub fn step(&mut self, model: &BwmModel, objective: &Objective, input: &Tensor, prepared: &Prepared, actions: &Tensor, keep: Option<&Tensor>) -> Result<Tensor> {
        let mut inputs = vec![input, &prepared.frame_timesteps, &prepared.target, &prepared.weights, actions];
        inputs.extend(keep);
        let indices = prepared.timestep_indices.clone();
        self.step
            .run(&inputs, |t| {
                let prepared = Prepared {
                    input: t[0].shallow_clone(),
                    frame_timesteps: t[1].shallow_clone(),
                    target: t[2].shallow_clone(),
                    weights: t[3].shallow_clone(),
                    timestep_indices: indices,
                };
                let loss = |pred: &Tensor| objective.per_sample_loss(pred, &prepared);
                forward_backward_per_sample(model, &t[0], &prepared.frame_timesteps, &t[4], t.get(5), Recompute::Off, &loss, &mut GradsInParams::default())
            })
            .context("the training step as a CUDA graph (train.cuda_graph)")
    }
}
