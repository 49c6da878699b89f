//! `bwm bench-train --breakdown`: where a training step's GPU time goes. One DiT block and its
//! parts are timed at the step's shapes (attention cores, linear layers, and the rest of the
//! block: norms, modulation, RoPE, gates, residual adds and casts), forward and forward+backward,
//! as device-synchronized wall time (median of 5 runs after 2 warm-up runs); the step is then
//! composed from them (every block runs forward, the recomputed ones a second time, all backward)
//! and what the blocks do not explain is reported as the rest (embeddings, head and loss, AdamW,
//! exposed collectives, host gaps). A profile of the step itself would need a GPU timeline tch
//! cannot record; these are the parts measured alone.

use std::time::Instant;

use anyhow::{Context, Result};
use bwm_model::nn::{attention, Linear};
use tch::{Device, Kind, Tensor};

use bwm_model::device::synchronize as sync;
use crate::Trainer;

/// Median seconds of `f` over 5 runs after 2 warm-up runs.
fn time(device: Device, mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    let mut runs = Vec::new();
    for i in 0..7 {
        sync(device);
        let start = Instant::now();
        f()?;
        sync(device);
        if i >= 2 {
            runs.push(start.elapsed().as_secs_f64());
        }
    }
    runs.sort_by(f64::total_cmp);
    Ok(runs[runs.len() / 2])
}

/// Backward of `out` against a gradient of ones, into `inputs`.
fn backward(out: &Tensor, inputs: &[Tensor]) -> Result<()> {
    let target = out.to_kind(Kind::Float).sum(Kind::Float);
    Tensor::f_run_backward(&[target], inputs, false, false)?;
    Ok(())
}

/// Forward and forward+backward seconds of a linear layer on [batch, rows, input width], and its
/// forward+backward FLOPs.
fn linear(l: &Linear, batch: i64, rows: i64, device: Device) -> Result<(f64, f64, f64)> {
    let (out, inp) = l.weight.size2()?;
    let x = Tensor::randn([batch, rows, inp], (l.weight.kind(), device)).set_requires_grad(true);
    let fwd = time(device, || Ok(drop(tch::no_grad(|| l.forward(&x)))))?;
    let inputs: Vec<Tensor> = [&x, &l.weight, &l.bias].into_iter().filter(|t| t.requires_grad()).map(Tensor::shallow_clone).collect();
    let both = time(device, || backward(&l.forward(&x), &inputs))?;
    Ok((fwd, both, 6.0 * (batch * rows * inp * out) as f64))
}

/// Forward and forward+backward seconds of the attention core (softmax(QK^T)V).
fn attention_core(batch: i64, rows: i64, keys: i64, dim: i64, heads: i64, kind: Kind, device: Device) -> Result<(f64, f64)> {
    let make = |n: i64| Tensor::randn([batch, n, dim], (kind, device)).set_requires_grad(true);
    let (q, k, v) = (make(rows), make(keys), make(keys));
    let fwd = time(device, || Ok(drop(tch::no_grad(|| attention(&q, &k, &v, heads)))))?;
    let both = time(device, || backward(&attention(&q, &k, &v, heads), &[q.shallow_clone(), k.shallow_clone(), v.shallow_clone()]))?;
    Ok((fwd, both))
}

