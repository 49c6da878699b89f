//! What `bwm prepare` is asked to do: its options (the command's flags), and the ones whose
//! defaults come from the environment or the dataset resolved (`--rank`/`--world`, `--actions`).

use std::path::{Path, PathBuf};

use anyhow::{ensure, Context, Result};
use bwm_data::{ActionSpec, ResizeMode};

/// The dataset, VAE, clip geometry and output of one `run` (the flags of `bwm prepare`).
#[derive(Clone, Debug)]
pub struct PrepareOptions {
    /// Dataset: BWM layout, LeRobot v2.1/v3.0 or RoboTwin 2.0 HDF5 (detected from the files).
    pub data: PathBuf,
    /// VAE: a `bwm train-vae` output, or the published Wan2.2_VAE.pth / safetensors (not needed
    /// with --merge).
    pub vae: Option<PathBuf>,
    /// A random full-width Wan2.2 VAE instead of --vae: for timing `prepare` where no weights are
    /// at hand (the latents mean nothing).
    pub random_vae: bool,
    /// VAE weights and activations: auto (bf16 on CUDA, f32 on CPU), bf16 or f32.
    pub dtype: String,
    /// Output folder of the latent cache.
    pub out: PathBuf,
    /// Clip frame size WIDTHxHEIGHT (multiples of 32).
    pub resolution: String,
    /// How frames of another aspect ratio are fitted to --resolution.
    pub resize: ResizeMode,
    /// Encode frames smaller than --resolution (after --resize) anyway; refused by default, since
    /// naively upscaled frames cost quality (re-render at the target size instead).
    pub allow_upscale: bool,
    /// History frames H and future frames K (multiples of 4).
    pub history: usize,
    pub future: usize,
    /// Frames between the starts of consecutive clips of an episode.
    pub stride: usize,
    /// Action vector: a preset (eef_abs, joint_abs, eef_delta, joint_delta, robotwin_eef_abs),
    /// COLUMN:INDICES (e.g. observation.state:0-5,7), or a JSON file holding an action spec.
    /// Default: robotwin_eef_abs for RoboTwin HDF5, eef_abs otherwise.
    pub actions: Option<String>,
    /// Cameras, comma-separated; several are stacked top to bottom. Default: the dataset's camera.
    pub camera: Vec<String>,
    /// stat.json normalizing the actions. Default: the dataset's own stat.json when it has one,
    /// else statistics of the training episodes, written to OUT/stat.json.
    pub stats: Option<PathBuf>,
    /// Fraction of episodes held out for validation (by episode, deterministic in --seed, as
    /// `bwm stats` splits): left out of computed statistics, their clips last in the cache.
    pub validation_fraction: f64,
    pub seed: u64,
    /// A command enhancing each episode's first frame x0 before resizing (e.g. super-resolution):
    /// {in} is replaced by the path of a PNG to read, {out} by the PNG path to write.
    pub enhance_x0: Option<String>,
    /// Keep the clips' pixel frames in the cache (validation against real pixels).
    pub keep_frames: bool,
    /// Raw clips: store the clips' pixel frames (u8) and actions without encoding them; the
    /// trainer encodes each batch as it reads it (set data.vae). --vae is then optional and only
    /// fixes the latent shape (default: the Wan2.2 VAE's).
    pub raw: bool,
    /// Clips per shard file.
    pub clips_per_shard: usize,
    /// Clips encoded by one VAE call.
    pub batch: usize,
    /// This process's rank among --world processes sharing the work (default: RANK, or 0).
    pub rank: Option<usize>,
    /// Processes sharing the work (default: WORLD_SIZE, or 1).
    pub world: Option<usize>,
    /// Replace a cache in --out that was prepared with other arguments.
    pub overwrite: bool,
    /// Only write index.json from the ranks' finished shards (after a multi-process run).
    pub merge: bool,
    pub device: String,
}

pub(crate) fn rank_and_world(rank: Option<usize>, world: Option<usize>) -> Result<(usize, usize)> {
    let env = |name: &str| -> Result<Option<usize>> {
        match std::env::var(name) {
            Ok(v) => Ok(Some(v.trim().parse().with_context(|| format!("{name}={v} is not a number"))?)),
            Err(_) => Ok(None),
        }
    };
    let rank = match rank {
        Some(r) => r,
        None => env("RANK")?.unwrap_or(0),
    };
    let world = match world {
        Some(w) => w,
        None => env("WORLD_SIZE")?.unwrap_or(1),
    };
    ensure!(world > 0 && rank < world, "--rank {rank} --world {world}: the rank must be below the world size");
    Ok((rank, world))
}

/// `--actions` (see `ActionSpec::parse`); None picks by dataset format.
pub(crate) fn action_spec(arg: Option<&str>, data: &Path) -> Result<ActionSpec> {
    let Some(arg) = arg else {
        let robotwin = !data.join("demo.jsonl").is_file()
            && !data.join("meta/info.json").is_file()
            && (matches!(data.extension().and_then(|e| e.to_str()), Some("hdf5" | "h5")) || (data.is_dir() && bwm_data::robotwin::has_hdf5_files(data)?));
        return Ok(if robotwin { ActionSpec::robotwin_eef_abs() } else { ActionSpec::eef_abs() });
    };
    ActionSpec::parse(arg).context("--actions")
}
