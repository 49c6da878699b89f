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
//! folder (which `open_any` refuses and the next export removes: `atomic_dir`).
//!
//! The model card is `model_card`'s; a LoRA checkpoint's adapters alone are `lora_export`'s.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use bwm_model::weights::{SafetensorsSource, TensorSource, WeightSource};
use bwm_model::ModelConfig;
use tch::Kind;

use crate::atomic_dir::write_dir_atomically;
use crate::keymap::{self, DitLayout, ACTION_PREFIX, TEXT_EMBEDDING_PREFIX};
use crate::model_card::{model_card, summarize_metrics, CardFacts};
use crate::open::{check_fits, model_keys, open_any};
use crate::repo::{
    self, Planned, RepoConfig, WeightsInfo, WrittenFile, ACTION_ENCODER_DIR, ACTION_STATS_FILE, CONFIG_FILE, DIFFUSERS_BASE,
    MODEL_BASE, README_FILE, TRANSFORMER_DIR,
};
pub use crate::repo::ExportDtype;
use crate::run_info::{CheckpointState, RunInfo};
use crate::sources::UnionSource;

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

/// The input contract an export carries: the checkpoint's (its `contract.json`), else one made
/// from the run's latent cache where it is still reachable, else the action width alone; the
/// normalization of `--action-stats` is added where none is recorded, and must equal a recorded one.
fn export_contract(input: &Path, run: Option<&RunInfo>, action_dim: usize, stats: Option<&(serde_json::Value, String)>) -> Result<crate::contract::InputContract> {
    use crate::contract::{read, InputContract, Normalization, NORMALIZATION_FORMULA};
    let mut contract = match read(input)? {
        Some(c) => c,
        None => match run.and_then(|r| r.latent_cache.as_ref()).filter(|c| c.join("index.json").is_file()) {
            Some(cache) => InputContract::from_cache(action_dim, cache).with_context(|| format!("the input contract of {}", input.display()))?,
            None => InputContract::of_model(action_dim),
        },
    };
    if let Some((value, group)) = stats {
        let parsed: bwm_data::ActionStats = serde_json::from_value(value[group].clone()).with_context(|| format!("--action-stats group '{group}'"))?;
        parsed.check().with_context(|| format!("--action-stats group '{group}'"))?;
        let actions = contract.actions.get_or_insert_with(|| InputContract::of_model(action_dim).actions.unwrap());
        // Weights trained with recorded statistics take their actions normalized by those: others
        // would have every caller normalize otherwise than training did.
        if let Some(recorded) = &actions.normalization {
            let same = |a: &[f64], b: &[f64]| a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-9 * x.abs().max(y.abs()).max(1.0));
            let (r, p) = (&recorded.stats, &parsed);
            ensure!(
                recorded.group == *group && same(&r.p01, &p.p01) && same(&r.p99, &p.p99) && same(&r.min, &p.min) && same(&r.max, &p.max),
                "--action-stats (group '{group}') differs from the statistics these weights were trained with (group '{}', recorded in {}); leave --action-stats out to export those",
                recorded.group,
                crate::contract::CONTRACT_FILE
            );
        }
        actions.normalization = Some(Normalization { formula: NORMALIZATION_FORMULA.into(), group: group.clone(), stats: parsed });
    }
    contract.check_action_dim(action_dim, "the weights")?;
    Ok(contract)
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
        Some(m) => summarize_metrics(m, p.state.as_ref().map(|s| s.step))?,
        None => None,
    };
    if opts.metrics.is_some() && metrics.is_none() {
        bail!("{}: no readable metrics (expected one JSON object with step and loss per line)", metrics_path.unwrap_or_default().display());
    }
    let cache_index = p.run.as_ref().and_then(read_cache_index);
    let contract = export_contract(&p.input, p.run.as_ref(), p.cfg.action.action_dim as usize, stats.as_ref())?;
    // Without --action-stats, the statistics the contract records (the training cache's) become
    // action_stats.json.
    let stats = stats.or_else(|| {
        let n = contract.actions.as_ref()?.normalization.as_ref()?;
        Some((serde_json::json!({ n.group.clone(): n.stats }), n.group.clone()))
    });
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
        // The input contract (with the sampler the fidelity was measured at) travels with the weights.
        let path = crate::contract::write(tmp, &contract)?;
        files.push(WrittenFile { path: crate::contract::CONTRACT_FILE.into(), bytes: std::fs::metadata(&path)?.len() });
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
        let card = model_card(&CardFacts {
            model: &p.cfg,
            run: p.run.as_ref(),
            state: p.state.as_ref(),
            repo_id: opts.repo_id.as_deref(),
            cfg: &repo_cfg,
            metrics: metrics.clone(),
            stats_group: stats_group.clone(),
            files: &files,
        });
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
fn ema_weights(dir: &Path, model_file: &Path) -> Result<TensorSource> {
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
    Ok(TensorSource::new(tensors, format!("EMA weights of {}", dir.display())))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contract::{write, InputContract, Normalization, NORMALIZATION_FORMULA};

    #[test]
    fn action_statistics_other_than_the_recorded_ones_are_refused() {
        let dir = bwm_testdir::tmp_dir("export-stats");
        let stats = |p99: f64| bwm_data::ActionStats { shape: vec![2], min: vec![-2.0; 2], max: vec![2.0; 2], p01: vec![-1.0; 2], p99: vec![p99; 2], mean: vec![0.0; 2], std: vec![0.5; 2] };
        let given = |p99: f64| (serde_json::json!({ "state_pose": stats(p99) }), "state_pose".to_string());
        // No statistics recorded: the given ones are taken.
        let c = export_contract(dir.path(), None, 2, Some(&given(1.0))).unwrap();
        assert_eq!(c.actions.as_ref().unwrap().normalization.as_ref().unwrap().stats, stats(1.0));
        // Recorded: the same ones pass, others are refused.
        let mut recorded = InputContract::of_model(2);
        recorded.actions.as_mut().unwrap().normalization = Some(Normalization { formula: NORMALIZATION_FORMULA.into(), group: "state_pose".into(), stats: stats(1.0) });
        write(dir.path(), &recorded).unwrap();
        export_contract(dir.path(), None, 2, Some(&given(1.0))).unwrap();
        let e = export_contract(dir.path(), None, 2, Some(&given(1.5))).unwrap_err().to_string();
        assert!(e.contains("differs from the statistics these weights were trained with"), "{e}");
    }
}
