//! What a reader of a checkpoint (export, open, inference) knows about the training run behind it,
//! from the run config TOML stored in the checkpoint's `state.json`. Its `[run]`, `[model]` and
//! `[objective]` sections are read through the trainer's own types (`bwm_run_config`), strictly;
//! the trainer's other sections are its business (this crate cannot depend on the trainer, which
//! depends on it): a config of any earlier trainer opens, and the values an export shows of them
//! (the model card's learning rate, batch, data) are read by name, as written.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use bwm_model::lora::LoraConfig;
use bwm_model::ModelConfig;
use bwm_run_config::{Dtype, InitSource, RunRecord};

/// What a run held out of its latent cache for validation: `data.holdout_episodes` (the
/// trainer's key), or the `data.holdout_clips` of early trainers (0 where neither is given).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeldOut {
    Episodes(usize),
    Clips(usize),
}

impl std::fmt::Display for HeldOut {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HeldOut::Episodes(n) => write!(f, "{n} episode{} held out", if *n == 1 { "" } else { "s" }),
            HeldOut::Clips(n) => write!(f, "{n} clip{} held out", if *n == 1 { "" } else { "s" }),
        }
    }
}

/// The run config, as far as a reader of its checkpoints uses it.
#[derive(Debug, Clone)]
pub struct RunInfo {
    /// `[run]`, `[model]` and `[objective]`, as the trainer reads them.
    pub record: RunRecord,
    /// The model's architecture (`[model]`'s preset or `[model.dit]`, and its action interface).
    pub model: ModelConfig,
    /// Of the trainer's own sections, what an export shows: `data.latent_cache`, and what was
    /// held out of it for validation.
    pub latent_cache: Option<PathBuf>,
    pub held_out: HeldOut,
    /// `optim.lr`, `optim.ema_decay`.
    pub lr: Option<f64>,
    pub ema_decay: Option<f64>,
    /// `train.steps`, `train.micro_batch`, `train.grad_accum`.
    pub steps_planned: Option<u64>,
    pub micro_batch: Option<usize>,
    pub grad_accum: Option<usize>,
    /// The TOML itself.
    pub toml: String,
}

impl RunInfo {
    /// Parses a run config TOML (`what` names it in errors).
    pub fn parse(text: &str, what: &str) -> Result<Self> {
        let record = RunRecord::parse(text).with_context(|| format!("{what}: not a BWM run config"))?;
        let model = record.model.model_config().with_context(|| format!("{what}: model section"))?;
        let what = || format!("{what}: not a BWM run config");
        Ok(Self {
            latent_cache: record.other("data", "latent_cache").with_context(what)?,
            held_out: match record.other("data", "holdout_episodes").with_context(what)? {
                Some(n) => HeldOut::Episodes(n),
                None => HeldOut::Clips(record.other("data", "holdout_clips").with_context(what)?.unwrap_or(0)),
            },
            lr: record.other("optim", "lr").with_context(what)?,
            ema_decay: record.other("optim", "ema_decay").with_context(what)?,
            steps_planned: record.other("train", "steps").with_context(what)?,
            micro_batch: record.other("train", "micro_batch").with_context(what)?,
            grad_accum: record.other("train", "grad_accum").with_context(what)?,
            record,
            model,
            toml: text.to_string(),
        })
    }

    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading run config {}", path.display()))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// `run.name` ("" for a config without `[run]`).
    pub fn name(&self) -> &str {
        &self.record.run.name
    }

    /// `run.seed`, which keyed the run's random draws (its random initial weights among them).
    pub fn seed(&self) -> u64 {
        self.record.run.seed
    }

    /// Where the run's initial weights came from (`model.init`).
    pub fn init(&self) -> &InitSource {
        &self.record.model.init
    }

    /// The run's LoRA adapters (`model.lora`): its checkpoints hold adapters, not whole weights.
    pub fn lora(&self) -> Option<&LoraConfig> {
        self.record.model.lora.as_ref()
    }

    /// `model.dtype`, the training dtype, where the config gives it (a config written by hand
    /// may leave it out; the trainer writes every key).
    pub fn stated_dtype(&self) -> Option<Dtype> {
        self.record.states("model", "dtype").then_some(self.record.model.dtype)
    }

    /// `model.residual` (`f32` or `model`: the DiT's residual stream in training) where the config
    /// gives it.
    pub fn stated_residual(&self) -> Option<String> {
        self.record.states("model", "residual").then(|| match self.record.model.residual {
            bwm_model::Residual::F32 => "f32".to_string(),
            bwm_model::Residual::Model => "model".to_string(),
        })
    }

    /// `objective.shift` where the config gives it (the default is Wan's 5).
    pub fn stated_shift(&self) -> Option<f64> {
        self.record.states("objective", "shift").then_some(self.record.objective.shift)
    }

    /// The base weights the run started from, when they are a file.
    pub fn init_path(&self) -> Option<&Path> {
        self.init().path()
    }

    /// Hub id of the base model, when the run started from published weights.
    pub fn base_model_id(&self) -> Option<String> {
        match self.init() {
            InitSource::WanPretrained { .. } => Some("Wan-AI/Wan2.2-TI2V-5B".into()),
            InitSource::BwmCheckpoint { path } if path.to_string_lossy().contains("step-12000") => Some("BLM-Lab/Boundless-World-Model".into()),
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
        assert_eq!(r.model.action, bwm_model::ActionConfig { action_dim: 4, ..bwm_model::ActionConfig::default() });
        for (off, on, why) in [("fourier_bands = 0", "fourier_bands = 3", "run 28"), ("temporal_rope = false", "temporal_rope = true", "run 39"), ("motion_weight = 0.0", "motion_weight = 4.0", "run 33")] {
            let e = format!("{:#}", RunInfo::parse(&old.replace(off, on), "the run config stored in c").unwrap_err());
            let key = on.split(" = ").next().unwrap();
            assert!(e.contains("the run config stored in c") && e.contains(key) && e.contains("was removed") && e.contains(why), "{e}");
        }
    }

    /// What the model card shows as held out: the trainer's `data.holdout_episodes`, or an early
    /// trainer's `data.holdout_clips` (a current run's card said "0 clips" before it read the
    /// trainer's key).
    #[test]
    fn held_out_reads_episodes_and_the_early_clips_key() {
        let base = "[run]\nname = \"t\"\n[model]\npreset = \"tiny\"\ndtype = \"f32\"\n[data]\nlatent_cache = \"c\"\n";
        for (extra, want) in [("holdout_episodes = 2\n", "2 episodes held out"), ("holdout_episodes = 1\n", "1 episode held out"), ("holdout_clips = 3\n", "3 clips held out"), ("", "0 clips held out")] {
            let r = RunInfo::parse(&format!("{base}{extra}"), "t").unwrap();
            assert_eq!(r.held_out.to_string(), want, "{extra}");
        }
    }
}
