//! `bwm sampler`: show or record the sampler a checkpoint's fidelity was measured at
//! (`bwm_checkpoints::sampler`), which the world-model commands then use by default.

use std::path::PathBuf;

use anyhow::{bail, Result};
use bwm_checkpoints::sampler::{self, SamplerRecord, UNRECORDED_STEPS};
use bwm_model::schedule::Solver;
use clap::Args;

#[derive(Args)]
pub struct SamplerArgs {
    /// A training checkpoint's folder (`runs/NAME/checkpoints/step-N`), an export folder, or a
    /// weights file (the record goes beside it).
    #[arg(long)]
    checkpoint: PathBuf,
    /// Record this many sampler steps per chunk (with --measured); without it, show the record.
    #[arg(long, requires = "measured")]
    steps: Option<usize>,
    /// The solver to record with --steps.
    #[arg(long, default_value = "euler", requires = "steps")]
    solver: Solver,
    /// What measured the model's fidelity at this setting (a command and its result), kept in
    /// the record for whoever samples the weights later.
    #[arg(long, requires = "steps")]
    measured: Option<String>,
}

pub fn run(a: SamplerArgs) -> Result<()> {
    if !a.checkpoint.exists() {
        bail!("--checkpoint {}: no such file or folder", a.checkpoint.display());
    }
    match (a.steps, a.measured) {
        (Some(steps), Some(measured)) => {
            let path = sampler::write(&a.checkpoint, &SamplerRecord { steps, solver: a.solver, measured })?;
            println!("sampler: recorded {steps} {} steps in {}", a.solver.name(), path.display());
        }
        _ => match sampler::read(&a.checkpoint)? {
            Some(r) => println!("sampler: {} {} steps ({}: {})", r.steps, r.solver.name(), sampler::record_path(&a.checkpoint).display(), r.measured),
            None => println!("sampler: none recorded for {}; the world-model commands sample it at {UNRECORDED_STEPS} Euler steps unless told otherwise", a.checkpoint.display()),
        },
    }
    Ok(())
}
