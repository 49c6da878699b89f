//! A trained world model ready to roll out: the DiT with its action encoder, the VAE, the action
//! statistics and the rollout settings, opened from one set of options.

use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::rc::Rc;

use anyhow::{bail, ensure, Context, Result};
use bwm_checkpoints::open::{build_model, open_any, training_record, with_lora_adapters, OpenedWeights};
use bwm_checkpoints::run_info::{CheckpointState, RunInfo};
use bwm_checkpoints::contract::{self, InputContract};
use bwm_checkpoints::sampler::{self, UNRECORDED_STEPS};
use bwm_data::frames::parse_resolution;
use bwm_data::{ActionSpec, ActionStats, CameraSelection, ResizeMode};
use bwm_model::device::{parse_device, parse_kind};
use bwm_model::fp8::{quantize_linears, Fp8Scaling, BLOCK_LINEARS};
use bwm_model::rollout::{history_sigma_for_shift, Rollout, RolloutSpec};
use bwm_model::schedule::Solver;
use bwm_model::light_decoder::{LightDecoder, LightDecoderConfig};
use bwm_model::vae::{VaeConfig, WanVae};
use bwm_model::{BwmModel, ModelConfig, Residual};
use tch::{Device, Kind, Tensor};

use crate::graphed::GraphedDenoiser;

/// Where the weights come from and how chunks are generated. `bwm`'s world-model flags
/// (`--checkpoint`, `--vae`, `--history`, ...) set the fields of the same names.
#[derive(Clone, Debug)]
pub struct WorldModelOptions {
    /// Trained BWM weights: a checkpoint folder or file, or an exported repo (local or Hub id), in
    /// any layout `bwm convert` knows.
    pub checkpoint: Option<String>,
    /// LoRA adapters (a `bwm export` of a LoRA checkpoint, or a diffusers/PEFT LoRA folder or file
    /// for `WanTransformer3DModel`) merged into `checkpoint`'s weights at load.
    pub lora: Option<PathBuf>,
    /// Random weights instead of a checkpoint (timing and smoke tests only): of a model preset
    /// (tiny, wan22_ti2v_5b), or of the `[model]` of a run config (a `.toml` file).
    pub random_weights: Option<String>,
    /// Model preset when the checkpoint carries no config (tiny, wan22_ti2v_5b).
    pub model_preset: Option<String>,
    /// VAE weights: Wan2.2_VAE.pth, its safetensors, or a `bwm train-vae` output; None: a random
    /// full-width Wan2.2 VAE (timing only).
    pub vae: Option<PathBuf>,
    /// Decode the generated chunks with this light decoder (`bwm train-light-decoder` for the
    /// same VAE) instead of the VAE's decoder; the VAE still encodes the condition frames.
    pub light_decoder: Option<PathBuf>,
    /// A light decoder of random weights instead (timing only).
    pub random_light_decoder: bool,
    /// The stat.json the model was trained with (turns raw actions into the model's [-1, 1]);
    /// None: the statistics in the weights' input contract, else `dataset_stats`.
    pub stats: Option<PathBuf>,
    /// A dataset's own `stat.json` (`with_stats_beside`), used only when neither `stats` nor the
    /// weights' contract gives statistics.
    pub dataset_stats: Option<PathBuf>,
    /// Statistics group of the action definition (state_pose for eef_abs).
    pub stats_group: String,
    /// auto, cpu, cuda or cuda:N.
    pub device: String,
    /// Weights and activations: auto (bf16 on CUDA, f32 on CPU), bf16 or f32.
    pub dtype: String,
    /// dtype of the DiT's residual stream; None: what the checkpoint was trained with, else f32.
    pub residual: Option<Residual>,
    /// History frames H in each chunk's condition; None: the weights' contract's (the training
    /// clips' H), else 8. A value the contract contradicts is refused.
    pub history: Option<usize>,
    /// Frames K generated per chunk; None: the contract's, else 72.
    pub future: Option<usize>,
    /// Sampler steps per chunk; None: the sampler recorded in the weights' input contract
    /// (`contract.json`), else 50.
    pub sample_steps: Option<usize>,
    /// The flow-matching shift of the sampler's grid; None: the shift the weights were trained
    /// with (a training checkpoint's `objective.shift`, an export's schedule), else Wan's 5.
    pub shift: Option<f64>,
    /// How the sampler steps: Euler (the reference's) or DPM-Solver++(2M); None: the weights'
    /// recorded sampler, else Euler.
    pub solver: Option<Solver>,
    /// Noise level of the history latents; None: the level the weights were trained with (a
    /// training checkpoint's run config, an export's schedule), else their training grid's sigma
    /// 50 steps from clean (the BWM release's 0.2083 at shift 5); 0 turns it off.
    pub history_sigma: Option<f64>,
    /// Classifier-free guidance by the actions (1: off; see `sample_chunk`).
    pub guidance: f64,
    pub seed: u64,
    /// The DiT blocks' linear layers in FP8 with this scaling (None: the weights' dtype).
    pub fp8: Option<Fp8Scaling>,
    /// The sampler's forward pass recorded as a CUDA graph per input shape and replayed
    /// (`graphed::GraphedDenoiser`); CUDA only.
    pub cuda_graph: bool,
}

