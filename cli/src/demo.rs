//! `bwm demo`: `bwm_inference::demo` from the command line.

use std::path::PathBuf;

use anyhow::Result;
use bwm_inference::demo::DemoOptions;
use clap::Args;

#[derive(Args)]
pub struct DemoArgs {
    /// Dataset in the BWM layout (demo.jsonl, stat.json, parquet, mp4).
    #[arg(long, default_value = "data/bwm-demo")]
    data: PathBuf,
    /// Episode (line of demo.jsonl) to take the clip from.
    #[arg(long, default_value_t = 0)]
    episode: usize,
    /// First frame of the clip's future; history and x0 come before it.
    #[arg(long, default_value_t = 8)]
    start: usize,
    /// History frames H and future frames K (both multiples of 4).
    #[arg(long, default_value_t = 8)]
    history: usize,
    #[arg(long, default_value_t = 8)]
    future: usize,
    /// Euler steps (shift 5).
    #[arg(long, default_value_t = 8)]
    steps: usize,
    #[arg(long, default_value_t = 0)]
    seed: i64,
}

pub fn run(a: DemoArgs) -> Result<()> {
    bwm_inference::demo::run(&DemoOptions {
        data: a.data,
        episode: a.episode,
        start: a.start,
        history: a.history,
        future: a.future,
        steps: a.steps,
        seed: a.seed,
    })
}
