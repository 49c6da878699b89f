//! The world-model flags that `bwm rollout`, `bwm fidelity`, `bwm evaluate`, `bwm serve` and
//! `bwm bench-rollout` share (they set `bwm_inference::WorldModelOptions`), and the episode flags
//! of `bwm rollout` and `bwm fidelity`.

use std::path::PathBuf;

use anyhow::Result;
pub use bwm_inference::world_model::{EpisodeFlags, WorldModel, WorldModelOptions};
use bwm_data::frames::parse_resize;
use bwm_data::ResizeMode;
use bwm_model::Residual;
use clap::Args;

#[derive(Args, Clone, Debug)]
pub struct WorldModelArgs {
    /// Trained BWM weights: a checkpoint folder or file, or an exported repo (local or Hub id), in
    /// any layout `bwm convert` knows.
    #[arg(long, required_unless_present = "random_weights")]
    pub checkpoint: Option<String>,
    /// LoRA adapters merged into --checkpoint's weights at load: a `bwm export` of a LoRA
    /// checkpoint, or a diffusers/PEFT LoRA folder or .safetensors for WanTransformer3DModel.
    #[arg(long, requires = "checkpoint")]
    pub lora: Option<PathBuf>,
    /// Random weights instead of a checkpoint (timing and smoke tests only): of a model preset
    /// (tiny, wan22_ti2v_5b), or of the `[model]` of a run config (a `.toml` file, e.g.
    /// configs/metaworld.toml).
    #[arg(long, conflicts_with = "checkpoint", value_name = "PRESET|CONFIG.toml")]
    pub random_weights: Option<String>,
    /// Model preset when the checkpoint carries no config (tiny, wan22_ti2v_5b).
    #[arg(long)]
    pub model_preset: Option<String>,
    /// VAE weights: Wan2.2_VAE.pth, its safetensors, or a `bwm train-vae` output.
    #[arg(long, required_unless_present = "random_vae")]
    pub vae: Option<PathBuf>,
    /// A random full-width Wan2.2 VAE instead (timing only).
    #[arg(long, conflicts_with = "vae")]
    pub random_vae: bool,
    /// Decode the generated chunks with a light decoder trained for this VAE (`bwm
    /// train-light-decoder`) instead of the VAE's decoder; the VAE still encodes the condition
    /// frames. Default: the VAE's decoder.
    #[arg(long)]
    pub light_decoder: Option<PathBuf>,
    /// A light decoder of random weights (TAEHV's widths) instead (timing only).
    #[arg(long, conflicts_with = "light_decoder")]
    pub random_light_decoder: bool,
    /// The stat.json the model was trained with (turns raw actions into the model's [-1, 1]).
    /// Default: the statistics in the weights' input contract (contract.json), else the dataset's
    /// own stat.json.
    #[arg(long)]
    pub stats: Option<PathBuf>,
    /// Statistics group of the action definition (state_pose for eef_abs).
    #[arg(long, default_value = "state_pose")]
    pub stats_group: String,
    #[arg(long, default_value = "auto")]
    pub device: String,
    /// Weights and activations: auto (bf16 on CUDA, f32 on CPU), bf16 or f32.
    #[arg(long, default_value = "auto")]
    pub dtype: String,
    /// dtype of the DiT's residual stream: f32 (the official Wan code) or model (the weights'
    /// dtype, as DiffSynth-Studio, which the BWM release trains and samples with; faster).
    /// Default: what the checkpoint was trained with (its run config's `model.residual`), else f32.
    #[arg(long)]
    pub residual: Option<Residual>,
    /// History frames H in each chunk's condition. Default: the training clips' H recorded in the
    /// weights' input contract (contract.json), else 8; another value than the contract's is
    /// refused.
    #[arg(long)]
    pub history: Option<usize>,
    /// Frames K generated per chunk. Default: the contract's, else 72; another value than the
    /// contract's is refused.
    #[arg(long)]
    pub future: Option<usize>,
    /// Sampler steps per chunk. Default: the sampler recorded in the weights' input contract
    /// (`contract.json`: the setting their fidelity was measured at, written by `bwm sampler`),
    /// else the reference's 50; the command says which it took. 4 held the Meta-World model's
    /// fidelity (docs/fidelity.md, "The sampler: 4 Euler steps").
    #[arg(long)]
    pub sample_steps: Option<usize>,
    /// The flow-matching shift of the sampler's grid (default: the shift the weights were trained
    /// with, `objective.shift`, else Wan's 5).
    #[arg(long)]
    pub shift: Option<f64>,
    /// How the sampler steps: euler (the reference's) or dpm++2m (DPM-Solver++(2M), second
    /// order at one model evaluation per step). Default: the weights' recorded sampler, else euler.
    #[arg(long)]
    pub solver: Option<bwm_model::schedule::Solver>,
    /// Noise level of the history latents (default: the level the weights were trained with,
    /// `objective.history_sigma`, else their training grid's sigma 50 steps from clean, 0.2083 at
    /// shift 5); 0 turns it off.
    #[arg(long)]
    pub history_sigma: Option<f64>,
    /// Classifier-free guidance by the actions: each step's velocity is v_null + w (v_actions -
    /// v_null), at two model evaluations per step. 1 (default) is off; other values need a model
    /// trained with `objective.action_dropout` > 0.
    #[arg(long, default_value_t = 1.0)]
    pub guidance: f64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The DiT blocks' linear layers in FP8 (e4m3, activations scaled on each call): tensor (one
    /// scale per tensor) or row (per token and output channel, CUDA only). Default: off.
    #[arg(long)]
    pub fp8: Option<bwm_model::fp8::Fp8Scaling>,
    /// Record the sampler's forward pass once per input shape as a CUDA graph and replay it: a
    /// small model's step is bound by launching its kernels (CUDA only; up to 4 shapes, the batch
    /// of episodes in flight shrinking as they end, each holding its own activations' memory).
    #[arg(long)]
    pub cuda_graph: bool,
}

