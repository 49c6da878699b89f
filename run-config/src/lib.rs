//! The sections of a run config that everything reading a run honours, defined once: `[run]`
//! (its name and the seed that keys every random draw), `[model]` (the architecture, its dtype,
//! residual stream, initial weights and LoRA adapters) and `[objective]` (the flow-matching
//! objective the weights were trained with, which sampling should match). Each section refuses
//! unknown keys, and keys removed after measurements (`bwm_model::config::removed`) load at their
//! old defaults only.
//!
//! The trainer's `RunConfig` embeds these sections beside its own (`[data]`, `[optim]`, `[train]`,
//! ...) and validates the whole file. A reader of a checkpoint's stored config (export, open,
//! inference) takes these sections out of the file with [`RunRecord`], leaving the trainer's own
//! sections to the trainer, so that a config written by any earlier trainer still opens.
//!
//! A crate of its own below both `bwm-checkpoints` and `bwm-trainer`: checkpoints cannot depend
//! on the trainer (which depends on them), and the model crate knows nothing of runs.

use std::path::PathBuf;

use anyhow::{anyhow, ensure, Context, Result};
use bwm_model::config::{removed, Removed};
use bwm_model::lora::LoraConfig;
use bwm_model::{ActionConfig, DitConfig, ModelConfig, Residual};
use serde::{Deserialize, Serialize};

/// `[run]`: what the run is called, where it writes, and what keys its random draws.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RunSection {
    /// The run's name: its default output folder (`runs/<name>`) and the name in its logs and
    /// exported model card.
    pub name: String,
    /// Checkpoints, TensorBoard events and metrics go here (default `runs/<name>`).
    #[serde(default)]
    pub out_dir: Option<PathBuf>,
    /// Keys every random draw: (seed, global sample index, purpose).
    #[serde(default)]
    pub seed: u64,
    /// `auto` (CUDA when available), `cpu`, `cuda` or `cuda:N`.
    #[serde(default = "default_device")]
    pub device: String,
}

fn default_device() -> String {
    "auto".into()
}

impl RunSection {
    /// A run config without `[run]` (written by hand for an export): no name, seed 0.
    pub fn unnamed() -> Self {
        Self { name: String::new(), out_dir: None, seed: 0, device: default_device() }
    }

    pub fn validate(&self) -> Result<()> {
        bwm_model::device::device_syntax(&self.device).context("run.device")?;
        Ok(())
    }
}

/// `model.dtype`: the dtype the weights train (and are stored) in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Dtype {
    F32,
    Bf16,
}

impl Dtype {
    pub fn kind(self) -> tch::Kind {
        match self {
            Dtype::F32 => tch::Kind::Float,
            Dtype::Bf16 => tch::Kind::BFloat16,
        }
    }

    /// The name a config writes (`f32`, `bf16`).
    pub fn name(self) -> &'static str {
        match self {
            Dtype::F32 => "f32",
            Dtype::Bf16 => "bf16",
        }
    }
}

/// Where the initial weights come from (`model.init`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, tag = "from")]
pub enum InitSource {
    /// Random weights of the preset's shapes (tests, benchmarks).
    Random,
    /// Official Wan2.2-TI2V-5B DiT weights (Wan-native or diffusers names; a file, shard index,
    /// folder or Hub repo id); the action encoder starts fresh with zero output layers.
    WanPretrained { path: PathBuf },
    /// A BWM checkpoint in any layout (the public `step-12000.safetensors`, a diffusers or Wan
    /// export of this trainer; a file, folder or Hub repo id).
    BwmCheckpoint { path: PathBuf },
}

impl InitSource {
    /// The base weights' path, when they are a file (not random).
    pub fn path(&self) -> Option<&std::path::Path> {
        match self {
            InitSource::Random => None,
            InitSource::WanPretrained { path } | InitSource::BwmCheckpoint { path } => Some(path),
        }
    }
}