impl Default for WorldModelOptions {
    fn default() -> Self {
        Self {
            checkpoint: None,
            lora: None,
            random_weights: None,
            model_preset: None,
            vae: None,
            light_decoder: None,
            random_light_decoder: false,
            stats: None,
            dataset_stats: None,
            stats_group: "state_pose".into(),
            device: "auto".into(),
            dtype: "auto".into(),
            residual: None,
            history: None,
            future: None,
            sample_steps: None,
            shift: None,
            solver: None,
            history_sigma: None,
            guidance: 1.0,
            seed: 0,
            fp8: None,
            cuda_graph: false,
        }
    }
}

/// Guidance by the actions contrasts the model's prediction with its prediction under the null
/// action condition, which only a model trained with action dropout has learned; weights whose
/// training recorded none are refused (weights that record nothing are taken at their word).
fn check_guidance(guidance: f64, trained_action_dropout: Option<f64>) -> Result<()> {
    ensure!(
        guidance == 1.0 || trained_action_dropout != Some(0.0),
        "--guidance {guidance} needs a model trained with objective.action_dropout > 0 (the null action condition it guides against); these weights were trained without it. Use --guidance 1"
    );
    Ok(())
}

/// The model that `--random-weights NAME` builds: a preset, or a run config's `[model]` (read as a
/// checkpoint's stored run config is, by `RunInfo`: the other sections are the trainer's business).
fn random_model_config(name: &str) -> Result<ModelConfig> {
    if name.ends_with(".toml") {
        return Ok(RunInfo::load(Path::new(name)).with_context(|| format!("--random-weights {name}"))?.model);
    }
    ModelConfig::preset(name).with_context(|| format!("--random-weights {name} (a preset, or a run config ending in .toml)"))
}

pub struct WorldModel {
    pub model: BwmModel,
    pub vae: WanVae,
    /// Decodes the generated chunks in place of the VAE's decoder, where one was given.
    pub light_decoder: Option<LightDecoder>,
    pub stats: Option<ActionStats>,
    pub spec: RolloutSpec,
    pub device: Device,
    /// How the DiT blocks' linear layers run in FP8, if they do.
    pub fp8: Option<Fp8Scaling>,
    /// Runs the sampler's forward passes of every rollout from CUDA graphs (`--cuda-graph`).
    pub graphed: Option<Rc<RefCell<GraphedDenoiser>>>,
    /// The frame size (width, height) the weights were trained at, where they record it (their
    /// contract; an older export's `conditioning.resolution` or checkpoint's latent cache).
    pub trained_resolution: Option<(u32, u32)>,
    /// What a caller must send the model (`bwm_checkpoints::contract`): the weights' own, or for
    /// weights without one, the action width alone.
    pub contract: InputContract,
}

