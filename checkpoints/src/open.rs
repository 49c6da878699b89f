//! Opening DiT (+ action encoder) weights in any layout this project knows, presenting them under
//! the Wan-native names the model asks for: a local file or folder (Wan-native, diffusers, BWM
//! release, an `export` of this crate, the official `Wan-AI/Wan2.2-TI2V-5B` and
//! `-Diffusers` folders), or a Hub repo id read through hf-hub's cache.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::rc::Rc;

use anyhow::{bail, ensure, Context, Result};
use bwm_model::weights::{SafetensorsSource, TensorSource, WeightSource};
use bwm_model::{BwmModel, ModelConfig, ParamStore};
use tch::{Device, Kind};

use crate::keymap::{self, DitLayout, ACTION_PREFIX, TEXT_EMBEDDING_PREFIX};
use crate::repo::{self, RepoConfig, ACTION_ENCODER_DIR, CONFIG_FILE, TRANSFORMER_DIR};
use crate::run_info::RunInfo;
use bwm_run_config::{Dtype, InitSource};
use crate::sources::{LoraMergedSource, MappedSource, UnionSource};

/// Weights opened by [`open_any`].
pub struct OpenedWeights {
    /// Wan-native names (`blocks.0.self_attn.q.weight`, `action_encoder.action_mlp1.0.weight`).
    pub source: Box<dyn WeightSource>,
    /// The layout the files are in.
    pub layout: DitLayout,
    /// The model config, when the files carry one (a BWM `config.json`, or a diffusers / official
    /// Wan config for the DiT with the default action interface).
    pub config: Option<ModelConfig>,
    /// The BWM repository config, for an export of this crate.
    pub repo_config: Option<RepoConfig>,
    /// Wan-native keys the files deliberately lack (declared in a BWM `config.json`, or
    /// `text_embedding.*` for the BWM release).
    pub declared_missing: Vec<String>,
    /// Stored dtype per Wan-native name.
    pub kinds: BTreeMap<String, Kind>,
    /// The local file or folder read (a Hub snapshot folder for a repo id).
    pub location: PathBuf,
}

impl OpenedWeights {
    pub fn into_source(self) -> Box<dyn WeightSource> {
        self.source
    }
}

impl std::fmt::Debug for OpenedWeights {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OpenedWeights")
            .field("location", &self.location)
            .field("layout", &self.layout)
            .field("tensors", &self.kinds.len())
            .finish()
    }
}


/// Opens weights from a local file or folder, or a Hub repo id (`owner/name[@revision]`) through
/// hf-hub's cache (`HF_HOME`, `HF_ENDPOINT`, `HF_TOKEN`; with `HF_HUB_OFFLINE=1` only the cache is
/// read), and picks the layout from the files present.
pub fn open_any(path_or_repo_id: &str) -> Result<OpenedWeights> {
    let path = Path::new(path_or_repo_id);
    if path.exists() {
        return open_local(path);
    }
    if crate::hub::is_repo_id(path_or_repo_id) {
        let env = crate::hub::HubEnv::from_env();
        let snapshot = crate::hub::snapshot_for_loading(path_or_repo_id, &env)
            .with_context(|| format!("'{path_or_repo_id}' is no local file or folder; read as a Hub repo id"))?;
        return open_local(&snapshot).with_context(|| format!("Hub repo {path_or_repo_id} ({})", snapshot.display()));
    }
    bail!("'{path_or_repo_id}': no such file or folder, and not a Hub repo id (owner/name)")
}

/// Opens a local weights file (`.safetensors`, `*.safetensors.index.json`, `.pth`) or folder.
pub fn open_local(path: &Path) -> Result<OpenedWeights> {
    if path.is_dir() {
        return open_dir(path);
    }
    ensure!(path.is_file(), "{}: no such file or folder", path.display());
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
    if name.ends_with(".index.json") {
        repo::index_shards(path)?;
    }
    let (source, kinds) = open_file(path)?;
    from_detected(source, kinds, path, None)
}

