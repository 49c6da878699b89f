//! `bwm info`, `bwm bench-forward`, `bwm bench-vae` and `bwm bench-rollout`: `bwm_inference::bench`
//! from the command line.

use anyhow::{Context, Result};
use bwm_inference::bench::{BenchShape, ForwardOptions, VaeBenchOptions};
use bwm_model::device::{parse_device, parse_kind};
use clap::Args;

#[derive(Args)]
pub struct InfoArgs {
    /// Model preset whose parameters to count: wan22_ti2v_5b or tiny.
    #[arg(long, default_value = "wan22_ti2v_5b")]
    preset: String,
    /// Instead: the input contract of trained weights (a checkpoint folder or file, an exported
    /// repo, local or a Hub id): the actions, frames, chunk and sampler they expect.
    #[arg(long)]
    checkpoint: Option<String>,
    /// With --checkpoint: print the contract's JSON (contract.json) instead of lines.
    #[arg(long, requires = "checkpoint")]
    json: bool,
}

pub fn info(args: InfoArgs) -> Result<()> {
    let Some(weights) = &args.checkpoint else { return bwm_inference::bench::info(&args.preset) };
    let opened = bwm_checkpoints::open::open_any(weights).with_context(|| format!("--checkpoint {weights}"))?;
    let path = bwm_checkpoints::contract::path_of(&opened.location);
    let contract = match bwm_checkpoints::contract::read(&opened.location).with_context(|| format!("--checkpoint {weights}"))? {
        Some(c) => c,
        None => {
            let dim = opened.config.as_ref().map(|c| c.action.action_dim as usize);
            println!("{weights}: no {} (weights written before the input contract, or elsewhere); what the weights themselves say:", path.display());
            dim.map(bwm_checkpoints::contract::InputContract::of_model).unwrap_or_else(bwm_checkpoints::contract::InputContract::unknown)
        }
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&contract)?);
    } else {
        println!("input contract of {weights} ({})", path.display());
        for line in contract.describe() {
            println!("{line}");
        }
    }
    Ok(())
}

/// Where and at what clip size a benchmark runs.
#[derive(Args)]
pub struct BenchRun {
    #[arg(long, default_value = "cuda")]
    device: String,
    #[arg(long, default_value = "bf16")]
    dtype: String,
    /// Pixel frames of the clip (1 + H + K); must be 1+4k.
    #[arg(long, default_value_t = 81)]
    frames: i64,
    #[arg(long, default_value_t = 480)]
    height: i64,
    #[arg(long, default_value_t = 640)]
    width: i64,
}

impl BenchRun {
    fn shape(&self) -> Result<BenchShape> {
        Ok(BenchShape {
            device: parse_device(&self.device)?,
            kind: parse_kind(&self.dtype)?,
            frames: self.frames,
            height: self.height,
            width: self.width,
        })
    }
}

#[derive(Args)]
pub struct BenchForwardArgs {
    #[arg(long, default_value = "wan22_ti2v_5b")]
    preset: String,
    #[command(flatten)]
    run: BenchRun,
    /// Condition latents (x0 + history) that get timestep 0.
    #[arg(long, default_value_t = 3)]
    condition_latents: i64,
    #[arg(long, default_value_t = 1)]
    batch: i64,
    #[arg(long, default_value_t = 2)]
    warmup: usize,
    #[arg(long, default_value_t = 5)]
    iters: usize,
}

pub fn forward(args: BenchForwardArgs) -> Result<()> {
    bwm_inference::bench::forward(&ForwardOptions {
        shape: args.run.shape()?,
        preset: args.preset,
        condition_latents: args.condition_latents,
        batch: args.batch,
        warmup: args.warmup,
        iters: args.iters,
    })
}

#[derive(Args)]
pub struct BenchVaeArgs {
    #[command(flatten)]
    run: BenchRun,
    #[arg(long, default_value_t = 3)]
    iters: usize,
    /// Then stream-decode this many seconds of video (0 to skip), moving frames to the host.
    #[arg(long, default_value_t = 30.0)]
    stream_seconds: f64,
    #[arg(long, default_value_t = 24.0)]
    fps: f64,
}

pub fn vae(args: BenchVaeArgs) -> Result<()> {
    bwm_inference::bench::vae(&VaeBenchOptions { shape: args.run.shape()?, iters: args.iters, stream_seconds: args.stream_seconds, fps: args.fps })
}

#[derive(Args)]
pub struct BenchRolloutArgs {
    #[command(flatten)]
    wm: crate::world_model::WorldModelArgs,
    /// Frame size of the rollout.
    #[arg(long, default_value_t = 480)]
    height: i64,
    #[arg(long, default_value_t = 640)]
    width: i64,
    /// Chunks to generate (the first includes one-time CUDA start-up costs).
    #[arg(long, default_value_t = 2)]
    chunks: usize,
    /// Rollouts advanced together, one batch per chunk (as `bwm evaluate`'s episodes in flight).
    #[arg(long, default_value_t = 1)]
    batch: usize,
    /// Lanes the rollouts are split into, taking turns, each on a CUDA stream of its own (as
    /// `bwm evaluate --streams`).
    #[arg(long, default_value_t = 1)]
    streams: usize,
}

pub fn rollout(args: BenchRolloutArgs) -> Result<()> {
    bwm_inference::bench::rollout(&args.wm.load()?, args.height, args.width, args.chunks, args.batch, args.streams)
}
