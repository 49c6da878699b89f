//! Export of a training checkpoint (or any weights file) into a Hugging Face model repository
//! folder: `config.json`, sharded safetensors with an index, the action encoder, `action_stats.json`
//! and a `README.md` model card, in the wan, diffusers or bwm-release layout (see `repo`).
//!
//! A training checkpoint holds only the *trainable* tensors. `text_embedding.*` (frozen and unused
//! when actions replace text) is left out and declared in `config.json` (`weights.missing_keys`);
//! any other tensor the checkpoint lacks (a run that froze more) is taken from the base weights the
//! run started from (`model.init` of its config, or `--base`), and an export without them fails.
//!
//! The folder appears atomically: everything is written under `.<name>.tmp-<pid>` beside the
//! destination, fsynced, then renamed; an interrupted export leaves only that hidden temporary
//! folder (which `open_any` refuses and the next export removes).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use bwm_model::weights::{SafetensorsSource, WeightSource};
use bwm_model::ModelConfig;
use tch::{Device, Kind};

use crate::keymap::{self, DitLayout, ACTION_PREFIX, TEXT_EMBEDDING_PREFIX};
use crate::open::{check_fits, model_keys, open_any};
use crate::repo::{
    self, human_bytes, Planned, RepoConfig, WeightsInfo, WrittenFile, ACTION_ENCODER_DIR, ACTION_STATS_FILE, CONFIG_FILE,
    DIFFUSERS_BASE, MODEL_BASE, README_FILE, TRANSFORMER_DIR,
};
use crate::run_info::{CheckpointState, RunInfo};
use crate::sources::UnionSource;

/// Stored dtype of an export.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExportDtype {
    Bf16,
    F32,
}

impl ExportDtype {
    pub fn kind(self) -> Kind {
        match self {
            ExportDtype::Bf16 => Kind::BFloat16,
            ExportDtype::F32 => Kind::Float,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            ExportDtype::Bf16 => "bfloat16",
            ExportDtype::F32 => "float32",
        }
    }
}

impl std::str::FromStr for ExportDtype {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "bf16" | "bfloat16" => ExportDtype::Bf16,
            "fp32" | "f32" | "float32" => ExportDtype::F32,
            other => bail!("unknown dtype '{other}' (allowed: bf16, fp32)"),
        })
    }
}

pub const DEFAULT_SHARD_SIZE: u64 = 5_000_000_000;

#[derive(Debug, Clone)]
pub struct ExportOptions {
    pub layout: DitLayout,
    pub dtype: ExportDtype,
    /// The EMA weights (`ema.<name>` of the checkpoint's `optimizer.safetensors`).
    pub ema: bool,
    /// A LoRA run's checkpoint: write its adapters merged into the base weights (`base`, else the
    /// run's `model.init`), full weights in the chosen layout.
    pub merge_lora: bool,
    /// Largest shard in bytes (default 5 GB).
    pub shard_size: u64,
    /// Replace a non-empty output folder.
    pub overwrite: bool,
    /// The dataset's `stat.json`; the group used for normalization is copied into `action_stats.json`.
    pub action_stats: Option<PathBuf>,
    /// Group of `action_stats` (default `state_pose`, BWM's `eef_abs`).
    pub action_stats_group: Option<String>,
    /// Base weights (path or Hub repo id) for tensors the checkpoint lacks; default: the run's
    /// `model.init` path.
    pub base: Option<String>,
    /// A run config TOML: required for a bare weights file that carries no config; for a checkpoint
    /// it must match the config stored in it.
    pub config: Option<PathBuf>,
    /// A model preset instead of `config` (bare weights files).
    pub preset: Option<String>,
    /// The run's `metrics.jsonl` (default: `<run>/metrics.jsonl` beside `<run>/checkpoints/`).
    pub metrics: Option<PathBuf>,
    /// The repo id named in the model card (also the `--push` target).
    pub repo_id: Option<String>,
    /// Hub id of the base model for the card (default from the run's `model.init`).
    pub base_model_id: Option<String>,
    /// Tests: stop after writing this many shards (an interrupted export).
    #[doc(hidden)]
    pub fail_after_shards: Option<usize>,
}

impl Default for ExportOptions {
    fn default() -> Self {
        Self {
            layout: DitLayout::WanNative,
            dtype: ExportDtype::Bf16,
            ema: false,
            merge_lora: false,
            shard_size: DEFAULT_SHARD_SIZE,
            overwrite: false,
            action_stats: None,
            action_stats_group: None,
            base: None,
            config: None,
            preset: None,
            metrics: None,
            repo_id: None,
            base_model_id: None,
            fail_after_shards: None,
        }
    }
}

#[derive(Debug, Clone)]
pub struct ExportReport {
    pub out: PathBuf,
    pub layout: DitLayout,
    pub files: Vec<WrittenFile>,
    pub tensors: usize,
    pub parameters: i64,
    pub declared_missing: Vec<String>,
    /// Tensors taken from the base weights (frozen tensors the checkpoint lacks).
    pub from_base: usize,
}

/// Weights ready to write: Wan-native names, a model config, and what is known about the run.
pub struct Prepared {
    pub source: Box<dyn WeightSource>,
    pub cfg: ModelConfig,
    /// (Wan-native name, shape) to write, in module order.
    pub names: Vec<(String, Vec<i64>)>,
    pub declared_missing: Vec<String>,
    pub from_base: usize,
    pub state: Option<CheckpointState>,
    pub run: Option<RunInfo>,
    pub input: PathBuf,
    pub ema: bool,
}


