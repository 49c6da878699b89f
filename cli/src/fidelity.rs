//! `bwm fidelity`: the fidelity report of `bwm_inference::fidelity` from the command line.

use std::path::PathBuf;

use anyhow::Result;
use bwm_inference::fidelity::FidelityOptions;
use clap::Args;

use crate::world_model::{EpisodeArgs, InFlightArgs, WorldModelArgs};

#[derive(Args)]
pub struct FidelityArgs {
    #[command(flatten)]
    wm: WorldModelArgs,
    #[command(flatten)]
    episode: EpisodeArgs,
    /// Dataset of held-out episodes (x0, recorded actions and the real frames).
    #[arg(long)]
    data: PathBuf,
    /// Episode positions to score (default: all); at least two, as each is also driven by
    /// another's actions (the next listed episode of the same task).
    #[arg(long, value_delimiter = ',')]
    episodes: Vec<usize>,
    /// Horizons (frames after x0) at which mean PSNR/SSIM are reported, besides the full episode.
    #[arg(long, value_delimiter = ',', default_value = "8,16,32,64")]
    horizons: Vec<usize>,
    /// Side-by-side videos per task (real | own actions | other actions | zero actions |
    /// copy-last-frame).
    #[arg(long, default_value_t = 4)]
    videos: usize,
    #[command(flatten)]
    in_flight: InFlightArgs,
    /// Output folder: fidelity.json, episodes.jsonl, psnr_<task>.svg, ssim_<task>.svg, videos/. A
    /// run with the same settings into the same folder keeps the episodes already scored.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(a: FidelityArgs) -> Result<()> {
    let options = FidelityOptions {
        data: a.data,
        episodes: a.episodes,
        reading: a.episode.flags(),
        max_frames: a.episode.max_frames,
        horizons: a.horizons,
        videos: a.videos,
        in_flight: a.in_flight.get(),
        streams: a.in_flight.streams(),
        out: a.out,
    };
    bwm_inference::fidelity::run(&a.wm.options(), &options)
}