/// How a caller asks for a dataset's episodes to be read (`bwm rollout` and `bwm fidelity`'s
/// flags of the same names); None and empty take the weights' contract's (`EpisodeReading`).
#[derive(Debug, Clone, Default)]
pub struct EpisodeFlags {
    /// A preset (eef_abs, joint_abs, eef_delta, joint_delta, robotwin_eef_abs), COLUMN:INDICES
    /// (e.g. observation.state:0-3) or a spec JSON file.
    pub actions: Option<String>,
    /// Cameras; several are stacked top to bottom.
    pub camera: Vec<String>,
    /// Frame size WIDTHxHEIGHT.
    pub resolution: Option<String>,
    /// How frames of another aspect ratio are fitted to the size.
    pub resize: Option<ResizeMode>,
}

/// How a dataset's episodes are read for a model: as asked, else as its contract says, else
/// BWM's defaults (`eef_abs`, the dataset's default camera, 640x480, crop); what is asked is
/// checked against the contract.
#[derive(Debug, Clone)]
pub struct EpisodeReading {
    pub actions: ActionSpec,
    pub cameras: CameraSelection,
    /// (width, height).
    pub size: (u32, u32),
    pub resize: ResizeMode,
}

/// A file's size and modification time (nanoseconds since the epoch), or those of a folder's
/// files by path inside it (two levels down: an export's component folders); null where `path` is
/// not on this machine (a Hub id).
fn file_version(path: &Path) -> serde_json::Value {
    fn one(m: &std::fs::Metadata) -> serde_json::Value {
        let modified = m.modified().ok().and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map(|d| d.as_nanos().to_string());
        serde_json::json!([m.len(), modified])
    }
    fn walk(dir: &Path, prefix: &str, depth: usize, files: &mut serde_json::Map<String, serde_json::Value>) {
        for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let name = format!("{prefix}{}", entry.file_name().to_string_lossy());
            match entry.metadata() {
                Ok(m) if m.is_file() => {
                    files.insert(name, one(&m));
                }
                Ok(m) if m.is_dir() && depth > 0 => walk(&entry.path(), &format!("{name}/"), depth - 1, files),
                _ => {}
            }
        }
    }
    match std::fs::metadata(path) {
        Ok(m) if m.is_dir() => {
            let mut files = serde_json::Map::new();
            walk(path, "", 1, &mut files);
            serde_json::Value::Object(files)
        }
        Ok(m) => one(&m),
        Err(_) => serde_json::Value::Null,
    }
}

impl WorldModelOptions {
    /// What decides the frames these options generate with a loaded model's resolved `spec`: the
    /// weights, VAE, decoder and statistics by path and by the version of the files there (each
    /// file's size and modification time, a folder's files one level down), so that weights
    /// trained again at the same path are not taken for the earlier ones; and the numeric settings.
    /// Commands that resume a run into the same folder (`fidelity`, `rollout --resume`) compare it.
    pub fn identity(&self, spec: &RolloutSpec) -> serde_json::Value {
        let path = |p: Option<&Path>| p.map(|p| serde_json::json!({ "path": p.display().to_string(), "version": file_version(p) }));
        serde_json::json!({
            "checkpoint": path(self.checkpoint.as_deref().map(Path::new)),
            "lora": path(self.lora.as_deref()),
            "random_weights": self.random_weights,
            "model_preset": self.model_preset,
            "vae": path(self.vae.as_deref()),
            "light_decoder": path(self.light_decoder.as_deref()),
            "random_light_decoder": self.random_light_decoder,
            "stats": path(self.stats.as_deref()),
            "dataset_stats": path(self.dataset_stats.as_deref()),
            "stats_group": self.stats_group,
            "dtype": self.dtype,
            "residual": format!("{:?}", self.residual),
            "fp8": self.fp8.map(|s| s.to_string()),
            "spec": {
                "history": spec.history, "future": spec.future, "steps": spec.steps, "shift": spec.shift,
                "solver": spec.solver.to_string(), "guidance": spec.guidance, "seed": spec.seed, "history_sigma": spec.history_sigma,
            },
        })
    }