/// `[model]`: the architecture (a preset, optionally overridden), the action interface, the
/// weights' dtype, the initial weights and LoRA adapters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ModelSection {
    /// `wan22_ti2v_5b` or `tiny`.
    pub preset: String,
    /// Overrides of the preset's DiT fields (a custom width for experiments).
    #[serde(default)]
    pub dit: Option<DitConfig>,
    #[serde(default)]
    pub action: ActionConfig,
    pub dtype: Dtype,
    /// dtype of the DiT's residual stream, its norms, modulation and gates.
    #[serde(default)]
    pub residual: Residual,
    #[serde(default = "default_init")]
    pub init: InitSource,
    /// LoRA adapters on the linear layers it targets; the base stays frozen in `dtype` and, with
    /// `train.trainable` left at its default, only the adapters train.
    #[serde(default)]
    pub lora: Option<LoraConfig>,
}

fn default_init() -> InitSource {
    InitSource::Random
}

impl ModelSection {
    /// The model's architecture: the preset, or `[model.dit]` where given, and the action
    /// interface; validated.
    pub fn model_config(&self) -> Result<ModelConfig> {
        let dit = match &self.dit {
            Some(d) => d.clone(),
            None => DitConfig::preset(&self.preset).context("model.preset")?,
        };
        let cfg = ModelConfig { dit, action: self.action.clone() };
        cfg.validate()?;
        Ok(cfg)
    }
}

/// How the training timestep of a sample is drawn (`objective.timestep_sampling`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, tag = "kind")]
pub enum TimestepSampling {
    /// Uniform over the 1000-step shifted grid (DiffSynth-Studio / the BWM release).
    Uniform,
    /// sigma = sigmoid(N(mean, std)), snapped to the nearest grid point (SD3-style).
    LogitNormal { mean: f64, std: f64 },
}

/// `[objective]`: the BWM flow-matching loss.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ObjectiveSection {
    #[serde(default = "default_sampling")]
    pub timestep_sampling: TimestepSampling,
    /// Flow-matching shift (Wan: 5).
    #[serde(default = "default_shift")]
    pub shift: f64,
    /// History-noise level; default: the training grid's sigma 50 steps from clean (0.2083), as the
    /// BWM release computes it.
    #[serde(default)]
    pub history_sigma: Option<f64>,
    /// Condition latents (x0 + history): 1 + H/4; the loss covers the latents after them.
    #[serde(default = "default_condition_latents")]
    pub condition_latents: i64,
    /// Share of samples trained with the null action condition (no action tokens, no per-frame
    /// action term), so that sampling can guide by actions (`--guidance`, classifier-free
    /// guidance); 0: every sample sees its actions (the BWM release).
    #[serde(default)]
    pub action_dropout: f64,
    /// Removed: the loss weighted towards what moves (`removed::MOTION_WEIGHT`).
    #[serde(default, skip_serializing, deserialize_with = "removed::motion_weight")]
    #[schemars(skip)]
    pub motion_weight: Removed,
}

fn default_sampling() -> TimestepSampling {
    TimestepSampling::Uniform
}
fn default_shift() -> f64 {
    bwm_model::schedule::DEFAULT_SHIFT
}
fn default_condition_latents() -> i64 {
    3
}

impl Default for ObjectiveSection {
    fn default() -> Self {
        Self {
            timestep_sampling: default_sampling(),
            shift: default_shift(),
            history_sigma: None,
            condition_latents: default_condition_latents(),
            action_dropout: 0.0,
            motion_weight: Removed,
        }
    }
}

impl ObjectiveSection {
    pub fn validate(&self) -> Result<()> {
        ensure!(self.condition_latents >= 1, "objective.condition_latents must be at least 1 (x0)");
        if let Some(s) = self.history_sigma {
            ensure!((0.0..=1.0).contains(&s), "objective.history_sigma must lie in [0, 1], got {s}");
        }
        ensure!((0.0..1.0).contains(&self.action_dropout), "objective.action_dropout must lie in [0, 1), got {}", self.action_dropout);
        if let TimestepSampling::LogitNormal { std, .. } = self.timestep_sampling {
            ensure!(std > 0.0, "objective.timestep_sampling.std must be positive");
        }
        Ok(())
    }
}