fn open_file(path: &Path) -> Result<(Box<dyn WeightSource>, BTreeMap<String, Kind>)> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("pth") | Some("pt") | Some("bin") => {
            let pth = bwm_model::pth::open(path)?;
            let kinds = pth.tensors().iter().map(|(k, t)| (k.clone(), t.kind())).collect();
            Ok((Box::new(pth), kinds))
        }
        _ => {
            let st = SafetensorsSource::open(path)?;
            let kinds = st.names().into_iter().map(|n| (n.clone(), st.kind(&n).unwrap_or(Kind::Float))).collect();
            Ok((Box::new(st), kinds))
        }
    }
}

/// A source whose layout is judged from its keys, renamed to Wan-native.
fn from_detected(
    source: Box<dyn WeightSource>,
    kinds: BTreeMap<String, Kind>,
    location: &Path,
    config: Option<ModelConfig>,
) -> Result<OpenedWeights> {
    let names = source.names();
    let layout = keymap::detect_layout(&names).with_context(|| format!("{}", location.display()))?;
    let (source, kinds) = rename(source, &kinds, layout, "")?;
    let declared_missing = if layout == DitLayout::BwmRelease { text_embedding_keys() } else { Vec::new() };
    Ok(OpenedWeights { source, layout, config, repo_config: None, declared_missing, kinds, location: location.to_path_buf() })
}

/// Renames `source` from `layout` (keys first prefixed with `prefix`) to Wan-native names.
fn rename(
    source: Box<dyn WeightSource>,
    kinds: &BTreeMap<String, Kind>,
    layout: DitLayout,
    prefix: &str,
) -> Result<(Box<dyn WeightSource>, BTreeMap<String, Kind>)> {
    let names = source.names();
    let prefixed: Vec<String> = names.iter().map(|n| format!("{prefix}{n}")).collect();
    let mapped = keymap::map_keys_from(layout, &prefixed).with_context(|| source.describe())?;
    let mut new_kinds = BTreeMap::new();
    let pairs: Vec<(String, String)> = mapped
        .into_iter()
        .zip(names)
        .map(|((_, wan), original)| {
            new_kinds.insert(wan.clone(), kinds.get(&original).copied().unwrap_or(Kind::Float));
            (wan, original)
        })
        .collect();
    Ok((Box::new(MappedSource::new(source, pairs)?), new_kinds))
}

fn text_embedding_keys() -> Vec<String> {
    ["0.weight", "0.bias", "2.weight", "2.bias"].iter().map(|s| format!("{TEXT_EMBEDDING_PREFIX}{s}")).collect()
}

fn read_json(path: &Path) -> Result<Option<serde_json::Value>> {
    match std::fs::read_to_string(path) {
        Ok(text) => Ok(Some(serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?)),
        Err(_) => Ok(None),
    }
}

/// The weights file of a component folder: its one `*.safetensors.index.json` (checked complete),
/// else its one `*.safetensors`.
fn component_weights(dir: &Path) -> Result<PathBuf> {
    let mut index = Vec::new();
    let mut single = Vec::new();
    for entry in std::fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))? {
        let p = entry?.path();
        let n = p.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_string();
        if n.ends_with(".safetensors.index.json") {
            index.push(p);
        } else if n.ends_with(".safetensors") {
            single.push(p);
        }
    }
    match (index.len(), single.len()) {
        (1, _) => {
            repo::index_shards(&index[0])?;
            Ok(index.remove(0))
        }
        (0, 1) => Ok(single.remove(0)),
        (0, 0) => bail!("{}: no .safetensors file or shard index", dir.display()),
        (0, _) => bail!("{}: several .safetensors files and no shard index; name the file", dir.display()),
        _ => bail!("{}: several shard indexes; name one", dir.display()),
    }
}