fn config_from_options(opts: &ExportOptions) -> Result<(Option<ModelConfig>, Option<RunInfo>)> {
    match (&opts.config, &opts.preset) {
        (Some(_), Some(_)) => bail!("give either a run config or a preset, not both"),
        (Some(path), None) => {
            let run = RunInfo::load(path)?;
            Ok((Some(run.model.clone()), Some(run)))
        }
        (None, Some(p)) => Ok((Some(ModelConfig::preset(p)?), None)),
        (None, None) => Ok((None, None)),
    }
}

/// Reads the input of an export: a training checkpoint folder, or weights in any layout.
pub fn prepare(input: &str, opts: &ExportOptions) -> Result<Prepared> {
    let (given_cfg, given_run) = config_from_options(opts)?;
    let path = Path::new(input);
    let base_dir_name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
    if path.is_dir() && base_dir_name.starts_with(".step-") && base_dir_name.contains(".tmp-") {
        bail!("{input}: the temporary folder of an interrupted checkpoint save, not a checkpoint");
    }
    let (primary, cfg, state, run): (Box<dyn WeightSource>, ModelConfig, Option<CheckpointState>, Option<RunInfo>) =
        if crate::run_dir::is_training_checkpoint(path) {
            let state = CheckpointState::read(path)?;
            let stored = state.run.model.clone();
            if let Some(given) = &given_cfg {
                ensure!(
                    *given == stored,
                    "{input} is a checkpoint of another model config: it was trained with {stored:?}, the given {} describes {given:?}",
                    opts.config.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| format!("preset {}", opts.preset.clone().unwrap_or_default()))
                );
            }
            let model_file = path.join("model.safetensors");
            ensure!(model_file.is_file(), "{input}: no model.safetensors; not a complete training checkpoint");
            let source: Box<dyn WeightSource> = if opts.ema {
                Box::new(ema_weights(path, &model_file).with_context(|| format!("{input}: --ema"))?)
            } else {
                Box::new(SafetensorsSource::open(&model_file)?)
            };
            let source = match (state.run.lora(), opts.merge_lora) {
                (Some(_), true) => crate::open::merge_lora_checkpoint(source, &state.run, opts.base.as_deref(), input)?,
                (Some(_), false) => bail!(
                    "{input} is a LoRA checkpoint (model.lora): export_lora_adapters writes its adapters (`bwm export` does so by itself), --merge-lora the merged full weights"
                ),
                (None, true) => bail!("--merge-lora: {input} is not a LoRA checkpoint (its run config has no model.lora)"),
                (None, false) => source,
            };
            let run = state.run.clone();
            (source, stored, Some(state), Some(run))
        } else {
            ensure!(!opts.ema, "--ema needs a training checkpoint folder (its optimizer.safetensors holds the EMA weights); {input} is not one");
            let opened = open_any(input)?;
            let cfg = match (&given_cfg, &opened.config) {
                (Some(given), Some(stored)) if opened.repo_config.is_some() => {
                    ensure!(given == stored, "{input} was exported for model config {stored:?}, not the given {given:?}");
                    given.clone()
                }
                (Some(given), _) => given.clone(),
                (None, Some(stored)) => stored.clone(),
                (None, None) => bail!("{input} carries no model config; pass the run config (--config) or a preset (--preset)"),
            };
            (opened.into_source(), cfg, None, given_run)
        };
    check_fits(primary.as_ref(), &cfg, input)?;

    let keys = model_keys(&cfg)?;
    let have: BTreeSet<String> = primary.names().into_iter().collect();
    let lacking: Vec<&(String, Vec<i64>)> = keys.iter().filter(|(n, _)| !have.contains(n) && !n.starts_with(TEXT_EMBEDDING_PREFIX)).collect();
    let mut declared_missing: Vec<String> =
        keys.iter().filter(|(n, _)| !have.contains(n) && n.starts_with(TEXT_EMBEDDING_PREFIX)).map(|(n, _)| n.clone()).collect();
    let mut from_base = 0;
    let source: Box<dyn WeightSource> = if lacking.is_empty() {
        primary
    } else {
        let base_spec = opts.base.clone().or_else(|| run.as_ref().and_then(|r| r.init_path()).map(|p| p.display().to_string()));
        let Some(base_spec) = base_spec else {
            bail!(
                "{input} lacks {} tensors of the model besides text_embedding (e.g. '{}'): frozen in training and not saved, and the run started from random weights, so they cannot be recovered; pass --base with the weights the run started from",
                lacking.len(),
                lacking[0].0
            );
        };
        let base = open_any(&base_spec).with_context(|| format!("base weights for the {} tensors {input} lacks", lacking.len()))?;
        let base_src = base.into_source();
        check_fits(base_src.as_ref(), &cfg, &base_spec)?;
        let base_names: BTreeSet<String> = base_src.names().into_iter().collect();
        if let Some((n, _)) = lacking.iter().find(|(n, _)| !base_names.contains(n)) {
            bail!("{input} lacks '{n}' and the base weights {base_spec} lack it too");
        }
        from_base = lacking.len();
        Box::new(UnionSource::overlay(primary, base_src))
    };
    let available: BTreeSet<String> = source.names().into_iter().collect();
    let names: Vec<(String, Vec<i64>)> = keys
        .iter()
        .filter(|(n, _)| have.contains(n) || (available.contains(n) && !n.starts_with(TEXT_EMBEDDING_PREFIX)))
        .cloned()
        .collect();
    declared_missing.sort();
    declared_missing.dedup();
    Ok(Prepared { source, cfg, names, declared_missing, from_base, state, run, input: path.to_path_buf(), ema: opts.ema })
}

