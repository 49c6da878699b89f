//! `bwm prepare`: the latent cache of `bwm_prepare` from the command line.

use std::path::PathBuf;

use anyhow::Result;
use bwm_data::frames::parse_resize;
use bwm_data::ResizeMode;
use bwm_prepare::PrepareOptions;
use clap::Args;

#[derive(Args)]
pub struct PrepareArgs {
    /// Dataset: BWM layout, LeRobot v2.1/v3.0 or RoboTwin 2.0 HDF5 (detected from the files).
    #[arg(long, default_value = "data/bwm-demo")]
    data: PathBuf,
    /// VAE: a `bwm train-vae` output, or the published Wan2.2_VAE.pth / safetensors (not needed
    /// with --merge).
    #[arg(long, conflicts_with = "random_vae")]
    vae: Option<PathBuf>,
    /// A random full-width Wan2.2 VAE instead of --vae: for timing `prepare` where no weights are
    /// at hand (the latents mean nothing).
    #[arg(long)]
    random_vae: bool,
    /// VAE weights and activations: auto (bf16 on CUDA, f32 on CPU), bf16 or f32.
    #[arg(long, default_value = "auto")]
    dtype: String,
    /// Output folder of the latent cache.
    #[arg(long)]
    out: PathBuf,
    /// Clip frame size WIDTHxHEIGHT (multiples of 32).
    #[arg(long, default_value = "640x480")]
    resolution: String,
    #[arg(long, default_value = "crop", value_parser = parse_resize)]
    resize: ResizeMode,
    /// Encode frames smaller than --resolution (after --resize) anyway; refused by default, since
    /// naively upscaled frames cost quality (re-render at the target size instead).
    #[arg(long)]
    allow_upscale: bool,
    /// History frames H and future frames K (multiples of 4).
    #[arg(long, default_value_t = 8)]
    history: usize,
    #[arg(long, default_value_t = 72)]
    future: usize,
    /// Frames between the starts of consecutive clips of an episode.
    #[arg(long, default_value_t = 8)]
    stride: usize,
    /// Action vector: a preset (eef_abs, joint_abs, eef_delta, joint_delta, robotwin_eef_abs),
    /// COLUMN:INDICES (e.g. observation.state:0-5,7), or a JSON file holding an action spec.
    /// Default: robotwin_eef_abs for RoboTwin HDF5, eef_abs otherwise.
    #[arg(long)]
    actions: Option<String>,
    /// Cameras, comma-separated; several are stacked top to bottom. Default: the dataset's camera.
    #[arg(long, value_delimiter = ',')]
    camera: Vec<String>,
    /// stat.json normalizing the actions. Default: the dataset's own stat.json when it has one,
    /// else statistics of the training episodes, written to OUT/stat.json.
    #[arg(long)]
    stats: Option<PathBuf>,
    /// Fraction of episodes held out for validation (by episode, deterministic in --seed, as
    /// `bwm stats` splits): left out of computed statistics, their clips last in the cache.
    #[arg(long, default_value_t = 0.0)]
    validation_fraction: f64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// A command enhancing each episode's first frame x0 before resizing (e.g. super-resolution):
    /// {in} is replaced by the path of a PNG to read, {out} by the PNG path to write.
    #[arg(long)]
    enhance_x0: Option<String>,
    /// Keep the clips' pixel frames in the cache (validation against real pixels).
    #[arg(long)]
    keep_frames: bool,
    /// Raw clips: store the clips' pixel frames (u8) and actions without encoding them; the
    /// trainer encodes each batch as it reads it (set data.vae). --vae is then optional and only
    /// fixes the latent shape (default: the Wan2.2 VAE's).
    #[arg(long)]
    raw: bool,
    /// Clips per shard file.
    #[arg(long, default_value_t = 64)]
    clips_per_shard: usize,
    /// Clips encoded by one VAE call.
    #[arg(long, default_value_t = 1)]
    batch: usize,
    /// This process's rank among --world processes sharing the work (default: RANK, or 0).
    #[arg(long)]
    rank: Option<usize>,
    /// Processes sharing the work (default: WORLD_SIZE, or 1).
    #[arg(long)]
    world: Option<usize>,
    /// Replace a cache in --out that was prepared with other arguments.
    #[arg(long)]
    overwrite: bool,
    /// Only write index.json from the ranks' finished shards (after a multi-process run).
    #[arg(long)]
    merge: bool,
    #[arg(long, default_value = "auto")]
    device: String,
}

pub fn run(a: PrepareArgs) -> Result<()> {
    bwm_prepare::run(&PrepareOptions {
        data: a.data,
        vae: a.vae,
        random_vae: a.random_vae,
        dtype: a.dtype,
        out: a.out,
        resolution: a.resolution,
        resize: a.resize,
        allow_upscale: a.allow_upscale,
        history: a.history,
        future: a.future,
        stride: a.stride,
        actions: a.actions,
        camera: a.camera,
        stats: a.stats,
        validation_fraction: a.validation_fraction,
        seed: a.seed,
        enhance_x0: a.enhance_x0,
        keep_frames: a.keep_frames,
        raw: a.raw,
        clips_per_shard: a.clips_per_shard,
        batch: a.batch,
        rank: a.rank,
        world: a.world,
        overwrite: a.overwrite,
        merge: a.merge,
        device: a.device,
    })
}