fn open_dir(dir: &Path) -> Result<OpenedWeights> {
    let name = dir.file_name().and_then(|n| n.to_str()).unwrap_or_default();
    ensure!(
        !name.contains(".tmp-"),
        "{}: the temporary folder of an unfinished export or checkpoint (it was interrupted); export again",
        dir.display()
    );
    if let Some(cfg) = RepoConfig::read(dir)? {
        return open_export(dir, cfg);
    }
    if crate::run_dir::is_training_checkpoint(dir) {
        return open_training_checkpoint(dir);
    }
    let config_json = read_json(&dir.join(CONFIG_FILE))?;
    let class = config_json.as_ref().and_then(|c| c.get("_class_name")).and_then(|c| c.as_str()).unwrap_or_default().to_string();
    let has_weights_here = std::fs::read_dir(dir)
        .with_context(|| format!("listing {}", dir.display()))?
        .filter_map(|e| e.ok())
        .any(|e| e.file_name().to_string_lossy().ends_with(".safetensors"));
    if class.is_empty() && has_weights_here && dir.join(repo::README_FILE).is_file() && config_json.is_none() {
        bail!(
            "{}: has weights and a model card but no {CONFIG_FILE}: an export that did not finish (config.json is written last); export again",
            dir.display()
        );
    }
    // A diffusers pipeline folder (or a BWM diffusers export without its config): transformer/.
    let transformer = dir.join(TRANSFORMER_DIR);
    if transformer.is_dir() && !has_weights_here {
        let mut opened = open_diffusers_component(&transformer)?;
        let enc = dir.join(ACTION_ENCODER_DIR);
        if enc.is_dir() {
            attach_action_encoder(&mut opened, &enc)?;
        }
        opened.location = dir.to_path_buf();
        return Ok(opened);
    }
    if class == "WanTransformer3DModel" {
        return open_diffusers_component(dir);
    }
    let foreign_cfg = config_json
        .as_ref()
        .and_then(repo::dit_config_from_foreign)
        .map(|dit| ModelConfig { dit, action: Default::default() });
    let file = component_weights(dir)?;
    let (source, kinds) = open_file(&file)?;
    let mut opened = from_detected(source, kinds, &file, foreign_cfg)?;
    opened.location = dir.to_path_buf();
    Ok(opened)
}

/// A training checkpoint folder: its `model.safetensors` (the trained tensors), under the model
/// config of the run that wrote it; a LoRA run's adapters merged into the base weights it
/// started from.
fn open_training_checkpoint(dir: &Path) -> Result<OpenedWeights> {
    let state = crate::run_info::CheckpointState::read(dir)?;
    let model_file = dir.join("model.safetensors");
    ensure!(model_file.is_file(), "{}: no model.safetensors; not a complete training checkpoint", dir.display());
    if state.run.lora().is_some() {
        let what = dir.display().to_string();
        let source = merge_lora_checkpoint(Box::new(SafetensorsSource::open(&model_file)?), &state.run, None, &what)?;
        let kind = if state.run.stated_dtype() == Some(Dtype::Bf16) { Kind::BFloat16 } else { Kind::Float };
        let kinds = source.names().into_iter().map(|n| (n, kind)).collect();
        return Ok(OpenedWeights {
            source,
            layout: DitLayout::WanNative,
            config: Some(state.run.model),
            repo_config: None,
            declared_missing: Vec::new(),
            kinds,
            location: dir.to_path_buf(),
        });
    }
    let mut opened = open_local(&model_file)?;
    opened.config = Some(state.run.model);
    opened.location = dir.to_path_buf();
    Ok(opened)
}

/// A LoRA run's trained tensors (Wan-native names: its adapters and whatever else it trained)
/// over the base weights it started from, the adapters merged in. The base is `base` (any weights
/// `open_any` reads), else the run's `model.init`; a run from random weights gets them drawn
/// again from its seed, as the trainer drew them.
pub fn merge_lora_checkpoint(trained: Box<dyn WeightSource>, run: &RunInfo, base: Option<&str>, what: &str) -> Result<Box<dyn WeightSource>> {
    let Some(lora) = run.lora() else { bail!("{what}: not a LoRA run (no model.lora in its config)") };
    let base_source: Box<dyn WeightSource> = match (base, run.init()) {
        (Some(spec), _) => open_any(spec).with_context(|| format!("{what}: the base weights {spec}"))?.into_source(),
        (None, InitSource::WanPretrained { path: p } | InitSource::BwmCheckpoint { path: p }) => open_any(&p.to_string_lossy())
            .with_context(|| format!("{what}: the base weights its run started from ({})", p.display()))?
            .into_source(),
        (None, InitSource::Random) => {
            let model = BwmModel::random(&run.model, Kind::Float, Device::Cpu, run.seed() as i64)
                .with_context(|| format!("{what}: drawing the random base weights of its run again"))?;
            Box::new(TensorSource::new(model.store.named_parameters(), format!("the random base weights of run {} (seed {})", run.name(), run.seed())))
        }
    };
    Ok(Box::new(LoraMergedSource::over(trained, base_source, lora.scale())?))
}