/// Removes `.{name}.tmp-<pid>` folders beside `out` whose writer process is gone.
fn remove_stale_temporaries(parent: &Path, name: &str) {
    let prefix = format!(".{name}.tmp-");
    let Ok(entries) = std::fs::read_dir(parent) else { return };
    for e in entries.flatten() {
        let n = e.file_name().to_string_lossy().to_string();
        if let Some(pid) = n.strip_prefix(&prefix) {
            let alive = pid.parse::<u32>().is_ok_and(|p| p == std::process::id() || Path::new(&format!("/proc/{p}")).exists());
            if !alive {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
}

fn sync_tree(dir: &Path) -> Result<()> {
    for e in std::fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))? {
        let p = e?.path();
        if p.is_dir() {
            sync_tree(&p)?;
        } else {
            std::fs::File::open(&p).and_then(|f| f.sync_all()).with_context(|| format!("syncing {}", p.display()))?;
        }
    }
    std::fs::File::open(dir).and_then(|f| f.sync_all()).with_context(|| format!("syncing {}", dir.display()))
}

/// Fills a fresh temporary folder beside `out` with `fill`, fsyncs it and renames it to `out`.
/// `out` may not exist as a non-empty folder unless `overwrite`; on failure nothing is left.
pub fn write_dir_atomically<T>(out: &Path, overwrite: bool, fill: impl FnOnce(&Path) -> Result<T>) -> Result<T> {
    let name = out
        .file_name()
        .and_then(|n| n.to_str())
        .with_context(|| format!("{}: the output must name a folder", out.display()))?
        .to_string();
    if out.exists() {
        ensure!(out.is_dir(), "{} exists and is not a folder", out.display());
        let empty = std::fs::read_dir(out).with_context(|| format!("listing {}", out.display()))?.next().is_none();
        ensure!(empty || overwrite, "{} exists and is not empty; pass --overwrite to replace it", out.display());
    }
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).with_context(|| format!("creating {}", parent.display()))?;
    remove_stale_temporaries(&parent, &name);
    let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).with_context(|| format!("removing {}", tmp.display()))?;
    }
    std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    let result = fill(&tmp).and_then(|v| sync_tree(&tmp).map(|_| v));
    let value = match result {
        Ok(v) => v,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
    };
    if out.exists() {
        let old = parent.join(format!(".{name}.old-{}", std::process::id()));
        std::fs::rename(out, &old).with_context(|| format!("moving the old {} aside", out.display()))?;
        if let Err(e) = std::fs::rename(&tmp, out) {
            let _ = std::fs::rename(&old, out);
            return Err(e).with_context(|| format!("renaming {} to {}", tmp.display(), out.display()));
        }
        std::fs::remove_dir_all(&old).with_context(|| format!("removing the replaced {}", old.display()))?;
    } else {
        std::fs::rename(&tmp, out).with_context(|| format!("renaming {} to {}", tmp.display(), out.display()))?;
    }
    std::fs::File::open(&parent).and_then(|f| f.sync_all()).ok();
    Ok(value)
}

/// The planned tensors of each weight component: (sub folder, shard base name, items).
pub fn plan_components(
    names: &[(String, Vec<i64>)],
    layout: DitLayout,
    kind_of: &dyn Fn(&str) -> Kind,
) -> Result<Vec<(&'static str, &'static str, Vec<Planned>)>> {
    let mut dit = Vec::new();
    let mut enc = Vec::new();
    let mut file_keys = BTreeSet::new();
    for (wan, shape) in names {
        if layout == DitLayout::BwmRelease && wan.starts_with(TEXT_EMBEDDING_PREFIX) {
            continue;
        }
        let mapped = keymap::to_layout(layout, wan)?;
        let is_enc = wan.starts_with(ACTION_PREFIX);
        let file_key = if layout == DitLayout::Diffusers && is_enc { wan[ACTION_PREFIX.len()..].to_string() } else { mapped };
        ensure!(file_keys.insert((is_enc && layout == DitLayout::Diffusers, file_key.clone())), "name collision: two tensors become '{file_key}'");
        let p = Planned { wan: wan.clone(), file_key, shape: shape.clone(), kind: kind_of(wan) };
        if layout == DitLayout::Diffusers && is_enc {
            enc.push(p);
        } else {
            dit.push(p);
        }
    }
    Ok(match layout {
        DitLayout::Diffusers => {
            let mut v = vec![(TRANSFORMER_DIR, DIFFUSERS_BASE, dit)];
            if !enc.is_empty() {
                v.push((ACTION_ENCODER_DIR, MODEL_BASE, enc));
            }
            v
        }
        _ => vec![("", MODEL_BASE, dit)],
    })
}

