//! `bwm evaluate`: the policy evaluator of `bwm_inference::evaluate` from the command line.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use crate::world_model::{InFlightArgs, WorldModelArgs};

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
    #[command(flatten)]
    in_flight: InFlightArgs,
}

pub fn run(a: EvaluateArgs) -> Result<()> {
    bwm_inference::evaluate::run(&a.wm.options(), &a.config, &a.out, a.in_flight.get(), a.in_flight.streams())
}