/// LoRA adapters as diffusers and PEFT store them for `WanTransformer3DModel` (what `bwm export`
/// writes for a LoRA checkpoint): a folder holding `pytorch_lora_weights.safetensors` (and
/// optionally PEFT's `adapter_config.json`), or the file itself. Returns the adapters under
/// Wan-native names (`blocks.0.self_attn.q.lora_A.weight`) and their scale (`lora_alpha / r` of
/// the config, 1 without one).
pub fn open_lora_adapters(path: &Path) -> Result<(Box<dyn WeightSource>, f64)> {
    let (file, config) = if path.is_dir() {
        (path.join(crate::lora_export::LORA_WEIGHTS_FILE), path.join("adapter_config.json"))
    } else {
        (path.to_path_buf(), path.with_file_name("adapter_config.json"))
    };
    ensure!(file.is_file(), "{}: no LoRA weights ({} expected)", path.display(), crate::lora_export::LORA_WEIGHTS_FILE);
    let source = SafetensorsSource::open(&file)?;
    let mut pairs = Vec::new();
    for name in source.names() {
        let stripped = name.strip_prefix("transformer.").unwrap_or(&name);
        let Some((module, part)) = bwm_model::lora::split_adapter_key(stripped) else {
            bail!("{}: '{name}' is not a LoRA tensor (<module>.lora_A.weight / .lora_B.weight)", file.display());
        };
        let wan = keymap::from_layout(DitLayout::Diffusers, &format!("{module}.weight"))
            .with_context(|| format!("{}: the adapter '{name}'", file.display()))?;
        let wan_module = wan.strip_suffix(".weight").unwrap_or(&wan);
        pairs.push((format!("{wan_module}.{part}.weight"), name));
    }
    ensure!(!pairs.is_empty(), "{}: holds no tensors", file.display());
    let scale = match read_json(&config)? {
        Some(c) => {
            let r = c.get("r").and_then(|v| v.as_f64()).with_context(|| format!("{}: no r", config.display()))?;
            c.get("lora_alpha").and_then(|v| v.as_f64()).unwrap_or(r) / r
        }
        None => 1.0,
    };
    Ok((Box::new(MappedSource::new(Box::new(source), pairs)?), scale))
}

/// `opened` with the adapters at `adapters` ([`open_lora_adapters`]) merged into its weights.
pub fn with_lora_adapters(mut opened: OpenedWeights, adapters: &Path) -> Result<OpenedWeights> {
    let (source, scale) = open_lora_adapters(adapters)?;
    let base = std::mem::replace(&mut opened.source, Box::new(TensorSource::new([], "")));
    opened.source = Box::new(LoraMergedSource::over(source, base, scale)?);
    Ok(opened)
}

fn open_diffusers_component(dir: &Path) -> Result<OpenedWeights> {
    let cfg = read_json(&dir.join(CONFIG_FILE))?
        .as_ref()
        .and_then(repo::dit_config_from_foreign)
        .map(|dit| ModelConfig { dit, action: Default::default() });
    let file = component_weights(dir)?;
    let (source, kinds) = open_file(&file)?;
    let layout = keymap::detect_layout(&source.names()).with_context(|| format!("{}", file.display()))?;
    ensure!(
        layout == DitLayout::Diffusers,
        "{}: a diffusers transformer folder whose weights are in the {layout} layout",
        dir.display()
    );
    let (source, kinds) = rename(source, &kinds, layout, "")?;
    Ok(OpenedWeights {
        source,
        layout,
        config: cfg,
        repo_config: None,
        declared_missing: Vec::new(),
        kinds,
        location: dir.to_path_buf(),
    })
}