/// Writes the weight files of `names` (read from `source`) into `root` in `layout`; returns the
/// files and the index files (relative paths).
#[allow(clippy::too_many_arguments)]
pub fn write_weights(
    root: &Path,
    source: &dyn WeightSource,
    names: &[(String, Vec<i64>)],
    layout: DitLayout,
    kind_of: &dyn Fn(&str) -> Kind,
    cfg: Option<&ModelConfig>,
    shard_size: u64,
    fail_after: Option<usize>,
    progress: &mut dyn FnMut(&str),
) -> Result<(Vec<WrittenFile>, Vec<String>)> {
    let mut files = Vec::new();
    let mut indexes = Vec::new();
    let mut shards_written = 0usize;
    for (sub, base, items) in plan_components(names, layout, kind_of)? {
        let remaining = fail_after.map(|f| f.saturating_sub(shards_written));
        let written = repo::write_sharded(root, sub, base, &items, source, layout, shard_size, remaining, progress)?;
        shards_written += written.len() - 1;
        if let Some(last) = written.last() {
            indexes.push(last.path.clone());
        }
        files.extend(written);
        if layout == DitLayout::Diffusers {
            let comp_cfg = match (sub, cfg) {
                (TRANSFORMER_DIR, Some(c)) => Some(repo::diffusers_transformer_config(&c.dit)),
                (ACTION_ENCODER_DIR, Some(c)) => Some(serde_json::json!({
                    "_class_name": "WanVideoActionEncoder",
                    "dim": c.dit.dim, "action_dim": c.action.action_dim, "prepend": c.action.prepend, "group": c.action.group,
                    "action_mlp1": "Linear(action_dim, dim) -> GELU -> Linear(dim, dim): one cross-attention token per pixel frame",
                    "action_mlp2": "Linear(group*action_dim, group*dim) -> SiLU -> Linear(group*dim, dim): added to the time embedding of each latent frame",
                })),
                _ => None,
            };
            if let Some(c) = comp_cfg {
                let rel = format!("{sub}/{CONFIG_FILE}");
                let text = serde_json::to_string_pretty(&c)?;
                std::fs::write(root.join(&rel), &text).with_context(|| format!("writing {rel}"))?;
                files.push(WrittenFile { path: rel, bytes: text.len() as u64 });
            }
        }
    }
    Ok((files, indexes))
}

/// The `action_stats.json` content (a stat.json holding the one group) and the group's name.
fn read_action_stats(path: &Path, group: Option<&str>, action_dim: i64) -> Result<(serde_json::Value, String)> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading action statistics {}", path.display()))?;
    let all: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let obj = all.as_object().with_context(|| format!("{}: not a JSON object", path.display()))?;
    let (name, stats) = if obj.contains_key("p01") {
        (group.unwrap_or("state_pose").to_string(), all.clone())
    } else {
        let g = group.unwrap_or("state_pose");
        let s = obj.get(g).with_context(|| {
            format!("{}: no statistics group '{g}' (groups: {})", path.display(), obj.keys().cloned().collect::<Vec<_>>().join(", "))
        })?;
        (g.to_string(), s.clone())
    };
    for field in ["p01", "p99", "min", "max"] {
        let n = stats.get(field).and_then(|v| v.as_array()).map(|a| a.len());
        ensure!(n.is_some(), "{}: group '{name}' has no '{field}' list", path.display());
        ensure!(
            n == Some(action_dim as usize),
            "{}: group '{name}' has {}-dimensional statistics, the model's action_dim is {action_dim}",
            path.display(),
            n.unwrap_or(0)
        );
    }
    Ok((serde_json::json!({ name.clone(): stats }), name))
}

/// A summary of the run's `metrics.jsonl`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MetricsSummary {
    pub records: usize,
    pub last_step: u64,
    pub last_loss: f64,
    pub mean_loss_recent: f64,
    pub recent: usize,
    pub min_loss: f64,
    pub mean_samples_per_s: Option<f64>,
}

pub fn summarize_metrics(path: &Path) -> Result<Option<MetricsSummary>> {
    let Ok(text) = std::fs::read_to_string(path) else { return Ok(None) };
    let rows: Vec<(u64, f64, Option<f64>)> = text
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| {
            let step = v.get("step")?.as_u64()?;
            let loss = v.get("loss")?.as_f64()?;
            Some((step, loss, v.get("samples_per_s").and_then(|s| s.as_f64())))
        })
        .filter(|(_, l, _)| l.is_finite())
        .collect();
    if rows.is_empty() {
        return Ok(None);
    }
    let recent = (rows.len() / 10).clamp(1, 100);
    let tail = &rows[rows.len() - recent..];
    let sps: Vec<f64> = rows.iter().filter_map(|r| r.2).collect();
    Ok(Some(MetricsSummary {
        records: rows.len(),
        last_step: rows[rows.len() - 1].0,
        last_loss: rows[rows.len() - 1].1,
        mean_loss_recent: tail.iter().map(|r| r.1).sum::<f64>() / recent as f64,
        recent,
        min_loss: rows.iter().map(|r| r.1).fold(f64::INFINITY, f64::min),
        mean_samples_per_s: (!sps.is_empty()).then(|| sps.iter().sum::<f64>() / sps.len() as f64),
    }))
}

/// The latent cache's `index.json` (clip structure), when the run's cache is reachable.
fn read_cache_index(run: &RunInfo) -> Option<serde_json::Value> {
    let dir = run.latent_cache.as_ref()?;
    let text = std::fs::read_to_string(dir.join("index.json")).ok()?;
    let mut v: serde_json::Value = serde_json::from_str(&text).ok()?;
    if let Some(o) = v.as_object_mut() {
        let clips = o.remove("clips").and_then(|c| c.as_array().map(|a| a.len()));
        if let Some(n) = clips {
            o.insert("clips".into(), n.into());
        }
    }
    Some(v)
}