/// The shared sections of a whole run config, read tolerantly of the others: the sections every
/// reader honours, strict; the rest of the file (the trainer's sections) as written.
#[derive(Debug, Clone)]
pub struct RunRecord {
    /// `[run]`, or [`RunSection::unnamed`] where the file has none.
    pub run: RunSection,
    pub model: ModelSection,
    pub objective: ObjectiveSection,
    /// The whole file: what it states (`states`) and the trainer's own sections, which a reader
    /// of a run may show but does not interpret.
    pub table: toml::Table,
}

/// The part of a run config [`RunRecord`] deserializes; other top-level sections are skipped.
#[derive(Deserialize)]
struct SharedSections {
    #[serde(default)]
    run: Option<RunSection>,
    model: ModelSection,
    #[serde(default)]
    objective: ObjectiveSection,
}

impl RunRecord {
    /// Reads the shared sections out of a run config's text. A config written by hand for an
    /// export may leave out `model.dtype` (the trainer writes every key): it reads as `f32`, and
    /// [`RunRecord::states`] tells that it was not given.
    pub fn parse(text: &str) -> Result<Self> {
        let table: toml::Table = toml::from_str(text).map_err(|e| anyhow!("{}", e.to_string().trim()))?;
        let mut shared = table.clone();
        let model = shared.get_mut("model").context("no [model] section")?;
        let model = model.as_table_mut().context("model: expected a table ([model])")?;
        model.entry("dtype").or_insert_with(|| toml::Value::String(Dtype::F32.name().into()));
        let sections = SharedSections::deserialize(toml::Value::Table(shared)).map_err(|e| anyhow!("{}", e.to_string().trim()))?;
        Ok(Self { run: sections.run.unwrap_or_else(RunSection::unnamed), model: sections.model, objective: sections.objective, table })
    }

    /// Whether the file itself gives `section.key` (rather than leaving it to its default).
    pub fn states(&self, section: &str, key: &str) -> bool {
        self.table.get(section).and_then(|s| s.get(key)).is_some()
    }

    /// `section.key` of a section this crate does not define (the trainer's), as written; None
    /// where the file leaves it out, an error where it holds another type than `T`.
    pub fn other<T: serde::de::DeserializeOwned>(&self, section: &str, key: &str) -> Result<Option<T>> {
        match self.table.get(section).and_then(|s| s.get(key)) {
            None => Ok(None),
            Some(v) => v.clone().try_into().map(Some).map_err(|e| anyhow!("{section}.{key}: {}", e.to_string().trim())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shared_sections_are_strict_and_the_others_are_left_to_their_owner() {
        let text = "[run]\nname = \"t\"\nseed = 3\n[model]\npreset = \"tiny\"\n[data]\nholdout_clips = 1\n[whatever]\nx = 1\n";
        let r = RunRecord::parse(text).unwrap();
        assert_eq!((r.run.name.as_str(), r.run.seed), ("t", 3));
        assert_eq!(r.model.dtype, Dtype::F32);
        assert!(!r.states("model", "dtype") && r.states("model", "preset"));
        assert_eq!(r.other::<u64>("data", "holdout_clips").unwrap(), Some(1));
        assert_eq!(r.other::<u64>("train", "steps").unwrap(), None);
        assert!(format!("{:#}", r.other::<String>("data", "holdout_clips").unwrap_err()).contains("data.holdout_clips"));
        assert_eq!(r.objective, ObjectiveSection::default());
        for bad in ["[model]\npreset = \"tiny\"\nbogus = 1\n", "[model]\npreset = \"tiny\"\n[objective]\nshfit = 2.0\n", "[run]\nname = \"t\"\nsede = 1\n[model]\npreset = \"tiny\"\n"] {
            let e = format!("{:#}", RunRecord::parse(bad).unwrap_err());
            assert!(e.contains("unknown field"), "{e}");
        }
        assert!(format!("{:#}", RunRecord::parse("[run]\nname = \"t\"\n").unwrap_err()).contains("[model]"));
    }
}
