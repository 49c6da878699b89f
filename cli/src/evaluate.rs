//! `bwm evaluate`: the policy evaluator of `bwm_inference::evaluate` from the command line.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use crate::world_model::WorldModelArgs;

#[derive(Args)]
pub struct EvaluateArgs {
    #[command(flatten)]
    wm: WorldModelArgs,
    /// Evaluation config (TOML): policies, tasks, observation layout, adapters, judge
    /// (see configs/evaluate-example.toml).
    #[arg(long)]
    config: PathBuf,
    /// Output folder: videos/, episodes.jsonl, success_rates.csv, policies.csv, summary.json.
    #[arg(long, default_value = "runs/evaluate")]
    out: PathBuf,
    /// Episodes run at once, their chunks generated as one batch (more keep the GPU busier; each
    /// episode's frames are what it gets alone).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    episodes_in_flight: u64,
}

pub fn run(a: EvaluateArgs) -> Result<()> {
    bwm_inference::evaluate::run(&a.wm.options(), &a.config, &a.out, a.episodes_in_flight as usize)
}