    /// These options, with the `stat.json` beside `dataset` (when it exists) as the statistics of
    /// last resort: used when neither `--stats` nor the weights' contract gives any.
    pub fn with_stats_beside(&self, dataset: Option<&Path>) -> WorldModelOptions {
        let mut options = self.clone();
        options.dataset_stats = dataset.map(|d| d.join("stat.json")).filter(|p| p.exists());
        options
    }

    /// The rollout settings, for weights trained with history noise `trained_history_sigma` and
    /// shift `trained_shift` (None: the default or not recorded). Unset history noise is the
    /// level training gave it at that shift, whatever the sampler's `--shift`.
    /// `sampler` is the resolved (steps, solver): `bwm_checkpoints::sampler::resolve`.
    /// `chunk` is the resolved (history, future): `InputContract::chunk_or`.
    pub fn spec(&self, sampler: (usize, Solver), chunk: (usize, usize), trained_history_sigma: Option<f64>, trained_shift: Option<f64>) -> Result<RolloutSpec> {
        let trained_grid = trained_shift.unwrap_or(bwm_model::schedule::DEFAULT_SHIFT);
        let sigma = self.history_sigma.or(trained_history_sigma).unwrap_or_else(|| history_sigma_for_shift(trained_grid));
        let spec = RolloutSpec {
            history: chunk.0,
            future: chunk.1,
            steps: sampler.0,
            shift: self.shift.unwrap_or(trained_grid),
            solver: sampler.1,
            history_sigma: (sigma > 0.0).then_some(sigma),
            guidance: self.guidance,
            seed: self.seed,
        };
        spec.validate().context("rollout settings (--history/--future/--sample-steps/--shift/--history-sigma/--guidance)")?;
        Ok(spec)
    }

