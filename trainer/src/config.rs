//! The run configuration: one typed tree read from TOML, unknown keys rejected, `--set a.b=v`
//! overrides applied before validation. The sections every reader of a run honours (`[run]`,
//! `[model]`, `[objective]`) are `bwm_run_config`'s, shared with the checkpoints' export and open;
//! the trainer's own sections (`[data]`, `[optim]`, `[train]`, `[checkpoint]`, `[log]`,
//! `[validation]`) are defined here.

use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
pub use bwm_run_config::{Dtype, InitSource, ModelSection, ObjectiveSection, RunSection, TimestepSampling};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    pub run: RunSection,
    pub model: ModelSection,
    pub data: DataSection,
    #[serde(default)]
    pub objective: ObjectiveSection,
    pub optim: OptimSection,
    pub train: TrainSection,
    #[serde(default)]
    pub checkpoint: CheckpointSection,
    #[serde(default)]
    pub log: LogSection,
    #[serde(default)]
    pub validation: ValidationSection,
    /// Step distillation: the model trains to take in few sampler steps what a teacher takes in
    /// many (`trainer/src/distill.rs`); absent, the flow-matching objective.
    #[serde(default)]
    pub distill: Option<DistillSection>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DistillSection {
    /// The teacher's weights: a checkpoint of this trainer (or any layout `bwm convert` reads) of
    /// the run's model, frozen. The student is the run's model; `model.init = { from =
    /// "bwm-checkpoint", path = ... }` with the same weights starts it from the teacher.
    pub teacher: PathBuf,
    /// Euler steps the student samples with (its grid: that many sigmas at `objective.shift`).
    pub student_steps: usize,
    /// Teacher Euler steps per student step: the teacher samples `student_steps` x this many.
    #[serde(default = "default_teacher_substeps")]
    pub teacher_substeps: usize,
}

/// `[distill] teacher_substeps` where it is not given.
pub const DEFAULT_TEACHER_SUBSTEPS: usize = 8;

fn default_teacher_substeps() -> usize {
    DEFAULT_TEACHER_SUBSTEPS
}

