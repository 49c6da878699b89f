//! `bwm rollout`: the data engine of `bwm_inference::rollout` from the command line.

use std::path::PathBuf;

use anyhow::Result;
use bwm_data::frames::parse_resize;
use bwm_data::ResizeMode;
use bwm_inference::rollout::{Drive, RolloutOptions};
use clap::Args;

use crate::world_model::WorldModelArgs;

#[derive(Args)]
pub struct RolloutArgs {
    #[command(flatten)]
    wm: WorldModelArgs,
    /// Dataset whose episodes give x0 (and the actions for --drive gt|perturbed).
    #[arg(long, required_unless_present = "inputs")]
    data: Option<PathBuf>,
    /// Episode positions to roll out (default: all).
    #[arg(long, value_delimiter = ',')]
    episodes: Vec<usize>,
    /// Instead of a dataset: JSON lines {"x0": image file, "actions": CSV file, "task": text}.
    #[arg(long, conflicts_with = "data")]
    inputs: Option<PathBuf>,
    /// Which actions drive the episodes: gt (the episode's own), perturbed (plus Gaussian noise of
    /// --perturb-std, clipped to [-1, 1]) or file (CSV files, the first row applied to x0).
    #[arg(long, default_value = "gt")]
    drive: Drive,
    /// --drive file with a dataset: the folder of `episode_<index:06>.csv` files.
    #[arg(long)]
    actions_dir: Option<PathBuf>,
    /// Standard deviation of the noise of --drive perturbed, in normalized action units.
    #[arg(long, default_value_t = 0.05)]
    perturb_std: f64,
    /// Action CSV files hold normalized values (default: raw, normalized with --stats).
    #[arg(long)]
    normalized: bool,
    /// How the dataset's action vectors are read: a preset (eef_abs, joint_abs, eef_delta,
    /// joint_delta, robotwin_eef_abs), COLUMN:INDICES (e.g. observation.state:0-3) or a spec JSON file.
    #[arg(long, default_value = "eef_abs")]
    actions: String,
    /// Cameras; several are stacked top to bottom (default: the dataset's default camera).
    #[arg(long, value_delimiter = ',')]
    camera: Vec<String>,
    /// Frame size WIDTHxHEIGHT (multiples of 32), the size the model was trained at.
    #[arg(long, default_value = "640x480")]
    resolution: String,
    #[arg(long, default_value = "crop", value_parser = parse_resize)]
    resize: ResizeMode,
    /// Longest episode to generate, in frames including x0 (default: the whole episode).
    #[arg(long)]
    max_frames: Option<usize>,
    /// Frame rate of --inputs episodes (dataset episodes keep theirs).
    #[arg(long, default_value_t = 30.0)]
    fps: f64,
    /// Output LeRobot v2.1 dataset folder.
    #[arg(long)]
    out: PathBuf,
    /// Continue an interrupted run into --out (finished episodes are kept).
    #[arg(long)]
    resume: bool,
}

pub fn run(a: RolloutArgs) -> Result<()> {
    let options = RolloutOptions {
        data: a.data,
        episodes: a.episodes,
        inputs: a.inputs,
        drive: a.drive,
        actions_dir: a.actions_dir,
        perturb_std: a.perturb_std,
        normalized: a.normalized,
        actions: a.actions,
        camera: a.camera,
        resolution: a.resolution,
        resize: a.resize,
        max_frames: a.max_frames,
        fps: a.fps,
        out: a.out,
        resume: a.resume,
    };
    bwm_inference::rollout::run(&a.wm.options(), &options)
}