    pub fn load(&self) -> Result<WorldModel> {
        // Wrong flags are named before any weights are opened.
        let unrecorded = InputContract::unknown();
        self.spec((self.sample_steps.unwrap_or(UNRECORDED_STEPS), self.solver.unwrap_or_default()), unrecorded.chunk_or(self.history, self.future)?, None, None)?;
        let device = parse_device(&self.device)?;
        let graphed = if self.cuda_graph { Some(Rc::new(RefCell::new(GraphedDenoiser::new(device)?))) } else { None };
        let kind = match self.dtype.as_str() {
            "auto" if device.is_cuda() => Kind::BFloat16,
            "auto" => Kind::Float,
            s => parse_kind(s)?,
        };
        let preset = self.model_preset.as_deref().map(ModelConfig::preset).transpose()?;
        ensure!(self.lora.is_none() || self.checkpoint.is_some(), "--lora needs --checkpoint: the base weights its adapters go onto");
        // The residual stream the weights were trained with, unless --residual says otherwise.
        let mut recorded = None;
        let (mut model, trained, trained_history_sigma, trained_shift, trained_resolution) = match (&self.checkpoint, &self.random_weights) {
            (Some(ckpt), _) => {
                let mut opened = open_any(ckpt).with_context(|| format!("--checkpoint {ckpt}"))?;
                recorded = contract::read(&opened.location).with_context(|| format!("--checkpoint {ckpt}"))?.map(|c| (c, contract::path_of(&opened.location)));
                let record = training_record(&opened).with_context(|| format!("--checkpoint {ckpt}"))?;
                let resolution = recorded.as_ref().and_then(|(c, _)| c.frames.as_ref()).map(|f| (f.width, f.height)).or_else(|| trained_resolution(&opened));
                check_guidance(self.guidance, record.action_dropout).with_context(|| format!("--checkpoint {ckpt}"))?;
                if let Some(adapters) = &self.lora {
                    opened = with_lora_adapters(opened, adapters).with_context(|| format!("--lora {}", adapters.display()))?;
                }
                let trained = record.residual.map(|r| r.parse::<Residual>().map_err(|e| anyhow::anyhow!("--checkpoint {ckpt}: model.residual {e}"))).transpose()?;
                (build_model(opened, preset.as_ref(), kind, device).with_context(|| format!("--checkpoint {ckpt}"))?, trained, record.history_sigma, record.shift, resolution)
            }
            (None, Some(name)) => (BwmModel::random(&random_model_config(name)?, kind, device, self.seed as i64)?, None, None, None, None),
            (None, None) => bail!("pass --checkpoint (trained weights) or --random-weights PRESET"),
        };
        let action_dim = model.cfg.action.action_dim as usize;
        let contract = match &recorded {
            Some((c, path)) => {
                c.check_action_dim(action_dim, "the weights").with_context(|| path.display().to_string())?;
                c.clone()
            }
            None => InputContract::of_model(action_dim),
        };
        let recorded_sampler = recorded.as_ref().and_then(|(c, p)| c.sampler.as_ref().map(|s| (s, p.as_path())));
        let (steps, solver, said) = sampler::resolve(self.sample_steps, self.solver, recorded_sampler);
        println!("{said}");
        let chunk = contract.chunk_or(self.history, self.future)?;
        let spec = self.spec((steps, solver), chunk, trained_history_sigma, trained_shift).context("the history noise and shift the weights were trained with")?;
        model.dit.residual = self.residual.or(trained).unwrap_or_default().kind(kind);
        if let Some(scaling) = self.fp8 {
            quantize_linears(&mut model, BLOCK_LINEARS, scaling).context("--fp8")?;
        }
        let vae = match &self.vae {
            Some(path) => WanVae::load_any(path, kind, device).with_context(|| format!("--vae {}", path.display()))?,
            None => WanVae::random(&VaeConfig::wan22(), kind, device, self.seed as i64)?.0,
        };
        ensure!(
            vae.cfg.z_dim == model.cfg.dit.in_dim,
            "the VAE's latents have {} channels but the model takes {}",
            vae.cfg.z_dim,
            model.cfg.dit.in_dim
        );
        let light_decoder = match (&self.light_decoder, self.random_light_decoder) {
            (Some(path), _) => Some(LightDecoder::load(path, kind, device).with_context(|| format!("--light-decoder {}", path.display()))?),
            (None, true) => Some(LightDecoder::random(&LightDecoderConfig::for_vae(&vae.cfg), kind, device, self.seed as i64)?.0),
            (None, false) => None,
        };
        if let (Some(d), Some(path)) = (&light_decoder, &self.light_decoder) {
            d.check_vae(&vae.cfg).with_context(|| format!("--light-decoder {} with this --vae", path.display()))?;
            println!("decoder: the light decoder {}", path.display());
        }
        let from_file = |path: &Path, how: &str| -> Result<ActionStats> {
            let s = ActionStats::read(path, &self.stats_group)?;
            ensure!(
                s.dim() == action_dim,
                "{} group '{}' has {} dimensions, the model takes {action_dim} action values",
                path.display(),
                self.stats_group,
                s.dim()
            );
            println!("action statistics: {} ({how})", path.display());
            Ok(s)
        };
        let recorded_stats = contract.actions.as_ref().and_then(|a| a.normalization.as_ref());
        let stats = match (&self.stats, recorded_stats, &self.dataset_stats) {
            (Some(path), _, _) => Some(from_file(path, "--stats")?),
            (None, Some(n), _) => {
                println!("action statistics: the weights' input contract (group '{}')", n.group);
                Some(n.stats.clone())
            }
            (None, None, Some(path)) => Some(from_file(path, "beside the dataset; the weights record none")?),
            (None, None, None) => None,
        };
        Ok(WorldModel { model, vae, light_decoder, stats, spec, device, fp8: self.fp8, graphed, trained_resolution, contract })
    }
}

