//! `bwm rollout`: the data engine of `bwm_inference::rollout` from the command line.

use std::path::PathBuf;

use anyhow::Result;
use bwm_data::lerobot_writer::FrameStorage;
use bwm_inference::rollout::{Drive, RolloutOptions};
use clap::Args;

use crate::world_model::{EpisodeArgs, InFlightArgs, WorldModelArgs};

#[derive(Args)]
pub struct RolloutArgs {
    #[command(flatten)]
    wm: WorldModelArgs,
    #[command(flatten)]
    episode: EpisodeArgs,
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
    /// Frame rate of --inputs episodes (dataset episodes keep theirs).
    #[arg(long, default_value_t = 30.0)]
    fps: f64,
    /// Output LeRobot v2.1 dataset folder.
    #[arg(long)]
    out: PathBuf,
    /// Continue an interrupted run into --out (finished episodes are kept).
    #[arg(long)]
    resume: bool,
    /// How the output stores its frames: video (one mp4 per episode) or image (PNG cells in the
    /// episode's parquet). Default: as the dataset being resumed does, else video where this build
    /// has it and image otherwise.
    #[arg(long)]
    frame_storage: Option<FrameStorage>,
    #[command(flatten)]
    in_flight: InFlightArgs,
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
        reading: a.episode.flags(),
        max_frames: a.episode.max_frames,
        fps: a.fps,
        out: a.out,
        resume: a.resume,
        frame_storage: a.frame_storage,
        in_flight: a.in_flight.get(),
        streams: a.in_flight.streams(),
    };
    bwm_inference::rollout::run(&a.wm.options(), &options)
}