impl DistillSection {
    /// Refuses a student of no steps or a teacher of no steps per student step.
    pub fn check_steps(student_steps: usize, teacher_substeps: usize) -> Result<()> {
        ensure!(student_steps >= 1 && teacher_substeps >= 1, "distill.student_steps and distill.teacher_substeps must be at least 1");
        Ok(())
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DataSection {
    /// A latent cache written by `bwm prepare` (clips of latents + normalized actions).
    pub latent_cache: PathBuf,
    /// Episodes held out for validation (the cache's last ones; `bwm prepare` writes clips episode
    /// by episode), never trained on.
    #[serde(default)]
    pub holdout_episodes: usize,
    /// The VAE that encodes raw clips (a cache written by `bwm prepare --raw`) as the trainer
    /// reads them: a `bwm train-vae` output or the published Wan2.2 VAE. Not used with a cache of
    /// latents.
    #[serde(default)]
    pub vae: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum LrSchedule {
    Constant,
    Cosine,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct OptimSection {
    /// Peak learning rate of AdamW (after warmup).
    pub lr: f64,
    /// Decoupled weight decay (AdamW).
    #[serde(default = "default_weight_decay")]
    pub weight_decay: f64,
    /// AdamW's (beta1, beta2).
    #[serde(default = "default_betas")]
    pub betas: [f64; 2],
    /// AdamW's epsilon.
    #[serde(default = "default_adam_eps")]
    pub eps: f64,
    /// Steps of linear warmup from 0 to `lr`.
    #[serde(default)]
    pub warmup_steps: u64,
    /// The learning rate after warmup: `constant`, or `cosine` decay to `min_lr_ratio x lr` at
    /// `train.steps`.
    #[serde(default = "default_schedule")]
    pub schedule: LrSchedule,
    /// Cosine floor as a fraction of `lr`.
    #[serde(default)]
    pub min_lr_ratio: f64,
    /// Global gradient-norm clip; 0 turns clipping off.
    #[serde(default = "default_grad_clip")]
    pub grad_clip: f64,
    /// EMA of the fp32 master weights, off when absent.
    #[serde(default)]
    pub ema_decay: Option<f64>,
    /// On CUDA, the update runs as one NVRTC-compiled kernel (`fused_adamw`) instead of about a
    /// dozen tensor operations; without NVRTC on the library path the tensor path runs, with a
    /// warning.
    #[serde(default = "default_fused")]
    pub fused: bool,
}

fn default_fused() -> bool {
    true
}

fn default_weight_decay() -> f64 {
    0.01
}
fn default_betas() -> [f64; 2] {
    [0.9, 0.999]
}
fn default_adam_eps() -> f64 {
    1e-8
}
fn default_schedule() -> LrSchedule {
    LrSchedule::Constant
}
fn default_grad_clip() -> f64 {
    1.0
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TrainSection {
    /// Optimizer steps of the run (a resumed run continues to this count).
    pub steps: u64,
    /// Clips per micro-step on each rank.
    #[serde(default = "one")]
    pub micro_batch: usize,
    /// Micro-steps accumulated into each optimizer step: the global batch is `micro_batch x
    /// grad_accum x ranks` clips.
    #[serde(default = "one")]
    pub grad_accum: usize,
    /// Recompute each DiT block in backward instead of keeping its activations.
    #[serde(default = "yes")]
    pub recompute: bool,
    /// With recomputation, the last N DiT blocks keep their activations from the forward instead
    /// of being recomputed in backward: faster by their recompute forward, at the memory of their
    /// activations (`docs/performance.md`, "MFU and memory", lists what fits).
    #[serde(default)]
    pub recompute_keep_last: usize,
    /// With several data-parallel ranks, each keeps 1/world of the optimizer state (fp32 master
    /// and moments; ZeRO-1) instead of all of it.
    #[serde(default = "yes")]
    pub shard_optimizer: bool,
    /// With several ranks and recomputation, each DiT block's gradients are reduced as soon as
    /// the backward walk of the step's last micro-batch has passed the block, overlapping the
    /// communication with the rest of the walk; otherwise all are reduced after it.
    #[serde(default = "yes")]
    pub overlap_grad_reduce: bool,
    /// Parameter-name patterns (`*` matches anything) of the trained set. The default, `["*"]`,
    /// means every parameter, or with `[model.lora]` every adapter (`*.lora_A.weight`,
    /// `*.lora_B.weight`).
    #[serde(default = "default_trainable")]
    pub trainable: Vec<String>,
    /// Parameter-name patterns kept frozen even when `trainable` matches them (the text
    /// embedding, unused when actions replace the text).
    #[serde(default = "default_frozen")]
    pub frozen: Vec<String>,
    /// Non-finite losses or gradients skip the update; this many in a row abort the run.
    #[serde(default = "default_max_nonfinite")]
    pub max_nonfinite_in_row: u32,
    /// The DiT blocks' linear layers run their forward and backward products in FP8 (per-tensor
    /// dynamic scales, e4m3 forward, e5m2 gradients, as torchao's float8 training recipe); the
    /// weights, fp32 masters, optimizer and norms stay as they are. Needs FP8 matmuls on the device
    /// (Hopper or newer on CUDA; any CPU) and no LoRA.
    #[serde(default)]
    pub fp8: bool,
    /// With `fp8`, products of fewer rows (tokens times batch) than this stay in the parameters'
    /// dtype: scaling the weight to float8 costs about what FP8 saves on about a thousand rows (the
    /// 5B's cross-attention k and v read its 81 condition tokens). 0: every product in FP8.
    #[serde(default = "default_fp8_min_rows")]
    pub fp8_min_rows: usize,
    /// Record the step's forward and backward pass once as a CUDA graph and replay it (after two
    /// eager warm-up steps): a small model's step is bound by launching its kernels, a replay is
    /// one launch. One CUDA process, `grad_accum = 1`, `recompute = false`, no LoRA and no FP8.
    #[serde(default)]
    pub cuda_graph: bool,
}

fn one() -> usize {
    1
}
fn yes() -> bool {
    true
}
fn default_trainable() -> Vec<String> {
    vec!["*".into()]
}
fn default_frozen() -> Vec<String> {
    vec!["text_embedding.*".into()]
}
fn default_fp8_min_rows() -> usize {
    1024
}

fn default_max_nonfinite() -> u32 {
    5
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct CheckpointSection {
    /// Save every N optimizer steps (and always at the end); 0 = only at the end.
    #[serde(default)]
    pub every: u64,
    /// Checkpoints kept: older ones are deleted once a newer one is complete.
    #[serde(default = "default_keep_last")]
    pub keep_last: usize,
}

fn default_keep_last() -> usize {
    3
}

impl Default for CheckpointSection {
    fn default() -> Self {
        Self { every: 0, keep_last: default_keep_last() }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LogSection {
    /// A summary line on stdout (and TensorBoard points) every N steps.
    #[serde(default = "one_u64")]
    pub every: u64,
    /// Write TensorBoard event files under the run's `tensorboard/` folder.
    #[serde(default = "yes")]
    pub tensorboard: bool,
    /// Show a progress bar on stderr (off when stderr is not a terminal).
    #[serde(default = "yes")]
    pub progress: bool,
    /// Peak dense throughput of one device in TFLOP/s for MFU (H200/H100 bf16: 989).
    #[serde(default)]
    pub peak_tflops: Option<f64>,
    /// Dense bf16 matmul rate measured on one device in TFLOP/s (H200: 788), reported beside MFU.
    #[serde(default)]
    pub matmul_tflops: Option<f64>,
}

fn one_u64() -> u64 {
    1
}

impl Default for LogSection {
    fn default() -> Self {
        Self { every: 1, tensorboard: true, progress: true, peak_tflops: None, matmul_tflops: None }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ValidationSection {
    /// Roll out held-out clips every N steps (0 = off).
    #[serde(default)]
    pub every: u64,
    /// Sampler steps of the validation rollout.
    #[serde(default = "default_sample_steps")]
    pub sample_steps: usize,
    /// How the validation sampler steps: "euler" or "dpm++2m".
    #[serde(default)]
    pub solver: bwm_model::schedule::Solver,
    /// Classifier-free guidance by the actions in the validation rollout (1 = off; other values
    /// need a model trained with `objective.action_dropout`).
    #[serde(default = "default_guidance")]
    pub guidance: f64,
    /// VAE to decode rollouts into pixels for PSNR/SSIM and the frame strip: a `bwm train-vae`
    /// output or the published Wan2.2 VAE (`.pth` or safetensors).
    #[serde(default)]
    pub vae: Option<PathBuf>,
}

fn default_sample_steps() -> usize {
    10
}
fn default_guidance() -> f64 {
    1.0
}

impl Default for ValidationSection {
    fn default() -> Self {
        Self { every: 0, sample_steps: default_sample_steps(), solver: Default::default(), guidance: default_guidance(), vae: None }
    }
}

impl RunConfig {
    /// Reads a TOML file and applies `key.path=value` overrides (values parsed as TOML, else as
    /// strings).
    pub fn load(path: &Path, overrides: &[String]) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading config {}", path.display()))?;
        Self::parse(&text, overrides).with_context(|| format!("config {}", path.display()))
    }

    pub fn parse(text: &str, overrides: &[String]) -> Result<Self> {
        // Without overrides the user's own text is parsed, so error positions point into their file.
        let rendered;
        let source = if overrides.is_empty() {
            text
        } else {
            let mut value: toml::Value = toml::from_str(text)?;
            for o in overrides {
                apply_override(&mut value, o)?;
            }
            rendered = toml::to_string(&value)?;
            &rendered
        };
        let cfg: RunConfig = toml::from_str(source).map_err(|e| anyhow::anyhow!("{}", e.to_string().trim()))?;
        cfg.validate()?;
        Ok(cfg)
    }

    pub fn validate(&self) -> Result<()> {
        self.model.model_config()?;
        if let Some(lora) = &self.model.lora {
            lora.validate()?;
            // Recomputation runs each block's forward twice; the second pass would draw other
            // dropout masks than the first.
            ensure!(
                lora.dropout == 0.0 || !self.train.recompute,
                "model.lora.dropout = {} with train.recompute = true: recomputation would draw different dropout masks; turn one of them off",
                lora.dropout
            );
        }
        ensure!(self.train.steps > 0, "train.steps must be at least 1");
        ensure!(self.train.micro_batch > 0, "train.micro_batch must be at least 1");
        ensure!(self.train.grad_accum > 0, "train.grad_accum must be at least 1");
        ensure!(self.optim.lr > 0.0 && self.optim.lr.is_finite(), "optim.lr must be positive, got {}", self.optim.lr);
        ensure!(self.optim.weight_decay >= 0.0, "optim.weight_decay must be >= 0");
        ensure!(
            self.optim.betas.iter().all(|b| (0.0..1.0).contains(b)),
            "optim.betas must lie in [0, 1), got {:?}",
            self.optim.betas
        );
        ensure!(self.optim.grad_clip >= 0.0, "optim.grad_clip must be >= 0 (0 = off)");
        ensure!((0.0..=1.0).contains(&self.optim.min_lr_ratio), "optim.min_lr_ratio must lie in [0, 1]");
        if let Some(d) = self.optim.ema_decay {
            ensure!((0.0..1.0).contains(&d), "optim.ema_decay must lie in [0, 1), got {d}");
        }
        self.objective.validate()?;
        bwm_model::sampler::validate_guidance(self.validation.guidance).context("validation.guidance")?;
        if let Some(d) = &self.distill {
            DistillSection::check_steps(d.student_steps, d.teacher_substeps)?;
            ensure!(
                self.objective.action_dropout == 0.0,
                "distill with objective.action_dropout = {}: the teacher's steps are conditioned on the actions, so a student without them would learn another target; set it to 0",
                self.objective.action_dropout
            );
        }
        ensure!(self.checkpoint.keep_last >= 1, "checkpoint.keep_last must be at least 1");
        ensure!(self.log.every >= 1, "log.every must be at least 1");
        self.run.validate()?;
        Ok(())
    }

    pub fn out_dir(&self) -> PathBuf {
        self.run.out_dir.clone().unwrap_or_else(|| PathBuf::from("runs").join(&self.run.name))
    }

    /// The trained set's patterns: `train.trainable`, where a LoRA run's default means the adapters.
    pub fn trainable_patterns(&self) -> Vec<String> {
        if self.model.lora.is_some() && self.train.trainable == default_trainable() {
            bwm_model::lora::ADAPTER_PATTERNS.iter().map(|p| p.to_string()).collect()
        } else {
            self.train.trainable.clone()
        }
    }

    /// Samples per optimizer step on one rank.
    pub fn samples_per_step(&self) -> usize {
        self.train.micro_batch * self.train.grad_accum
    }

    pub fn to_toml(&self) -> Result<String> {
        Ok(toml::to_string_pretty(self)?)
    }
}

fn apply_override(root: &mut toml::Value, spec: &str) -> Result<()> {
    let Some((key, raw)) = spec.split_once('=') else {
        bail!("--set expects key.path=value, got '{spec}'");
    };
    let key = key.trim();
    let value: toml::Value = toml::from_str::<toml::Table>(&format!("v = {raw}"))
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(raw.to_string()));
    let parts: Vec<&str> = key.split('.').collect();
    ensure!(parts.iter().all(|p| !p.is_empty()), "--set key '{key}' has an empty part");
    let mut node = root;
    for part in &parts[..parts.len() - 1] {
        let table = node.as_table_mut().with_context(|| format!("--set {key}: '{part}' is not inside a table"))?;
        node = table.entry(part.to_string()).or_insert_with(|| toml::Value::Table(toml::Table::new()));
    }
    let table = node.as_table_mut().with_context(|| format!("--set {key}: parent is not a table"))?;
    table.insert(parts[parts.len() - 1].to_string(), value);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `objective.motion_weight` was removed after measurements rejected it (issue 69): a config
    /// written before, which holds it at its old default 0 (in the file, as a checkpoint stores
    /// its run's config, or as an override), loads as one without it; any other value is refused
    /// by the key's name, saying that it was removed and why. Unknown keys are still refused.
    #[test]
    fn the_removed_motion_weight_loads_at_its_old_default_and_is_refused_otherwise() {
        let tiny = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/tiny.toml")).unwrap();
        let plain = RunConfig::parse(&tiny, &[]).unwrap();
        for off in ["0.0", "0"] {
            assert_eq!(RunConfig::parse(&format!("{tiny}\n[objective]\nmotion_weight = {off}\n"), &[]).unwrap(), plain);
            assert_eq!(RunConfig::parse(&tiny, &[format!("objective.motion_weight={off}")]).unwrap(), plain);
        }
        assert!(!plain.to_toml().unwrap().contains("motion"), "nothing removed is written");
        for e in [RunConfig::parse(&format!("{tiny}\n[objective]\nmotion_weight = 4.0\n"), &[]), RunConfig::parse(&tiny, &["objective.motion_weight=4.0".into()])] {
            let e = format!("{:#}", e.unwrap_err());
            assert!(e.contains("objective.motion_weight = 4") && e.contains("was removed") && e.contains("run 33") && e.contains("docs/fidelity.md"), "{e}");
        }
        let e = format!("{:#}", RunConfig::parse(&tiny, &["objective.motion_weigth=0.0".into()]).unwrap_err());
        assert!(e.contains("unknown field"), "{e}");
    }
}