/// The frame size (width, height) the opened weights were trained at: an export's
/// `conditioning.resolution`, else the resolution of the latent cache a training checkpoint's run
/// read (when that cache is still where the run found it). None when neither says.
fn trained_resolution(opened: &OpenedWeights) -> Option<(u32, u32)> {
    let pair = |v: &serde_json::Value| -> Option<(u32, u32)> {
        let a = v.as_array()?;
        match a.as_slice() {
            [w, h] => Some((u32::try_from(w.as_u64()?).ok()?, u32::try_from(h.as_u64()?).ok()?)),
            _ => None,
        }
    };
    if let Some(r) = opened.repo_config.as_ref().and_then(|c| c.conditioning.as_ref()).and_then(|c| c.get("resolution")) {
        return pair(r);
    }
    if !bwm_checkpoints::run_dir::is_training_checkpoint(&opened.location) {
        return None;
    }
    let cache = CheckpointState::read(&opened.location).ok()?.run.latent_cache?;
    let index: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(cache.join("index.json")).ok()?).ok()?;
    pair(index.get("resolution")?)
}

impl WorldModel {
    pub fn action_dim(&self) -> usize {
        self.model.cfg.action.action_dim as usize
    }

    /// How episodes are read for this model (see `EpisodeReading`): what `flags` ask for (the
    /// resolution a multiple of `multiple`), the rest from the contract; a flag that contradicts
    /// the contract is refused by its name.
    pub fn episode_reading(&self, flags: &EpisodeFlags, multiple: u32) -> Result<EpisodeReading> {
        let (actions, camera, resolution, resize) = (flags.actions.as_deref(), &flags.camera, flags.resolution.as_deref(), flags.resize);
        let c = &self.contract;
        // A definition asked for is checked whole (`check_definition` checks its width too); the
        // recorded one, or eef_abs where none is, by its width.
        let actions = match actions {
            Some(arg) => {
                let spec = ActionSpec::parse(arg).context("--actions")?;
                c.check_definition(&spec, &format!("--actions {arg}"))?;
                spec
            }
            None => {
                let spec = c.actions.as_ref().and_then(|a| a.definition.clone()).unwrap_or_else(ActionSpec::eef_abs);
                c.check_action_dim(spec.dim(), "--actions")?;
                spec
            }
        };
        let frames = c.frames.as_ref();
        let size = match resolution {
            Some(r) => {
                let size = parse_resolution(r, multiple).context("--resolution")?;
                c.check_frame_size(size.0, size.1, &format!("--resolution {r}"))?;
                size
            }
            None => frames.map(|f| (f.width, f.height)).unwrap_or((640, 480)),
        };
        let cameras = match (camera.is_empty(), frames) {
            (true, Some(f)) => CameraSelection { cameras: f.cameras.clone(), layout: f.layout },
            _ => CameraSelection::from_names(camera),
        };
        let resize = resize.or(frames.map(|f| f.resize)).unwrap_or_default();
        Ok(EpisodeReading { actions, cameras, size, resize })
    }

    /// The statistics that raw actions need.
    fn raw_stats(&self) -> Result<&ActionStats> {
        self.stats.as_ref().context("raw actions need the training statistics, and neither the weights' contract nor the dataset gives them: pass --stats stat.json")
    }

    /// Raw action rows to the model's normalized [rows, d_a] tensor (needs statistics).
    pub fn normalize(&self, rows: &[Vec<f32>]) -> Result<Tensor> {
        let stats = self.raw_stats()?;
        self.rows_to_tensor(rows.iter().map(|r| stats.normalize(r)).collect())
    }

