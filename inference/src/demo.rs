//! `bwm demo`: the tiny model on the bundled episodes. Until a trained tiny VAE exists, the
//! condition latents are seeded random stand-ins; the actions are the episode's real ones.

use std::path::PathBuf;

use anyhow::{ensure, Result};
use bwm_data::{ActionSpec, ActionStats, BwmDataset};
use bwm_model::{sampler::{sample_chunk, Eager}, BwmModel, FlowSchedule, ModelConfig};
use tch::{Device, Kind, Tensor};

/// What `bwm demo` samples: a clip of one episode of a BWM-layout dataset.
#[derive(Clone, Debug)]
pub struct DemoOptions {
    /// Dataset in the BWM layout (demo.jsonl, stat.json, parquet, mp4).
    pub data: PathBuf,
    /// Episode (line of demo.jsonl) to take the clip from.
    pub episode: usize,
    /// First frame of the clip's future; history and x0 come before it.
    pub start: usize,
    /// History frames H and future frames K (both multiples of 4).
    pub history: usize,
    pub future: usize,
    /// Euler steps (shift 5).
    pub steps: usize,
    pub seed: i64,
}

/// Prints the dataset's episodes, the clip's actions raw and normalized, then samples the clip's
/// future latents with the tiny model on random weights, step by step.
pub fn run(args: &DemoOptions) -> Result<()> {
    ensure!(args.history % 4 == 0 && args.future % 4 == 0 && args.future > 0, "--history and --future must be multiples of 4");
    let ds = BwmDataset::open(&args.data)?;
    let spec = ActionSpec::eef_abs();
    let stats = ActionStats::read(&ds.root.join("stat.json"), &spec.stats_group)?;
    ensure!(
        stats.dim() == spec.dim(),
        "{}: group '{}' has statistics of {} values, the {} actions {}",
        ds.root.join("stat.json").display(),
        spec.stats_group,
        stats.dim(),
        spec.column,
        spec.dim()
    );
    println!("dataset {}: {} episodes", ds.root.display(), ds.episodes.len());
    for (i, ep) in ds.episodes.iter().enumerate() {
        println!("  [{i}] {} frames, task {}, {}", ep.length, ep.task, ep.action);
    }
    let ep = ds.episodes.get(args.episode).ok_or_else(|| {
        anyhow::anyhow!("--episode {} out of range (the dataset has {})", args.episode, ds.episodes.len())
    })?;
    let raw = ds.actions(ep, &spec)?;
    ensure!(
        args.start + args.future <= raw.len(),
        "episode {} has {} frames; the clip needs frames up to {}",
        args.episode,
        raw.len(),
        args.start + args.future
    );
    // Clip frames: x0, then H history frames before `start` (x0 where the episode has none), then K future.
    let history: Vec<usize> = (0..args.history).map(|j| (args.start + j).saturating_sub(args.history)).collect();
    let frames: Vec<usize> =
        std::iter::once(0).chain(history).chain(args.start..args.start + args.future).collect();
    let normalized: Vec<f32> = frames.iter().flat_map(|&f| stats.normalize(&raw[f])).collect();
    let actions = Tensor::from_slice(&normalized).view([1, frames.len() as i64, spec.indices.len() as i64]);
    println!(
        "clip: x0 + {} history + {} future frames = {} action frames (pixel frames {:?})",
        args.history,
        args.future,
        frames.len(),
        frames
    );
    println!("  action[x0] raw        {:?}", fmt(&raw[0]));
    println!("  action[x0] normalized {:?}", fmt(&stats.normalize(&raw[0])));

    let cfg = ModelConfig::preset("tiny")?;
    let model = BwmModel::random(&cfg, Kind::Float, Device::Cpu, args.seed)?;
    let (cond, fut) = (1 + args.history as i64 / 4, args.future as i64 / 4);
    println!(
        "model: tiny DiT (dim {}, {} layers) + action encoder, {} parameters, random weights (seed {})",
        cfg.dit.dim,
        cfg.dit.num_layers,
        model.store.num_parameters(),
        args.seed
    );
    tch::manual_seed(args.seed + 1);
    let prefix = Tensor::randn([1, 48, cond, 4, 6], (Kind::Float, Device::Cpu));
    let noise = Tensor::randn([1, 48, cond + fut, 4, 6], (Kind::Float, Device::Cpu));
    let schedule = FlowSchedule::inference(args.steps, 5.0);
    println!("sampling {} latent frames ({cond} condition + {fut} future) with {} Euler steps:", cond + fut, args.steps);
    let out = tch::no_grad(|| {
        sample_chunk(&mut Eager, &model, &prefix, &noise, &actions, &schedule, 1.0, &mut |i, _, v| {
            let future_v = v.narrow(2, cond, fut);
            println!(
                "  step {:>2}: t = {:7.2}  sigma = {:.4}  |v_future| rms = {:.4}",
                i + 1,
                schedule.timesteps[i],
                schedule.sigmas[i],
                future_v.square().mean(Kind::Float).sqrt().double_value(&[])
            );
        })
    })?;
    let kept = (out.narrow(2, 0, cond) - &prefix).abs().max().double_value(&[]);
    let future = out.narrow(2, cond, fut);
    println!("condition prefix kept exactly: max |diff| = {kept:e}");
    println!(
        "future latents: mean {:.4}, std {:.4}, checksum {:.6}",
        future.mean(Kind::Float).double_value(&[]),
        future.std(true).double_value(&[]),
        future.sum(Kind::Double).double_value(&[])
    );
    Ok(())
}

fn fmt(v: &[f32]) -> Vec<String> {
    v.iter().map(|x| format!("{x:.3}")).collect()
}
