//! Forward + backward of the BWM model, optionally recomputing each DiT block in backward.
//!
//! tch has no activation-checkpoint API, so recomputation is done by hand (docs/architecture.md): the
//! preparation (action encoder, patchify, time embedding) runs with autograd; its outputs are
//! cut into leaves; the blocks run without autograd keeping only each block's input; the head and
//! the loss run with autograd and backward; then the blocks are walked in reverse, each recomputed
//! from its saved input with autograd and backpropagated with the incoming gradient; finally the
//! gradients gathered on the leaves flow back through the preparation graph. Each block's backward
//! hands the gradients of that block's parameters to a [`BlockGradSink`] instead of accumulating
//! them in `.grad`, so at most one block's model-dtype gradients exist at a time; they are final
//! for this micro-step there, which is also where data-parallel reduction of a block can start.
//! The last `keep_last` blocks can keep their activations instead (when memory allows): they run
//! with autograd in the forward, each from a leaf input, and the walk backpropagates their saved
//! graphs without recomputing them.

use anyhow::{Context, Result};
use bwm_model::dit::Conditioning;
use bwm_model::BwmModel;
use tch::{Kind, Tensor};

/// Which activations backward recomputes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Recompute {
    /// Autograd keeps every activation; every gradient accumulates in `.grad`.
    Off,
    /// Each DiT block is recomputed from its input in backward, except the last `keep_last`,
    /// whose activations are kept from the forward.
    Blocks { keep_last: usize },
}

/// A block's state between the forward and the backward walk.
enum Saved {
    /// Its input, to recompute it from.
    Input(Tensor),
    /// Its leaf input and its output with the autograd graph between them.
    Graph { input: Tensor, output: Tensor },
}

/// Receives the gradients of the DiT blocks' parameters during the recomputing backward walk,
/// and all gradients at once when nothing is recomputed.
pub trait BlockGradSink {
    /// The parameters of block `block` whose gradients go to `block_grads` (the others, and all
    /// parameters outside the blocks, accumulate in `.grad`).
    fn block_params(&self, block: usize) -> Vec<Tensor>;
    /// Gradients of `block_params(block)`, in order; undefined for a parameter the block did not use.
    fn block_grads(&mut self, block: usize, grads: &[Tensor]) -> Result<()>;
    /// Without recomputation: the parameters whose gradients go to `all_grads` when the backward
    /// pass ends, instead of accumulating in `.grad` (empty: every gradient goes to `.grad`).
    fn all_params(&self) -> Vec<Tensor> {
        Vec::new()
    }
    /// Gradients of `all_params()`, in order; undefined for a parameter the step did not use.
    fn all_grads(&mut self, _grads: Vec<Tensor>) -> Result<()> {
        Ok(())
    }
}

/// Every gradient accumulates in `.grad`; the blocks' backward order is recorded.
#[derive(Default)]
pub struct GradsInParams {
    pub blocks_done: Vec<usize>,
}

impl BlockGradSink for GradsInParams {
    fn block_params(&self, _: usize) -> Vec<Tensor> {
        Vec::new()
    }
    fn block_grads(&mut self, block: usize, _: &[Tensor]) -> Result<()> {
        self.blocks_done.push(block);
        Ok(())
    }
}

/// `forward_backward` of the mean of `per_sample_loss` (prediction -> losses `[B]`); returns the
/// detached per-sample losses.
#[allow(clippy::too_many_arguments)]
pub fn forward_backward_per_sample(
    model: &BwmModel,
    latents: &Tensor,
    frame_timesteps: &Tensor,
    actions: &Tensor,
    action_keep: Option<&Tensor>,
    recompute: Recompute,
    per_sample_loss: &dyn Fn(&Tensor) -> Tensor,
    sink: &mut dyn BlockGradSink,
) -> Result<Tensor> {
    let per_sample = std::cell::RefCell::new(None);
    let loss_fn = |pred: &Tensor| {
        let l = per_sample_loss(pred);
        *per_sample.borrow_mut() = Some(l.detach());
        l.mean(Kind::Float)
    };
    // The mean loss it returns is the mean of the per-sample losses kept here.
    let _ = forward_backward(model, latents, frame_timesteps, actions, action_keep, recompute, &loss_fn, sink)?;
    per_sample.into_inner().context("the loss function did not run")
}