    /// Normalized rows back to raw units (needs statistics).
    pub fn denormalize(&self, normalized: &Tensor) -> Result<Vec<Vec<f32>>> {
        let stats = self.raw_stats()?;
        Ok(tensor_rows(normalized)?.iter().map(|r| stats.denormalize(r)).collect())
    }

    /// Rows already in the model's [-1, 1] space.
    pub fn rows_to_tensor(&self, rows: Vec<Vec<f32>>) -> Result<Tensor> {
        let d = self.action_dim();
        ensure!(!rows.is_empty(), "no action rows");
        if let Some((i, r)) = rows.iter().enumerate().find(|(_, r)| r.len() != d) {
            bail!("action row {i} has {} values; the model takes {d}", r.len());
        }
        let flat: Vec<f32> = rows.into_iter().flatten().collect();
        Ok(Tensor::from_slice(&flat).view([-1, d as i64]))
    }

    /// Checks, before any work, that rollouts of `batch` episodes at `height` x `width` fit the
    /// model (multiples of 32) and that their chunk's frames can be held where the model runs: an
    /// impossible size is an error naming it (`what`, e.g. the flag that set it), not a failed
    /// allocation deep inside the first chunk.
    pub fn check_frame_size(&self, what: &str, height: i64, width: i64, batch: usize) -> Result<()> {
        ensure!(
            height > 0 && width > 0 && height % 32 == 0 && width % 32 == 0,
            "{what}: frames of {height}x{width} (HxW); rollouts need positive multiples of 32 (DiT patch x VAE stride)"
        );
        let frames = (1 + self.spec.history + self.spec.future) as i64;
        let shape = [batch as i64, 3, frames, height, width];
        crate::fallible::probe(&format!("{what}: frames of {height}x{width} (HxW): a chunk's frames"), &shape, Kind::Float, self.device)
    }

    /// A rollout from x0 `[3, H, W]` in [-1, 1] and its normalized action a0 `[d_a]`.
    pub fn rollout(&self, x0: &Tensor, a0: &Tensor) -> Result<Rollout<'_>> {
        self.rollout_with(self.spec.clone(), x0, a0)
    }

    /// `n` lanes of rollouts on this model's device (`--streams`), each on a CUDA stream of its own
    /// when there are several.
    pub fn lanes(&self, n: usize) -> Result<crate::lanes::Lanes> {
        ensure!(
            n <= 1 || self.graphed.is_none(),
            "--streams {n} with --cuda-graph: the recorded sampler step's buffers are shared by every rollout, so the lanes would write each other's; use one or the other"
        );
        crate::lanes::Lanes::new(self.device, n)
    }

    /// `rollout` with other settings than the loaded ones (a request's seed).
    pub fn rollout_with(&self, spec: RolloutSpec, x0: &Tensor, a0: &Tensor) -> Result<Rollout<'_>> {
        let mut rollout = Rollout::new(&self.model, &self.vae, spec, x0, a0)?;
        if let Some(d) = &self.light_decoder {
            rollout = rollout.with_light_decoder(d)?;
        }
        Ok(match &self.graphed {
            Some(g) => rollout.with_denoiser(g.clone()),
            None => rollout,
        })
    }
}

/// A [rows, d] float tensor as rows of f32.
pub fn tensor_rows(t: &Tensor) -> Result<Vec<Vec<f32>>> {
    let s = t.size();
    ensure!(s.len() == 2, "expected [rows, d] actions, got {s:?}");
    let flat = Vec::<f32>::try_from(t.to_device(Device::Cpu).to_kind(Kind::Float).contiguous().view([-1]))?;
    Ok(flat.chunks(s[1].max(1) as usize).map(|c| c.to_vec()).collect())
}

#[cfg(test)]
mod tests {
    use super::{check_guidance, Solver, WorldModelOptions};
    use bwm_model::rollout::default_history_sigma;