struct CardFacts<'a> {
    p: &'a Prepared,
    opts: &'a ExportOptions,
    cfg: &'a RepoConfig,
    metrics: Option<MetricsSummary>,
    stats_group: Option<String>,
    files: &'a [WrittenFile],
}

fn model_card(f: &CardFacts) -> String {
    let c = &f.p.cfg;
    let repo = f.opts.repo_id.clone().unwrap_or_else(|| "OWNER/NAME".into());
    let title = f
        .opts
        .repo_id
        .as_deref()
        .and_then(|r| r.split('/').nth(1))
        .map(String::from)
        .or_else(|| f.p.run.as_ref().map(|r| r.name().to_string()).filter(|n| !n.is_empty()))
        .unwrap_or_else(|| "BWM world model".into());
    let mut s = String::from("---\nlicense: apache-2.0\n");
    if let Some(b) = &f.cfg.base_model {
        s += &format!("base_model: {b}\n");
    }
    s += "library_name: bwm\npipeline_tag: image-to-video\ntags:\n- world-model\n- robotics\n- action-conditioned\n- video-generation\n- wan2.2\n---\n\n";
    s += &format!("# {title}\n\n");
    s += "An action-conditioned robot world model: the Wan2.2-TI2V DiT driven by the BWM action encoder instead of text \
(frame-level action tokens as the cross-attention context, latent-level action vectors added to the timestep embedding), \
post-trained with the `bwm` trainer. Given the first frame, recent history latents and an action trajectory, it predicts the future video latents (Wan2.2 VAE).\n\n";
    s += "## Model\n\n| | |\n|---|---|\n";
    s += &format!("| base model | {} |\n", f.cfg.base_model.clone().unwrap_or_else(|| "none (trained from random initialization)".into()));
    s += &format!(
        "| DiT | dim {}, {} layers, {} heads, ffn {}, patch {:?}, in/out {} channels |\n",
        c.dit.dim, c.dit.num_layers, c.dit.num_heads, c.dit.ffn_dim, c.dit.patch_size, c.dit.in_dim
    );
    s += &format!(
        "| action interface | {}-D actions, P={} copies of a_0 prepended, G={} actions per latent frame |\n",
        c.action.action_dim, c.action.prepend, c.action.group
    );
    s += &format!("| parameters | {} in {} tensors |\n", f.cfg.weights.parameters, f.cfg.weights.tensors);
    s += &format!("| layout | `{}` |\n| dtype | {} |\n| EMA weights | {} |\n\n", f.cfg.layout, f.cfg.weights.dtype, if f.cfg.weights.ema { "yes" } else { "no" });

    s += "## Training\n\n";
    match (&f.p.run, &f.p.state) {
        (Some(run), state) => {
            s += "| | |\n|---|---|\n";
            s += &format!("| run | `{}` |\n", run.name());
            if let Some(st) = state {
                s += &format!("| steps | {} (optimizer updates {}) |\n| samples seen | {} |\n", st.step, st.optimizer_step, st.samples_seen);
            }
            if let Some(p) = run.steps_planned {
                s += &format!("| steps planned | {p} |\n");
            }
            if let Some(lr) = run.lr {
                s += &format!("| learning rate | {lr} |\n");
            }
            if let (Some(mb), Some(ga)) = (run.micro_batch, run.grad_accum) {
                s += &format!("| batch | micro-batch {mb} x accumulation {ga} |\n");
            }
            if let Some(d) = run.ema_decay {
                s += &format!("| EMA decay | {d} |\n");
            }
            s += &format!("| training dtype | {} |\n", run.stated_dtype().map_or("?", |d| d.name()));
            if let Some(cache) = &run.latent_cache {
                s += &format!("| data | latent cache `{}` ({} clips held out) |\n", cache.display(), run.holdout_clips);
            }
            if let Some(cond) = &f.cfg.conditioning {
                let g = |k: &str| cond.get(k).map(|v| v.to_string()).unwrap_or_else(|| "?".into());
                s += &format!(
                    "| clips | {} pixel frames (1 + {} history + {} future), {} condition latents, resolution {}, {} fps |\n",
                    g("pixel_frames"),
                    g("history_frames"),
                    g("future_frames"),
                    g("condition_latents"),
                    g("resolution"),
                    g("fps")
                );
            }
            s += "\n";
        }
        (None, _) => s += "Exported from a weights file; no training run information was given.\n\n",
    }

    s += "## Metrics\n\n";
    match &f.metrics {
        Some(m) => {
            s += "From the run's `metrics.jsonl` (flow-matching training loss, timestep-weighted):\n\n| | |\n|---|---|\n";
            s += &format!("| logged steps | {} (last step {}) |\n", m.records, m.last_step);
            s += &format!("| final loss | {:.5} |\n", m.last_loss);
            s += &format!("| mean loss, last {} logged steps | {:.5} |\n", m.recent, m.mean_loss_recent);
            s += &format!("| lowest logged loss | {:.5} |\n", m.min_loss);
            if let Some(sps) = m.mean_samples_per_s {
                s += &format!("| throughput | {sps:.2} samples/s |\n");
            }
            s += "\n";
        }
        None => s += "No `metrics.jsonl` was found for this export.\n\n",
    }

    s += "## Actions\n\n";
    match &f.stats_group {
        Some(g) => {
            s += &format!(
                "Raw actions are normalized per dimension with the statistics in `{ACTION_STATS_FILE}` (group `{g}`): \
`2*(x - p01)/(p99 - p01 + 1e-8) - 1`, clipped to [-1, 1] (min/max where p01 = p99).\n\n"
            )
        }
        None => s += "No action statistics were exported: normalize actions to [-1, 1] as in training (`2*(x - p01)/(p99 - p01 + 1e-8) - 1` with the dataset's `stat.json`).\n\n",
    }

    s += "## Files\n\n";
    for file in f.files {
        s += &format!("- `{}` ({})\n", file.path, human_bytes(file.bytes));
    }
    s += &format!("- `{CONFIG_FILE}`: model, action interface, clip and normalization settings\n\n");
    if !f.cfg.weights.missing_keys.is_empty() {
        s += &format!(
            "Deliberately absent: {} (`{}`...): {}\n\n",
            f.cfg.weights.missing_keys.len(),
            f.cfg.weights.missing_keys[0],
            f.cfg.weights.missing_reason.clone().unwrap_or_default()
        );
    }

    s += "## How to load\n\n";
    s += &format!(
        "With `bwm` (any layout, picked from the files; a local folder or a Hub repo id through the Hugging Face cache):\n\n```rust\nlet model = bwm_checkpoints::open::load_model(\"{repo}\", None, tch::Kind::BFloat16, tch::Device::Cuda(0))?;\n```\n\n\
or `bwm convert dit {repo} OUT --to wan|diffusers|bwm-release`.\n\n"
    );
    let layout = f.cfg.layout.as_str();
    match layout {
        "diffusers" => {
            s += "With diffusers (the DiT; the action encoder is the `action_encoder/` component, which diffusers has no class for):\n\n```python\nfrom diffusers import WanTransformer3DModel\n";
            s += &format!("dit = WanTransformer3DModel.from_pretrained(\"{repo}\", subfolder=\"transformer\")\n```\n\n");
            s += "diffusers reports `condition_embedder.text_embedder.*` as newly initialized: it is absent on purpose (unused with actions).\n\n";
        }
        _ => {
            let prefix = f.cfg.weights.action_encoder_prefix.clone();
            s += "With DiffSynth-Studio (`diffsynth==2.0.11`, as the BWM release):\n\n```python\nimport json, torch\nfrom safetensors.torch import load_file\nfrom diffsynth.models.wan_video_dit import WanModel\n";
            s += "index = json.load(open(\"model.safetensors.index.json\"))\nsd = {}\nfor f in sorted(set(index[\"weight_map\"].values())):\n    sd.update(load_file(f))\n";
            s += &format!("enc = {{k[len(\"{prefix}\"):]: v for k, v in sd.items() if k.startswith(\"{prefix}\")}}\ndit_sd = {{k: v for k, v in sd.items() if not k.startswith(\"{prefix}\")}}\n");
            s += &format!(
                "dit = WanModel(dim={}, in_dim={}, ffn_dim={}, out_dim={}, text_dim={}, freq_dim={}, eps={:e}, patch_size={:?}, num_heads={}, num_layers={},\n              has_image_input=False, seperated_timestep=True, require_clip_embedding=False, require_vae_embedding=False, fuse_vae_embedding_in_latents=True)\n",
                c.dit.dim, c.dit.in_dim, c.dit.ffn_dim, c.dit.out_dim, c.dit.text_dim, c.dit.freq_dim, c.dit.eps, c.dit.patch_size, c.dit.num_heads, c.dit.num_layers
            );
            s += "missing, unexpected = dit.load_state_dict(dit_sd, strict=False)   # missing: text_embedding.* only\n```\n\n";
        }
    }
    s += "## License\n\nApache-2.0, as the Wan2.2 base model.\n";
    s
}

