//! `bwm bench-train`: `bwm_trainer::bench` from the command line.

use std::path::PathBuf;

use anyhow::Result;
use bwm_trainer::bench::{BenchTrainOptions, DistillBench};
use bwm_trainer::config::DEFAULT_TEACHER_SUBSTEPS;
use clap::Args;

#[derive(Args)]
pub struct BenchTrainArgs {
    #[arg(long, default_value = "configs/bwm-wan22-ti2v-5b.toml")]
    config: PathBuf,
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
    /// Pixel frames per clip: x0 + history + future.
    #[arg(long, default_value_t = 8)]
    history: usize,
    #[arg(long, default_value_t = 72)]
    future: usize,
    #[arg(long, default_value_t = 480)]
    height: i64,
    #[arg(long, default_value_t = 640)]
    width: i64,
    #[arg(long, default_value_t = 3)]
    steps: u64,
    /// After the steps, time one DiT block and its parts and print the step's breakdown
    /// (attention, linear layers, norms/elementwise, the rest; collectives).
    #[arg(long)]
    breakdown: bool,
    /// Record the steps after the first with libtorch's profiler into this Chrome trace (JSON,
    /// for chrome://tracing or Perfetto) and print where their GPU time went.
    #[arg(long, value_name = "TRACE")]
    profile: Option<PathBuf>,
    /// Scratch folder for the synthetic cache and the run's logs.
    #[arg(long, default_value = "runs/bench-train")]
    out: PathBuf,
    /// Time the step of step distillation ([distill]) instead, for a student of this many sampler
    /// steps, from a frozen teacher of random weights of the same model (actions never dropped).
    #[arg(long, value_name = "STUDENT_STEPS")]
    distill: Option<usize>,
    /// With --distill: the teacher's Euler steps per student step ([distill] teacher_substeps).
    #[arg(long, default_value_t = DEFAULT_TEACHER_SUBSTEPS, requires = "distill")]
    teacher_substeps: usize,
}

pub fn run(a: BenchTrainArgs) -> Result<()> {
    bwm_trainer::bench::run(&BenchTrainOptions {
        config: a.config,
        overrides: a.overrides,
        history: a.history,
        future: a.future,
        height: a.height,
        width: a.width,
        steps: a.steps,
        breakdown: a.breakdown,
        profile: a.profile,
        out: a.out,
        distill: a.distill.map(|student_steps| DistillBench { student_steps, teacher_substeps: a.teacher_substeps }),
    })
}
