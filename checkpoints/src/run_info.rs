//! What an export needs to know about the training run behind a checkpoint, read tolerantly from
//! the run config TOML stored in the checkpoint's `state.json` (this crate cannot depend on the
//! trainer, which depends on it; unknown sections are ignored here, the trainer validates them).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use bwm_model::lora::LoraConfig;
use bwm_model::config::{removed, Removed};
use bwm_model::{ActionConfig, DitConfig, ModelConfig};
use serde::Deserialize;

/// Where the run's initial weights came from (`model.init`).
#[derive(Debug, Clone, PartialEq)]
pub enum InitInfo {
    Random,
    WanPretrained(PathBuf),
    BwmCheckpoint(PathBuf),
}

#[derive(Debug, Clone, Default, Deserialize)]
struct RunPart {
    #[serde(default)]
    name: String,
    #[serde(default)]
    seed: u64,
}

#[derive(Debug, Clone, Deserialize)]
struct ModelPart {
    preset: String,
    #[serde(default)]
    dit: Option<DitConfig>,
    #[serde(default)]
    action: Option<ActionConfig>,
    #[serde(default)]
    dtype: Option<String>,
    #[serde(default)]
    residual: Option<String>,
    #[serde(default)]
    init: Option<toml::Value>,
    #[serde(default)]
    lora: Option<LoraConfig>,
}

#[derive(Debug, Clone, Default, Deserialize)]
struct DataPart {
    #[serde(default)]
    latent_cache: Option<PathBuf>,
    #[serde(default)]
    holdout_clips: usize,
}

#[derive(Debug, Clone, Default, Deserialize)]
struct ObjectivePart {
    #[serde(default)]
    shift: Option<f64>,
    #[serde(default)]
    history_sigma: Option<f64>,
    #[serde(default)]
    condition_latents: Option<i64>,
    #[serde(default)]
    action_dropout: Option<f64>,
    /// Removed (issue 69): read only to refuse a run that used it (`removed::MOTION_WEIGHT`).
    #[serde(default, deserialize_with = "removed::motion_weight")]
    #[allow(dead_code)]
    motion_weight: Removed,
}

#[derive(Debug, Clone, Default, Deserialize)]
struct OptimPart {
    #[serde(default)]
    lr: Option<f64>,
    #[serde(default)]
    ema_decay: Option<f64>,
}

#[derive(Debug, Clone, Default, Deserialize)]
struct TrainPart {
    #[serde(default)]
    steps: Option<u64>,
    #[serde(default)]
    micro_batch: Option<usize>,
    #[serde(default)]
    grad_accum: Option<usize>,
}

#[derive(Debug, Clone, Deserialize)]
struct RunToml {
    #[serde(default)]
    run: RunPart,
    model: ModelPart,
    #[serde(default)]
    data: DataPart,
    #[serde(default)]
    objective: ObjectivePart,
    #[serde(default)]
    optim: OptimPart,
    #[serde(default)]
    train: TrainPart,
}

/// The run config, as far as an export uses it.
#[derive(Debug, Clone)]
pub struct RunInfo {
    pub name: String,
    pub seed: u64,
    pub preset: String,
    pub model: ModelConfig,
    /// `f32` or `bf16`: the training dtype.
    pub dtype: Option<String>,
    /// `f32` or `model`: the DiT's residual stream in training (`model.residual`; absent = f32).
    pub residual: Option<String>,
    pub init: InitInfo,
    /// The run's LoRA adapters (`model.lora`): its checkpoints hold adapters, not whole weights.
    pub lora: Option<LoraConfig>,
    pub latent_cache: Option<PathBuf>,
    pub holdout_clips: usize,
    pub shift: Option<f64>,
    pub history_sigma: Option<f64>,
    pub condition_latents: Option<i64>,
    /// `objective.action_dropout`: the share of samples trained on the null action condition
    /// (absent = 0).
    pub action_dropout: Option<f64>,
    pub lr: Option<f64>,
    pub ema_decay: Option<f64>,
    pub steps_planned: Option<u64>,
    pub micro_batch: Option<usize>,
    pub grad_accum: Option<usize>,
    /// The TOML itself.
    pub toml: String,
}