/// Exports `input` (a training checkpoint folder, or weights in any layout) into the model
/// repository folder `out`.
pub fn export(input: &str, out: &Path, opts: &ExportOptions, progress: &mut dyn FnMut(&str)) -> Result<ExportReport> {
    ensure!(opts.shard_size > 0, "the shard size must be positive");
    let in_path = Path::new(input);
    if in_path.exists() {
        let a = in_path.canonicalize().with_context(|| format!("resolving {input}"))?;
        let b = out.canonicalize().unwrap_or_else(|_| out.to_path_buf());
        ensure!(!a.starts_with(&b) && a != b, "the output {} would replace the input {input}", out.display());
    }
    let p = prepare(input, opts)?;
    let kind = opts.dtype.kind();
    let layout = opts.layout;
    let parameters: i64 = p
        .names
        .iter()
        .filter(|(n, _)| !(layout == DitLayout::BwmRelease && n.starts_with(TEXT_EMBEDDING_PREFIX)))
        .map(|(_, s)| s.iter().product::<i64>())
        .sum();
    let mut declared = p.declared_missing.clone();
    if layout == DitLayout::BwmRelease {
        declared.extend(p.names.iter().filter(|(n, _)| n.starts_with(TEXT_EMBEDDING_PREFIX)).map(|(n, _)| n.clone()));
        declared.sort();
        declared.dedup();
    }
    let tensors = p.names.len() - p.names.iter().filter(|(n, _)| layout == DitLayout::BwmRelease && n.starts_with(TEXT_EMBEDDING_PREFIX)).count();

    let stats = match &opts.action_stats {
        Some(path) => Some(read_action_stats(path, opts.action_stats_group.as_deref(), p.cfg.action.action_dim)?),
        None => None,
    };
    let metrics_path = opts.metrics.clone().or_else(|| {
        // <run>/checkpoints/step-N/ -> <run>/metrics.jsonl
        p.state.as_ref().and_then(|_| p.input.canonicalize().ok()).and_then(|c| c.parent()?.parent().map(|r| r.join("metrics.jsonl")))
    });
    let metrics = match &metrics_path {
        Some(m) => summarize_metrics(m)?,
        None => None,
    };
    if opts.metrics.is_some() && metrics.is_none() {
        bail!("{}: no readable metrics (expected one JSON object with step and loss per line)", metrics_path.unwrap_or_default().display());
    }
    let cache_index = p.run.as_ref().and_then(read_cache_index);
    let conditioning = p.run.as_ref().map(|r| {
        let mut c = serde_json::json!({ "condition_latents": r.record.objective.condition_latents });
        if let Some(ix) = &cache_index {
            for k in ["pixel_frames", "history_frames", "future_frames", "resolution", "fps", "latent_shape", "vae", "clips"] {
                if let Some(v) = ix.get(k) {
                    c[k] = v.clone();
                }
            }
        }
        c
    });
    let base_model = opts.base_model_id.clone().or_else(|| p.run.as_ref().and_then(|r| r.base_model_id()));
    let missing_reason = (!declared.is_empty()).then(|| {
        "text_embedding (umT5 text -> DiT width) is frozen and unused when actions replace the text context; BWM training checkpoints and the BWM release do not store it. Load with strict=False in PyTorch; diffusers reports the text embedder as newly initialized.".to_string()
    });

    progress(&format!(
        "exporting {} tensors ({} parameters) from {} as {} {}{}",
        tensors,
        parameters,
        p.source.describe(),
        layout,
        opts.dtype.name(),
        if p.ema { " (EMA)" } else { "" }
    ));
    let report = write_dir_atomically(out, opts.overwrite, |tmp| {
        let kind_of = |_: &str| kind;
        let (mut files, indexes) = write_weights(
            tmp,
            p.source.as_ref(),
            &p.names,
            layout,
            &kind_of,
            Some(&p.cfg),
            opts.shard_size,
            opts.fail_after_shards,
            progress,
        )?;
        let stats_group = match &stats {
            Some((value, group)) => {
                let text = serde_json::to_string_pretty(value)?;
                std::fs::write(tmp.join(ACTION_STATS_FILE), &text).context("writing action_stats.json")?;
                files.push(WrittenFile { path: ACTION_STATS_FILE.into(), bytes: text.len() as u64 });
                Some(group.clone())
            }
            None => None,
        };
        let repo_cfg = RepoConfig {
            model_type: repo::MODEL_TYPE.into(),
            bwm_format_version: repo::FORMAT_VERSION,
            architecture: "Wan2.2-TI2V DiT (WanModel) + BWM action encoder (WanVideoActionEncoder, ti2v2 path)".into(),
            layout: layout.name().into(),
            dit: p.cfg.dit.clone(),
            action: p.cfg.action.clone(),
            weights: WeightsInfo {
                index_files: indexes,
                dtype: opts.dtype.name().into(),
                tensors,
                parameters,
                action_encoder_prefix: if layout == DitLayout::Diffusers { format!("{ACTION_ENCODER_DIR}/ (keys without prefix)") } else { layout.action_prefix().into() },
                missing_keys: declared.clone(),
                missing_reason: missing_reason.clone(),
                ema: p.ema,
            },
            conditioning: conditioning.clone(),
            action_normalization: Some(serde_json::json!({
                "formula": "2*(x - p01)/(p99 - p01 + 1e-8) - 1, clipped to [-1, 1]; min/max where p99 <= p01",
                "stats_file": stats_group.as_ref().map(|_| ACTION_STATS_FILE),
                "group": stats_group,
                "action_dim": p.cfg.action.action_dim,
            })),
            schedule: p.run.as_ref().map(|r| {
                serde_json::json!({"kind": "flow-matching (Wan)", "num_train_timesteps": 1000, "shift": r.record.objective.shift, "history_sigma": r.record.objective.history_sigma})
            }),
            base_model: base_model.clone(),
            training: p.run.as_ref().map(|r| {
                let mut t = serde_json::json!({"run": r.name(), "seed": r.seed(), "preset": r.record.model.preset, "dtype": r.stated_dtype().map(|d| d.name()), "residual": r.stated_residual(), "action_dropout": r.record.objective.action_dropout, "lr": r.lr, "ema_decay": r.ema_decay});
                if let Some(st) = &p.state {
                    t["step"] = st.step.into();
                    t["samples_seen"] = st.samples_seen.into();
                    t["trained_tensors"] = st.trainable.len().into();
                }
                if let Some(m) = &metrics {
                    t["final_loss"] = m.last_loss.into();
                    t["mean_loss_recent"] = m.mean_loss_recent.into();
                }
                t
            }),
        };
        let card = model_card(&CardFacts { p: &p, opts, cfg: &repo_cfg, metrics: metrics.clone(), stats_group: stats_group.clone(), files: &files });
        std::fs::write(tmp.join(README_FILE), &card).context("writing README.md")?;
        files.push(WrittenFile { path: README_FILE.into(), bytes: card.len() as u64 });
        // config.json last: a folder without it is not a finished export.
        let text = serde_json::to_string_pretty(&repo_cfg)?;
        std::fs::write(tmp.join(CONFIG_FILE), &text).context("writing config.json")?;
        files.push(WrittenFile { path: CONFIG_FILE.into(), bytes: text.len() as u64 });
        Ok(ExportReport {
            out: out.to_path_buf(),
            layout,
            files,
            tensors,
            parameters,
            declared_missing: declared.clone(),
            from_base: p.from_base,
        })
    })?;
    Ok(report)
}