impl WorldModelArgs {
    pub fn options(&self) -> WorldModelOptions {
        WorldModelOptions {
            checkpoint: self.checkpoint.clone(),
            lora: self.lora.clone(),
            random_weights: self.random_weights.clone(),
            model_preset: self.model_preset.clone(),
            vae: if self.random_vae { None } else { self.vae.clone() },
            light_decoder: self.light_decoder.clone(),
            random_light_decoder: self.random_light_decoder,
            stats: self.stats.clone(),
            dataset_stats: None,
            stats_group: self.stats_group.clone(),
            device: self.device.clone(),
            dtype: self.dtype.clone(),
            residual: self.residual,
            history: self.history,
            future: self.future,
            sample_steps: self.sample_steps,
            shift: self.shift,
            solver: self.solver,
            history_sigma: self.history_sigma,
            guidance: self.guidance,
            seed: self.seed,
            fp8: self.fp8,
            cuda_graph: self.cuda_graph,
        }
    }

    pub fn load(&self) -> Result<WorldModel> {
        self.options().load()
    }
}

/// How many episodes `bwm rollout`, `fidelity` and `evaluate` advance together.
#[derive(Args, Clone, Debug)]
pub struct InFlightArgs {
    /// Episodes run at once, each chunk of all of them one batch through the VAE and the DiT
    /// (more keep the GPU busier; every episode gets what it gets alone, in the usual order).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub episodes_in_flight: u64,
    /// Lanes the episodes in flight are split into, taking turns, each on a CUDA stream of its
    /// own: one lane's chunk runs on the GPU while the host reads, judges and drives another's,
    /// and one lane's decode can run beside another's DiT steps (at most the episodes in flight;
    /// not with --cuda-graph).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub streams: u64,
}

impl InFlightArgs {
    pub fn get(&self) -> usize {
        self.episodes_in_flight as usize
    }

    pub fn streams(&self) -> usize {
        self.streams as usize
    }
}

/// How `bwm rollout` and `bwm fidelity` read a dataset's episodes.
#[derive(Args, Clone, Debug)]
pub struct EpisodeArgs {
    /// How the dataset's action vectors are read: a preset (eef_abs, joint_abs, eef_delta,
    /// joint_delta, robotwin_eef_abs), COLUMN:INDICES (e.g. observation.state:0-3) or a spec JSON
    /// file. Default: the definition in the weights' input contract (contract.json), else eef_abs;
    /// another than the contract's is refused.
    #[arg(long)]
    pub actions: Option<String>,
    /// Cameras; several are stacked top to bottom (default: the contract's, else the dataset's
    /// default camera).
    #[arg(long, value_delimiter = ',')]
    pub camera: Vec<String>,
    /// Frame size WIDTHxHEIGHT. Default: the size the weights were trained at (their contract),
    /// else 640x480; another than the contract's is refused.
    #[arg(long)]
    pub resolution: Option<String>,
    /// How frames of another aspect ratio are fitted to --resolution: crop, pad or stretch
    /// (default: the contract's, else crop).
    #[arg(long, value_parser = parse_resize)]
    pub resize: Option<ResizeMode>,
    /// Longest rollout, in frames including x0 (default: the whole episode).
    #[arg(long)]
    pub max_frames: Option<usize>,
}

impl EpisodeArgs {
    pub fn flags(&self) -> EpisodeFlags {
        EpisodeFlags { actions: self.actions.clone(), camera: self.camera.clone(), resolution: self.resolution.clone(), resize: self.resize }
    }
}