/// Adds the action encoder stored as its own component (keys without the prefix).
fn attach_action_encoder(opened: &mut OpenedWeights, enc_dir: &Path) -> Result<()> {
    let file = component_weights(enc_dir)?;
    let (source, kinds) = open_file(&file)?;
    let (enc, enc_kinds) = rename(source, &kinds, DitLayout::WanNative, ACTION_PREFIX)?;
    for name in enc.names() {
        ensure!(name.starts_with(ACTION_PREFIX), "{}: '{name}' is not an action-encoder key", file.display());
    }
    let dit = std::mem::replace(&mut opened.source, Box::new(TensorSource::new([], "")));
    opened.source = Box::new(UnionSource::new(vec![dit, enc])?);
    opened.kinds.extend(enc_kinds);
    Ok(())
}

fn open_export(dir: &Path, cfg: RepoConfig) -> Result<OpenedWeights> {
    let layout = cfg.layout().with_context(|| format!("{}/{CONFIG_FILE}", dir.display()))?;
    ensure!(!cfg.weights.index_files.is_empty(), "{}/{CONFIG_FILE}: lists no weight files", dir.display());
    let mut parts: Vec<Box<dyn WeightSource>> = Vec::new();
    let mut kinds = BTreeMap::new();
    for index in &cfg.weights.index_files {
        let path = dir.join(index);
        ensure!(path.is_file(), "{}: {CONFIG_FILE} lists {index}, which is missing: a partial copy of the export", dir.display());
        repo::index_shards(&path)?;
        let (source, k) = open_file(&path)?;
        let is_action_component = layout == DitLayout::Diffusers && index.starts_with(&format!("{ACTION_ENCODER_DIR}/"));
        let (prefix, part_layout) = if is_action_component { (ACTION_PREFIX, DitLayout::WanNative) } else { ("", layout) };
        let (renamed, k) = rename(source, &k, part_layout, prefix)?;
        kinds.extend(k);
        parts.push(renamed);
    }
    let source: Box<dyn WeightSource> = if parts.len() == 1 { parts.remove(0) } else { Box::new(UnionSource::new(parts)?) };
    let expected = cfg.weights.tensors;
    ensure!(
        source.names().len() == expected,
        "{}: {CONFIG_FILE} declares {expected} tensors, the files hold {}",
        dir.display(),
        source.names().len()
    );
    Ok(OpenedWeights {
        source,
        layout,
        config: Some(cfg.model_config()),
        declared_missing: cfg.weights.missing_keys.clone(),
        repo_config: Some(cfg),
        kinds,
        location: dir.to_path_buf(),
    })
}

/// Every (Wan-native name, shape) of the model `cfg` describes, in module order (text_embedding
/// included).
pub fn model_keys(cfg: &ModelConfig) -> Result<Vec<(String, Vec<i64>)>> {
    let store = ParamStore::shapes_only(Kind::Float);
    BwmModel::build(&store, cfg)?;
    Ok(store.named_parameters().into_iter().map(|(n, t)| (n, t.size())).collect())
}

/// Checks that every tensor of `source` is a tensor of the model `cfg` with its shape: an error
/// that names the first key that is not (weights from a model of another size).
pub fn check_fits(source: &dyn WeightSource, cfg: &ModelConfig, what: &str) -> Result<()> {
    let keys: BTreeMap<String, Vec<i64>> = model_keys(cfg)?.into_iter().collect();
    let summary = format!(
        "dim {}, {} layers, {} heads, ffn {}, action_dim {}",
        cfg.dit.dim, cfg.dit.num_layers, cfg.dit.num_heads, cfg.dit.ffn_dim, cfg.action.action_dim
    );
    for name in source.names() {
        let shape = source.shape(&name).unwrap_or_default();
        match keys.get(&name) {
            None => bail!("{what} holds '{name}', which the model config ({summary}) has no tensor for: weights of another model config"),
            Some(expected) if *expected != shape => bail!(
                "{what}: '{name}' has shape {shape:?}, the model config ({summary}) expects {expected:?}: weights of another model config"
            ),
            _ => {}
        }
    }
    Ok(())
}