/// The EMA weights of a training checkpoint, shaped like its `model.safetensors`: the `ema` slices
/// of the optimizer shard files (or `ema.<name>` of an unsharded `optimizer.safetensors`).
fn ema_weights(dir: &Path, model_file: &Path) -> Result<crate::sources::TensorSource> {
    use crate::optimizer_shards::{stored_layout, OptimizerState, LEGACY_FILE};
    let model = SafetensorsSource::open(model_file)?;
    let layout = if dir.join(LEGACY_FILE).is_file() {
        let numel = |n: &str| model.shape(n).map_or(0, |s| s.iter().product::<i64>() as usize);
        model.names().into_iter().map(|n| (n.clone(), numel(&n))).collect()
    } else {
        stored_layout(dir)?
    };
    let state = OptimizerState::open(dir, &layout)?;
    ensure!(state.has("ema")?, "the optimizer state holds no EMA weights (the run had no optim.ema_decay)");
    let mut tensors = Vec::new();
    for (name, flat) in state.read_named("ema", tch::Device::Cpu)? {
        let shape = model.shape(&name).with_context(|| format!("{}: no '{name}' for the EMA tensor", model_file.display()))?;
        tensors.push((name, flat.view(shape.as_slice())));
    }
    Ok(crate::sources::TensorSource::new(tensors, format!("EMA weights of {}", dir.display())))
}