/// Runs forward and backward; returns the detached loss. `loss_fn` maps the model's prediction
/// [B, C, F, H, W] to a scalar. Without recomputation (`Recompute::Off`) the gradients of
/// `sink.all_params()` go to `sink.all_grads`, every other one accumulates in `.grad`.
pub fn forward_backward(
    model: &BwmModel,
    latents: &Tensor,
    frame_timesteps: &Tensor,
    actions: &Tensor,
    action_keep: Option<&Tensor>,
    recompute: Recompute,
    loss_fn: &dyn Fn(&Tensor) -> Tensor,
    sink: &mut dyn BlockGradSink,
) -> Result<Tensor> {
    let Recompute::Blocks { keep_last } = recompute else {
        let prediction = model.forward_keeping(latents, frame_timesteps, actions, action_keep)?;
        let loss = loss_fn(&prediction);
        let params = sink.all_params();
        if params.is_empty() {
            loss.f_backward()?;
        } else {
            // Returned rather than accumulated: no `.grad` to zero and add into each micro-step.
            let grads = Tensor::f_run_backward(&[&loss], &params, false, false)?;
            sink.all_grads(grads)?;
        }
        return Ok(loss.detach());
    };

    let emb = model.embed_actions(latents, actions, action_keep)?;
    let (tokens, cond) = model.dit.prepare(latents, frame_timesteps, &emb.dit_inputs())?;
    let Conditioning { e, e0, context, rope, grid } = cond;
    let leaf = |t: &Tensor| t.detach().set_requires_grad(true);
    let cut = Conditioning { e: leaf(&e), e0: leaf(&e0), context: leaf(&context), rope, grid };

    let blocks = model.dit.blocks.len();
    let kept_from = blocks.saturating_sub(keep_last);
    let mut saved = Vec::with_capacity(blocks);
    let mut x = tokens.detach();
    for (i, block) in model.dit.blocks.iter().enumerate() {
        if i < kept_from {
            let next = tch::no_grad(|| block.forward(&x, &cut));
            saved.push(Saved::Input(std::mem::replace(&mut x, next)));
        } else {
            let input = leaf(&x);
            let output = block.forward(&input, &cut);
            x = output.detach();
            saved.push(Saved::Graph { input, output });
        }
    }

    let x_last = leaf(&x);
    let loss = loss_fn(&model.dit.finish(&x_last, &cut));
    loss.f_backward()?;
    let mut grad = x_last.grad();
    // Gradients of the conditioning leaves from the blocks whose parameters go to the sink (the
    // head's and the other blocks' accumulate in the leaves' `.grad`).
    let mut cond_grads: Vec<Tensor> = (0..3).map(|_| Tensor::new()).collect();
    let add = |acc: &mut Tensor, g: &Tensor| {
        if g.defined() {
            *acc = if acc.defined() { &*acc + g } else { g.shallow_clone() };
        }
    };
    for (i, block) in model.dit.blocks.iter().enumerate().rev() {
        let (x_in, out) = match saved.pop().context("a block's saved state is missing")? {
            Saved::Input(input) => {
                let x_in = leaf(&input);
                let out = block.forward(&x_in, &cut);
                (x_in, out)
            }
            Saved::Graph { input, output } => (input, output),
        };
        let target = (out * &grad).sum(Kind::Float);
        let params = sink.block_params(i);
        if params.is_empty() {
            target.f_backward()?;
            grad = x_in.grad();
            sink.block_grads(i, &[])?;
            continue;
        }
        let mut wrt = vec![x_in.shallow_clone(), cut.e.shallow_clone(), cut.e0.shallow_clone(), cut.context.shallow_clone()];
        wrt.extend(params.iter().map(Tensor::shallow_clone));
        let grads = Tensor::f_run_backward(&[target], &wrt, false, false)?;
        grad = grads[0].shallow_clone();
        for (acc, g) in cond_grads.iter_mut().zip(&grads[1..4]) {
            add(acc, g);
        }
        sink.block_grads(i, &grads[4..])?;
    }
    for (acc, leaf) in cond_grads.iter_mut().zip([&cut.e, &cut.e0, &cut.context]) {
        add(acc, &leaf.grad());
    }

    let term = |value: &Tensor, g: &Tensor| -> Tensor {
        if g.defined() {
            (value.to_kind(Kind::Float) * g.to_kind(Kind::Float)).sum(Kind::Float)
        } else {
            Tensor::zeros([], (Kind::Float, value.device()))
        }
    };
    let upstream = (tokens * grad).sum(Kind::Float) + term(&e, &cond_grads[0]) + term(&e0, &cond_grads[1]) + term(&context, &cond_grads[2]);
    // Nothing upstream requires grad when the action encoder and embeddings are all frozen.
    if upstream.requires_grad() {
        upstream.f_backward()?;
    }
    Ok(loss.detach())
}