/// What weights record of the training behind them: a training checkpoint's run config, or an
/// export's `config.json` (`training`). Weights that do not say (official, release, foreign files)
/// record nothing.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TrainingRecord {
    /// `f32` or `model`: the DiT's residual stream in training (`model.residual`).
    pub residual: Option<String>,
    /// `objective.action_dropout`: the share of samples trained on the null action condition,
    /// which classifier-free guidance by the actions needs (0 for a run that did not set it).
    pub action_dropout: Option<f64>,
    /// `objective.history_sigma`: the noise level of the history latents in training, which
    /// sampling should match; None where the run kept the default or the weights do not say.
    pub history_sigma: Option<f64>,
    /// `objective.shift`: the flow-matching shift of the training grid, which sampling should
    /// match; None where the run kept the default or the weights do not say.
    pub shift: Option<f64>,
}

pub fn training_record(opened: &OpenedWeights) -> Result<TrainingRecord> {
    if crate::run_dir::is_training_checkpoint(&opened.location) {
        let run = crate::run_info::CheckpointState::read(&opened.location)?.run;
        return Ok(TrainingRecord {
            residual: run.stated_residual(),
            action_dropout: Some(run.record.objective.action_dropout),
            history_sigma: run.record.objective.history_sigma,
            shift: run.stated_shift(),
        });
    }
    let config = opened.repo_config.as_ref();
    let training = config.and_then(|c| c.training.as_ref());
    Ok(TrainingRecord {
        residual: training.and_then(|t| t.get("residual")).and_then(|r| r.as_str()).map(String::from),
        action_dropout: training.and_then(|t| t.get("action_dropout")).and_then(|a| a.as_f64()),
        history_sigma: config.and_then(|c| c.schedule.as_ref()).and_then(|s| s.get("history_sigma")).and_then(|h| h.as_f64()),
        shift: config.and_then(|c| c.schedule.as_ref()).and_then(|s| s.get("shift")).and_then(|h| h.as_f64()),
    })
}

/// Builds the BWM model from weights in any layout ([`open_any`]). `cfg` defaults to the config the
/// files carry; when both exist they must agree. `text_embedding` may be absent.
pub fn load_model(path_or_repo_id: &str, cfg: Option<&ModelConfig>, kind: Kind, device: Device) -> Result<BwmModel> {
    build_model(open_any(path_or_repo_id)?, cfg, kind, device)
}

/// [`load_model`] from weights already opened.
pub fn build_model(opened: OpenedWeights, cfg: Option<&ModelConfig>, kind: Kind, device: Device) -> Result<BwmModel> {
    let (store, cfg, what) = weight_store(opened, cfg, kind, device)?;
    BwmModel::build(&store, &cfg).with_context(|| format!("building the model from {what}"))
}

/// The parameter store [`build_model`] builds from (to add LoRA adapters before the build), the
/// model config that applies and the weights' location for messages.
pub fn weight_store(opened: OpenedWeights, cfg: Option<&ModelConfig>, kind: Kind, device: Device) -> Result<(Rc<ParamStore>, ModelConfig, String)> {
    let cfg = match (cfg, &opened.config) {
        (Some(given), Some(stored)) if opened.repo_config.is_some() && given != stored => bail!(
            "{}: the weights were exported for model config {:?}, not the requested {:?}",
            opened.location.display(),
            stored,
            given
        ),
        (Some(given), _) => given.clone(),
        (None, Some(stored)) => stored.clone(),
        (None, None) => bail!("{}: the files carry no model config; pass one (a preset or run config)", opened.location.display()),
    };
    let what = opened.location.display().to_string();
    check_fits(opened.source.as_ref(), &cfg, &what)?;
    let store: Rc<ParamStore> = ParamStore::from_weights(opened.into_source(), bwm_model::bwm::ACTION_MODE_OPTIONAL, kind, device);
    Ok((store, cfg, what))
}
