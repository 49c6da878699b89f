//! `bwm stats`: per-dimension action statistics over a dataset's training split, written in the
//! BWM release's `stat.json` format (the normalization `bwm prepare` reads).

use std::path::PathBuf;

use anyhow::Result;
use bwm_data::open_dataset;
use bwm_data::stats::{compute_stats, split_episodes, write_stat_json, SplitSpec, ValidationSize};
use bwm_data::ActionSpec;
use clap::Args;

#[derive(Args)]
pub struct StatsArgs {
    /// Dataset: BWM layout, LeRobot v2.1/v3.0 or RoboTwin 2.0 HDF5 (detected from the files).
    #[arg(long, default_value = "data/bwm-demo")]
    data: PathBuf,
    /// Output stat.json.
    #[arg(long)]
    out: PathBuf,
    /// Action definitions, each written as its stats group: eef_abs (state_pose), joint_abs
    /// (state_joint), eef_delta, joint_delta, robotwin_eef_abs.
    #[arg(long, value_delimiter = ',', default_value = "eef_abs")]
    actions: Vec<String>,
    /// Fraction of episodes held out for validation (by episode, deterministic in --seed).
    #[arg(long, default_value_t = 0.0)]
    validation_fraction: f64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

pub fn run(a: StatsArgs) -> Result<()> {
    let source = open_dataset(&a.data)?;
    let specs = a.actions.iter().map(|n| ActionSpec::parse(n)).collect::<Result<Vec<_>>>()?;
    let split = split_episodes(source.episodes(), &SplitSpec { seed: a.seed, validation: ValidationSize::Fraction(a.validation_fraction) })?;
    println!("stats: {} ({} episodes: {} for statistics, {} held out)", source.describe(), source.episodes().len(), split.train.len(), split.validation.len());
    let result = compute_stats(source.as_ref(), &split.train, &specs, None)?;
    for (name, s) in &result.groups {
        println!("  {name}: {} dims over {} frames; p01 {:?}", s.p01.len(), result.frames, s.p01.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>());
    }
    println!("  {}", result.report);
    write_stat_json(&a.out, &result.groups)?;
    println!("wrote {}", a.out.display());
    Ok(())
}