/// Lines of the breakdown of a step of `step_seconds` (median of the timed steps) in which the
/// collectives took `collective_seconds` of GPU time.
pub fn breakdown(t: &Trainer, step_seconds: f64, collective_seconds: f64) -> Result<Vec<String>> {
    let device = t.device;
    let kind = t.model.store.kind();
    // A micro-batch of the first clip repeated.
    let batch = t.cfg.train.micro_batch as i64;
    let clip = t.clip(0)?;
    let draw = t.objective.draw(0, &t.cache.index.latent_shape);
    let repeat = |x: &Tensor| {
        let mut times = vec![1i64; x.dim() + 1];
        times[0] = batch;
        x.unsqueeze(0).repeat(times.as_slice()).to_device(device)
    };
    let prepared =
        t.objective.prepare(&repeat(&clip.latents), &repeat(&draw.noise), &repeat(&draw.history_noise), &vec![draw.timestep_index; batch as usize])?;
    let (x, cond) = tch::no_grad(|| -> Result<_> {
        let input = prepared.input.to_kind(kind);
        let emb = t.model.embed_actions(&input, &repeat(&clip.actions), None)?;
        t.model.dit.prepare(&input, &prepared.frame_timesteps, &emb.dit_inputs())
    })?;
    let block = t.model.dit.blocks.first().context("the model has no DiT block")?;
    let rows = x.size()[1];
    let keys = cond.context.size()[1];
    let dim = t.model.cfg.dit.dim;
    let heads = t.model.cfg.dit.num_heads;

    let block_fwd = time(device, || Ok(drop(tch::no_grad(|| block.forward(&x, &cond)))))?;
    let mut params: Vec<Tensor> = Vec::new();
    let x_in = x.detach().set_requires_grad(true);
    params.push(x_in.shallow_clone());
    for l in [&block.self_attn.q, &block.self_attn.k, &block.self_attn.v, &block.self_attn.o, &block.cross_attn.q, &block.cross_attn.k, &block.cross_attn.v, &block.cross_attn.o, &block.ffn.l0, &block.ffn.l2] {
        params.extend([l.weight.shallow_clone(), l.bias.shallow_clone()].into_iter().filter(Tensor::requires_grad));
    }
    let block_both = time(device, || backward(&block.forward(&x_in, &cond), &params))?;

    let (self_fwd, self_both) = attention_core(batch, rows, rows, dim, heads, kind, device)?;
    let (cross_fwd, cross_both) = attention_core(batch, rows, keys, dim, heads, kind, device)?;
    let mut lin = (0.0, 0.0, 0.0);
    let sa = &block.self_attn;
    let ca = &block.cross_attn;
    for (l, n) in [(&sa.q, rows), (&sa.k, rows), (&sa.v, rows), (&sa.o, rows), (&ca.q, rows), (&ca.k, keys), (&ca.v, keys), (&ca.o, rows), (&block.ffn.l0, rows), (&block.ffn.l2, rows)] {
        let (f, b, flops) = linear(l, batch, n, device)?;
        lin = (lin.0 + f, lin.1 + b, lin.2 + flops);
    }
    let attn = (self_fwd + cross_fwd, self_both + cross_both);
    let rest = (block_fwd - attn.0 - lin.0, block_both - attn.1 - lin.1);

    // Per micro-step: every block forward (+ backward), the recomputed ones forward again.
    let n = t.model.dit.blocks.len() as f64;
    let recomputed = if t.cfg.train.recompute { n - (t.cfg.train.recompute_keep_last as f64).min(n) } else { 0.0 };
    let micro = t.cfg.train.grad_accum as f64;
    let per_step = |(fwd, both): (f64, f64)| micro * (n * both + recomputed * fwd);
    let (a, l, r) = (per_step(attn), per_step((lin.0, lin.1)), per_step(rest));
    let blocks = a + l + r;
    let share = |s: f64| 100.0 * s / step_seconds;
    let mut out = vec![
        format!(
            "breakdown of a {step_seconds:.3} s step ({micro} micro-batches of {batch}; {n} blocks of {rows} tokens, {recomputed} recomputed), from one block timed alone: forward {:.2} ms, forward+backward {:.2} ms",
            block_fwd * 1e3,
            block_both * 1e3
        ),
        format!("  attention cores (self + cross)        {a:.3} s  {:5.1}%  (one block: {:.2} / {:.2} ms fwd / fwd+bwd)", share(a), attn.0 * 1e3, attn.1 * 1e3),
        format!(
            "  linear layers (10 per block)          {l:.3} s  {:5.1}%  (one block: {:.2} / {:.2} ms; {:.0} TFLOP/s in fwd+bwd)",
            share(l),
            lin.0 * 1e3,
            lin.1 * 1e3,
            lin.2 / lin.1 / 1e12
        ),
        format!("  norms, modulation, RoPE, gates, adds  {r:.3} s  {:5.1}%  (one block: {:.2} / {:.2} ms)", share(r), rest.0 * 1e3, rest.1 * 1e3),
        format!("  outside the blocks                    {:.3} s  {:5.1}%  (embeddings, head, loss, AdamW, exposed collectives, host gaps)", step_seconds - blocks, share(step_seconds - blocks)),
    ];
    if collective_seconds > 0.0 {
        out.push(format!("  collectives (GPU time, overlapped or not) {collective_seconds:.3} s  {:5.1}%", share(collective_seconds)));
    }
    Ok(out)
}