/// Whether `input` is a training checkpoint folder of a LoRA run.
pub fn is_lora_checkpoint(input: &str) -> Result<bool> {
    let dir = Path::new(input);
    Ok(crate::run_dir::is_training_checkpoint(dir) && CheckpointState::read(dir)?.run.lora().is_some())
}

/// What [`export_lora_adapters`] wrote.
#[derive(Debug, Clone)]
pub struct AdapterExport {
    pub out: PathBuf,
    /// Adapted linear layers.
    pub layers: usize,
    pub parameters: i64,
    /// Trained tensors besides the adapters (the action encoder), which an adapter file cannot
    /// carry: export them with `--merge-lora`.
    pub left_out: Vec<String>,
}

/// The file diffusers' `load_lora_weights` / `load_lora_adapter` reads from a folder.
pub const LORA_WEIGHTS_FILE: &str = "pytorch_lora_weights.safetensors";

/// A LoRA checkpoint's adapters in the layout diffusers and PEFT read for
/// `WanTransformer3DModel`: `transformer.<diffusers module>.lora_A.weight` / `.lora_B.weight` in
/// `LORA_WEIGHTS_FILE`, B scaled by alpha / rank (so the default alpha = rank of a loader applies
/// the trained update), and PEFT's `adapter_config.json`. Written atomically as `export` is.
pub fn export_lora_adapters(input: &str, out: &Path, dtype: ExportDtype, overwrite: bool) -> Result<AdapterExport> {
    let dir = Path::new(input);
    ensure!(crate::run_dir::is_training_checkpoint(dir), "{input}: not a training checkpoint folder (an adapter export reads one)");
    let state = CheckpointState::read(dir)?;
    let Some(lora) = state.run.lora().cloned() else { bail!("{input} is not a LoRA checkpoint (its run config has no model.lora)") };
    let source = SafetensorsSource::open(&dir.join("model.safetensors"))?;
    let kind = dtype.kind();
    let mut tensors = Vec::new();
    let mut modules = BTreeSet::new();
    let mut left_out = Vec::new();
    let mut parameters = 0i64;
    for name in source.names() {
        let Some((module, part)) = bwm_model::lora::split_adapter_key(&name) else {
            left_out.push(name);
            continue;
        };
        let diffusers = keymap::to_layout(DitLayout::Diffusers, &format!("{module}.weight"))
            .with_context(|| format!("{input}: the adapter {name}"))?;
        let diffusers_module = diffusers.strip_suffix(".weight").unwrap_or(&diffusers).to_string();
        let mut t = source.load(&name, Kind::Float, Device::Cpu)?;
        if part == "lora_B" {
            t = t * lora.scale();
        }
        parameters += t.numel() as i64;
        modules.insert(diffusers_module.clone());
        tensors.push((format!("transformer.{diffusers_module}.{part}.weight"), t.to_kind(kind)));
    }
    ensure!(!tensors.is_empty(), "{input}: the checkpoint holds no adapter tensors");
    let config = serde_json::json!({
        "peft_type": "LORA",
        "r": lora.rank,
        "lora_alpha": lora.rank,
        "lora_dropout": lora.dropout,
        "target_modules": modules.iter().collect::<Vec<_>>(),
        "bias": "none",
        "bwm": {"alpha": lora.alpha.unwrap_or(lora.rank as f64), "scale_folded_into_lora_B": lora.scale(), "step": state.step},
    });
    write_dir_atomically(out, overwrite, |tmp| {
        crate::tensor_file::write_tensors(&tmp.join(LORA_WEIGHTS_FILE), &tensors, &BTreeMap::new())?;
        std::fs::write(tmp.join("adapter_config.json"), serde_json::to_string_pretty(&config)? + "\n").context("writing adapter_config.json")
    })?;
    Ok(AdapterExport { out: out.to_path_buf(), layers: modules.len(), parameters, left_out })
}