    #[test]
    fn history_noise_follows_the_flag_then_the_training_then_the_release() {
        let sigma = |flag: Option<f64>, trained: Option<f64>| WorldModelOptions { history_sigma: flag, ..Default::default() }.spec((4, Solver::Euler), (8, 72), trained, None).unwrap().history_sigma;
        assert_eq!(sigma(None, None), Some(default_history_sigma()), "weights that record nothing: the release's level");
        assert_eq!(sigma(None, Some(0.05)), Some(0.05), "the level the weights were trained with");
        assert_eq!(sigma(Some(0.1), Some(0.05)), Some(0.1), "--history-sigma overrides it");
        assert_eq!(sigma(Some(0.0), Some(0.05)), None, "--history-sigma 0 turns it off");
        assert_eq!(sigma(None, Some(0.0)), None, "weights trained on clean history sample on clean history");
    }

    #[test]
    fn the_sampler_shift_follows_the_flag_then_the_training_then_wan() {
        let shift = |flag: Option<f64>, trained: Option<f64>| WorldModelOptions { shift: flag, ..Default::default() }.spec((4, Solver::Euler), (8, 72), None, trained).unwrap().shift;
        assert_eq!(shift(None, None), bwm_model::schedule::DEFAULT_SHIFT, "weights that record nothing: Wan's shift");
        assert_eq!(shift(None, Some(2.0)), 2.0, "the shift the weights were trained with");
        assert_eq!(shift(Some(3.0), Some(2.0)), 3.0, "--shift overrides it");
        // History noise left unset in training was the trained grid's, and sampling matches it.
        let sigma = |flag: Option<f64>, trained: Option<f64>| WorldModelOptions { shift: flag, ..Default::default() }.spec((4, Solver::Euler), (8, 72), None, trained).unwrap().history_sigma;
        let at_2 = bwm_model::rollout::history_sigma_for_shift(2.0);
        assert!((at_2 - 2.0 * 0.05 / 1.05).abs() < 1e-9, "{at_2}");
        assert_eq!(sigma(None, Some(2.0)), Some(at_2));
        assert_eq!(sigma(Some(3.0), Some(2.0)), Some(at_2), "--shift moves the sampler's grid, not the trained history noise");
    }

    #[test]
    fn random_weights_take_a_preset_or_a_run_configs_model() {
        let repo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let metaworld = super::random_model_config(repo.join("configs/metaworld.toml").to_str().unwrap()).unwrap();
        assert_eq!((metaworld.dit.dim, metaworld.dit.num_layers, metaworld.action.action_dim), (768, 8, 4));
        assert_eq!(super::random_model_config("tiny").unwrap().dit.dim, 96);
        let e = format!("{:#}", super::random_model_config("huge").unwrap_err());
        assert!(e.contains("--random-weights huge") && e.contains(".toml"), "{e}");
        let e = format!("{:#}", super::random_model_config("missing.toml").unwrap_err());
        assert!(e.contains("--random-weights missing.toml"), "{e}");
    }

    #[test]
    fn cuda_graphs_are_refused_on_the_cpu_by_their_flag() {
        let options = WorldModelOptions { random_weights: Some("tiny".into()), device: "cpu".into(), cuda_graph: true, ..Default::default() };
        let e = options.load().err().expect("--cuda-graph on the CPU must be refused").to_string();
        assert!(e.contains("--cuda-graph needs a CUDA device"), "{e}");
    }

    #[test]
    fn guidance_needs_a_model_trained_with_action_dropout() {
        assert!(check_guidance(1.0, Some(0.0)).is_ok(), "no guidance: any model");
        assert!(check_guidance(2.0, Some(0.1)).is_ok());
        assert!(check_guidance(2.0, None).is_ok(), "weights that record nothing are not second-guessed");
        let e = check_guidance(2.0, Some(0.0)).unwrap_err().to_string();
        assert!(e.contains("--guidance 2") && e.contains("objective.action_dropout"), "{e}");
    }
}