impl RunInfo {
    /// Parses a run config TOML (`what` names it in errors).
    pub fn parse(text: &str, what: &str) -> Result<Self> {
        let raw: RunToml = toml::from_str(text).map_err(|e| anyhow::anyhow!("{what}: not a BWM run config: {}", e.to_string().trim()))?;
        let dit = match &raw.model.dit {
            Some(d) => d.clone(),
            None => DitConfig::preset(&raw.model.preset).with_context(|| format!("{what}: model.preset"))?,
        };
        let model = ModelConfig { dit, action: raw.model.action.clone().unwrap_or_default() };
        model.validate().with_context(|| format!("{what}: model section"))?;
        let init = match &raw.model.init {
            None => InitInfo::Random,
            Some(v) => {
                let from = v.get("from").and_then(|f| f.as_str()).unwrap_or("random");
                let path = v.get("path").and_then(|p| p.as_str()).map(PathBuf::from);
                match (from, path) {
                    ("random", _) => InitInfo::Random,
                    ("wan-pretrained", Some(p)) => InitInfo::WanPretrained(p),
                    ("bwm-checkpoint", Some(p)) => InitInfo::BwmCheckpoint(p),
                    (other, _) => bail!("{what}: model.init.from = '{other}' is not understood (random, wan-pretrained or bwm-checkpoint with a path)"),
                }
            }
        };
        Ok(Self {
            name: raw.run.name,
            seed: raw.run.seed,
            preset: raw.model.preset,
            model,
            dtype: raw.model.dtype,
            residual: raw.model.residual,
            init,
            lora: raw.model.lora,
            latent_cache: raw.data.latent_cache,
            holdout_clips: raw.data.holdout_clips,
            shift: raw.objective.shift,
            history_sigma: raw.objective.history_sigma,
            condition_latents: raw.objective.condition_latents,
            action_dropout: raw.objective.action_dropout,
            lr: raw.optim.lr,
            ema_decay: raw.optim.ema_decay,
            steps_planned: raw.train.steps,
            micro_batch: raw.train.micro_batch,
            grad_accum: raw.train.grad_accum,
            toml: text.to_string(),
        })
    }

    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading run config {}", path.display()))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// The base weights the run started from, when they are a file.
    pub fn init_path(&self) -> Option<&Path> {
        match &self.init {
            InitInfo::Random => None,
            InitInfo::WanPretrained(p) | InitInfo::BwmCheckpoint(p) => Some(p),
        }
    }

    /// Hub id of the base model, when the run started from published weights.
    pub fn base_model_id(&self) -> Option<String> {
        match &self.init {
            InitInfo::WanPretrained(_) => Some("Wan-AI/Wan2.2-TI2V-5B".into()),
            InitInfo::BwmCheckpoint(p) if p.to_string_lossy().contains("step-12000") => Some("BLM-Lab/Boundless-World-Model".into()),
            _ => None,
        }
    }
}

/// A training checkpoint folder's `state.json`, as far as an export uses it.
#[derive(Debug, Clone)]
pub struct CheckpointState {
    pub step: u64,
    pub optimizer_step: u64,
    pub samples_seen: u64,
    pub trainable: Vec<String>,
    pub run: RunInfo,
}

impl CheckpointState {
    pub fn read(dir: &Path) -> Result<Self> {
        let path = dir.join(crate::run_dir::STATE_FILE);
        let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
        let v: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
        let num = |k: &str| v.get(k).and_then(|x| x.as_u64()).unwrap_or(0);
        let config = v
            .get("config")
            .and_then(|c| c.as_str())
            .with_context(|| format!("{}: no \"config\" string (the run config TOML); not a BWM training checkpoint", path.display()))?;
        let trainable = v
            .get("trainable")
            .and_then(|t| t.as_array())
            .map(|a| a.iter().filter_map(|s| s.as_str().map(String::from)).collect())
            .unwrap_or_default();
        Ok(Self {
            step: num("step"),
            optimizer_step: num("optimizer_step"),
            samples_seen: num("samples_seen"),
            trainable,
            run: RunInfo::parse(config, &format!("the run config stored in {}", path.display()))?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_model_section_and_ignores_the_rest() {
        let text = r#"
[run]
name = "t"
seed = 3
[model]
preset = "tiny"
dtype = "f32"
[model.init]
from = "wan-pretrained"
path = "/w/Wan2.2-TI2V-5B/diffusion_pytorch_model.safetensors.index.json"
[data]
latent_cache = "cache"
[optim]
lr = 1e-4
[train]
steps = 10
[whatever]
x = 1
"#;
        let r = RunInfo::parse(text, "t").unwrap();
        assert_eq!(r.model, ModelConfig::preset("tiny").unwrap());
        assert_eq!(r.base_model_id().as_deref(), Some("Wan-AI/Wan2.2-TI2V-5B"));
        assert_eq!(r.steps_planned, Some(10));
        let e = RunInfo::parse("[model]\npreset = \"huge\"\n", "x").unwrap_err();
        assert!(format!("{e:#}").contains("allowed"), "{e:#}");
    }

    /// A checkpoint's stored run config from before issue 69 removed `model.action.fourier_bands`,
    /// `model.action.temporal_rope` and `objective.motion_weight` holds them at their defaults
    /// (`motion_weight = 0.0` always): it reads as before. One whose run switched one on is
    /// refused by the key's name, saying that it was removed and why, not read as another model.
    #[test]
    fn removed_keys_read_at_their_old_defaults_and_are_refused_otherwise() {
        let old = "[run]\nname = \"t\"\n[model]\npreset = \"tiny\"\n[model.action]\naction_dim = 4\nfourier_bands = 0\ntemporal_rope = false\n[objective]\nmotion_weight = 0.0\n";
        let r = RunInfo::parse(old, "t").unwrap();
        assert_eq!(r.model.action, ActionConfig { action_dim: 4, ..ActionConfig::default() });
        for (off, on, why) in [("fourier_bands = 0", "fourier_bands = 3", "run 28"), ("temporal_rope = false", "temporal_rope = true", "run 39"), ("motion_weight = 0.0", "motion_weight = 4.0", "run 33")] {
            let e = format!("{:#}", RunInfo::parse(&old.replace(off, on), "the run config stored in c").unwrap_err());
            let key = on.split(" = ").next().unwrap();
            assert!(e.contains("the run config stored in c") && e.contains(key) && e.contains("was removed") && e.contains(why), "{e}");
        }
    }
}
