//! Conversions between checkpoint layouts: the DiT (+ action encoder) between wan, diffusers and
//! bwm-release (one safetensors file, or a sharded folder), and the Wan2.2 VAE between
//! `Wan2.2_VAE.pth` names (the `.pth` itself or safetensors) and diffusers `AutoencoderKLWan`
//! names, always written as safetensors.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use bwm_model::vae::{diffusers_key, VaeConfig, WanVae};
use bwm_model::weights::WeightSource;
use bwm_model::ModelConfig;
use tch::{Device, Kind};

use crate::atomic_dir::write_dir_atomically;
use crate::export::{write_weights, ExportDtype};
use crate::keymap::{self, DitLayout, TEXT_EMBEDDING_PREFIX};
use crate::open::{check_fits, model_keys, open_any};
use crate::repo::{self, RepoConfig, WeightsInfo, WrittenFile, CONFIG_FILE};
use crate::sources::MappedSource;
use crate::tensor_file::write_tensors;

#[derive(Debug, Clone)]
pub struct ConvertOptions {
    pub to: DitLayout,
    /// `None` keeps each tensor's stored dtype.
    pub dtype: Option<ExportDtype>,
    /// Largest shard of a folder output (default 5 GB).
    pub shard_size: u64,
    pub overwrite: bool,
    /// The model config when the input carries none (needed for a diffusers `transformer/config.json`
    /// and to check the tensors against a model).
    pub model: Option<ModelConfig>,
}

impl Default for ConvertOptions {
    fn default() -> Self {
        Self { to: DitLayout::WanNative, dtype: None, shard_size: crate::export::DEFAULT_SHARD_SIZE, overwrite: false, model: None }
    }
}

#[derive(Debug, Clone)]
pub struct ConvertReport {
    pub from: DitLayout,
    pub to: DitLayout,
    pub tensors: usize,
    pub files: Vec<WrittenFile>,
    /// Keys not written (text_embedding for the bwm-release layout).
    pub dropped: Vec<String>,
}

fn is_single_file(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()) == Some("safetensors")
}

/// Writes `tensors` to the file `out` through a temporary file and a rename.
fn write_file_atomically(out: &Path, overwrite: bool, tensors: &[(String, tch::Tensor)], meta: &BTreeMap<String, String>) -> Result<u64> {
    ensure!(!out.is_dir(), "{} is a folder; name a .safetensors file or a new folder", out.display());
    ensure!(!out.exists() || overwrite, "{} exists; pass --overwrite to replace it", out.display());
    let name = out.file_name().and_then(|n| n.to_str()).with_context(|| format!("{}: not a file name", out.display()))?;
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).with_context(|| format!("creating {}", parent.display()))?;
    let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    if let Err(e) = write_tensors(&tmp, tensors, meta) {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    std::fs::rename(&tmp, out).with_context(|| format!("renaming {} to {}", tmp.display(), out.display()))?;
    Ok(std::fs::metadata(out).map(|m| m.len()).unwrap_or(0))
}

/// Converts DiT weights in any layout (a file, folder or Hub repo id) to `opts.to`: a single
/// `.safetensors` file when `output` ends so (the diffusers layout keeps `action_encoder.*` in it),
/// else a repository folder as `export` writes it (with `config.json` when the model config is
/// known).
pub fn convert_dit(input: &str, output: &Path, opts: &ConvertOptions, progress: &mut dyn FnMut(&str)) -> Result<ConvertReport> {
    let in_path = Path::new(input);
    if in_path.exists() {
        let a = in_path.canonicalize()?;
        let b = output.canonicalize().unwrap_or_else(|_| output.to_path_buf());
        ensure!(a != b && !a.starts_with(&b), "the output {} would replace the input {input}", output.display());
    }
    let opened = open_any(input)?;
    let from = opened.layout;
    let cfg = match (&opts.model, &opened.config) {
        (Some(given), Some(stored)) if opened.repo_config.is_some() && given != stored => {
            bail!("{input} was exported for model config {stored:?}, not the given {given:?}")
        }
        (Some(given), _) => Some(given.clone()),
        (None, stored) => stored.clone(),
    };
    let kinds = opened.kinds.clone();
    let source = opened.into_source();
    let present: BTreeSet<String> = source.names().into_iter().collect();
    let names: Vec<(String, Vec<i64>)> = match &cfg {
        Some(c) => {
            check_fits(source.as_ref(), c, input)?;
            let keys = model_keys(c)?;
            // Only the text embedding may be absent (unused when actions replace the text): a
            // checkpoint of a partly trained set lacks frozen tensors no loader could do without.
            let lacking: Vec<&str> = keys.iter().map(|(n, _)| n.as_str()).filter(|n| !present.contains(*n) && !n.starts_with(TEXT_EMBEDDING_PREFIX)).collect();
            ensure!(
                lacking.is_empty(),
                "{input} lacks {} tensors of the model (e.g. '{}'): a training checkpoint of a partly trained set; `bwm export --checkpoint {input} --base BASE` fills them from the base weights",
                lacking.len(),
                lacking[0]
            );
            keys.into_iter().filter(|(n, _)| present.contains(n)).collect()
        }
        None => present.iter().map(|n| (n.clone(), source.shape(n).unwrap_or_default())).collect(),
    };
    let dropped: Vec<String> = if opts.to == DitLayout::BwmRelease {
        names.iter().filter(|(n, _)| n.starts_with(TEXT_EMBEDDING_PREFIX)).map(|(n, _)| n.clone()).collect()
    } else {
        Vec::new()
    };
    let names: Vec<(String, Vec<i64>)> = names.into_iter().filter(|(n, _)| !dropped.contains(n)).collect();
    ensure!(!names.is_empty(), "{input}: no tensors to convert");
    let dtype = opts.dtype;
    let kind_of = move |n: &str| dtype.map(|d| d.kind()).unwrap_or_else(|| kinds.get(n).copied().unwrap_or(Kind::Float));
    progress(&format!("converting {} tensors from the {from} layout to {} ({})", names.len(), opts.to, source.describe()));

    let files = if is_single_file(output) {
        let mut tensors = Vec::with_capacity(names.len());
        let mut seen = BTreeSet::new();
        for (wan, shape) in &names {
            let key = keymap::to_layout(opts.to, wan)?;
            ensure!(seen.insert(key.clone()), "name collision: two tensors become '{key}'");
            let t = source.load(wan, kind_of(wan), Device::Cpu).with_context(|| format!("reading '{wan}'"))?;
            ensure!(t.size() == *shape, "'{wan}' has shape {:?}, expected {shape:?}", t.size());
            tensors.push((key, keymap::transform_tensor(opts.to, wan, t)));
        }
        let meta = BTreeMap::from([("format".to_string(), "pt".to_string()), ("bwm.layout".to_string(), opts.to.name().to_string())]);
        let bytes = write_file_atomically(output, opts.overwrite, &tensors, &meta)?;
        vec![WrittenFile { path: output.display().to_string(), bytes }]
    } else {
        write_dir_atomically(output, opts.overwrite, |tmp| {
            let (mut files, indexes) =
                write_weights(tmp, source.as_ref(), &names, opts.to, &kind_of, cfg.as_ref(), opts.shard_size, None, progress)?;
            match &cfg {
                Some(c) => {
                    let declared: Vec<String> =
                        model_keys(c)?.into_iter().map(|(n, _)| n).filter(|n| !names.iter().any(|(m, _)| m == n)).collect();
                    let kinds_used: BTreeSet<&'static str> =
                        names.iter().map(|(n, _)| if kind_of(n) == Kind::BFloat16 { "bfloat16" } else { "float32" }).collect();
                    let rc = RepoConfig {
                        model_type: repo::MODEL_TYPE.into(),
                        bwm_format_version: repo::FORMAT_VERSION,
                        architecture: "Wan2.2-TI2V DiT (WanModel) + BWM action encoder (WanVideoActionEncoder, ti2v2 path)".into(),
                        layout: opts.to.name().into(),
                        dit: c.dit.clone(),
                        action: c.action.clone(),
                        weights: WeightsInfo {
                            index_files: indexes,
                            dtype: if kinds_used.len() == 1 { kinds_used.into_iter().next().unwrap_or("float32").into() } else { "mixed".into() },
                            tensors: names.len(),
                            parameters: names.iter().map(|(_, s)| s.iter().product::<i64>()).sum(),
                            action_encoder_prefix: opts.to.action_prefix().into(),
                            missing_reason: (!declared.is_empty()).then(|| "not present in the converted input".to_string()),
                            missing_keys: declared,
                            ema: false,
                        },
                        conditioning: None,
                        action_normalization: None,
                        schedule: None,
                        base_model: None,
                        training: None,
                    };
                    let text = serde_json::to_string_pretty(&rc)?;
                    std::fs::write(tmp.join(CONFIG_FILE), &text).context("writing config.json")?;
                    files.push(WrittenFile { path: CONFIG_FILE.into(), bytes: text.len() as u64 });
                }
                None => progress("no model config known (pass --preset or --config): config.json not written"),
            }
            Ok(files)
        })?
    };
    Ok(ConvertReport { from, to: opts.to, tensors: names.len(), files, dropped })
}

/// VAE key naming.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VaeNaming {
    /// `Wan2.2_VAE.pth` names (what `WanVae::load` reads).
    Wan,
    /// diffusers `AutoencoderKLWan` names.
    Diffusers,
}

impl std::str::FromStr for VaeNaming {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "wan" | "wan-native" | "pth" => VaeNaming::Wan,
            "diffusers" => VaeNaming::Diffusers,
            other => bail!("unknown VAE naming '{other}' (allowed: wan, diffusers)"),
        })
    }
}

/// The stored dtype of each tensor of a `.pth` or safetensors file.
fn stored_kinds(path: &Path) -> Result<BTreeMap<String, Kind>> {
    Ok(match path.extension().and_then(|e| e.to_str()) {
        Some("pth") | Some("pt") | Some("bin") => {
            bwm_model::pth::open(path)?.tensors().iter().map(|(k, t)| (k.clone(), t.kind())).collect()
        }
        _ => {
            let st = bwm_model::weights::SafetensorsSource::open(path)?;
            st.names().into_iter().map(|n| (n.clone(), st.kind(&n).unwrap_or(Kind::Float))).collect()
        }
    })
}

/// Every key of the Wan2.2 VAE (the names do not depend on the widths).
fn wan_vae_keys() -> Result<Vec<String>> {
    let store = bwm_model::ParamStore::shapes_only(Kind::Float);
    WanVae::new(&store.root(), &VaeConfig::wan22())?;
    Ok(store.named_parameters().into_iter().map(|(n, _)| n).collect())
}

#[derive(Debug, Clone)]
pub struct VaeConvertReport {
    pub from: VaeNaming,
    pub to: VaeNaming,
    pub tensors: usize,
    pub bytes: u64,
}

/// Converts a Wan2.2 VAE (`.pth` or safetensors, Wan or diffusers names; the naming is detected)
/// into one safetensors file with `to` names. `dtype` `None` keeps the stored dtypes.
pub fn convert_vae(input: &Path, output: &Path, to: VaeNaming, dtype: Option<ExportDtype>, overwrite: bool) -> Result<VaeConvertReport> {
    ensure!(is_single_file(output), "{}: the VAE is written as one .safetensors file", output.display());
    let source = bwm_model::weight_file::open_source(input)?;
    let names = source.names();
    let wan_keys = wan_vae_keys()?;
    let to_diffusers: BTreeMap<String, String> = wan_keys.iter().map(|k| (k.clone(), diffusers_key(k))).collect();
    let to_wan: BTreeMap<String, String> = to_diffusers.iter().map(|(w, d)| (d.clone(), w.clone())).collect();
    let from = if names.iter().any(|n| to_wan.contains_key(n) && !to_diffusers.contains_key(n)) {
        VaeNaming::Diffusers
    } else {
        VaeNaming::Wan
    };
    let mut pairs = Vec::new();
    for n in &names {
        if n == "latents_mean" || n == "latents_std" {
            pairs.push((n.clone(), n.clone()));
            continue;
        }
        let wan = match from {
            VaeNaming::Wan => to_diffusers.contains_key(n).then(|| n.clone()),
            VaeNaming::Diffusers => to_wan.get(n).cloned(),
        };
        let wan = wan.with_context(|| format!("{}: '{n}' is not a Wan2.2 VAE key in the {from:?} naming", input.display()))?;
        let out = match to {
            VaeNaming::Wan => wan,
            VaeNaming::Diffusers => to_diffusers[&wan].clone(),
        };
        pairs.push((out, n.clone()));
    }
    let kinds = stored_kinds(input)?;
    let originals: BTreeMap<String, String> = pairs.iter().cloned().collect();
    let mapped = MappedSource::new(source, pairs)?;
    let mut tensors = Vec::new();
    for name in mapped.names() {
        let kind = match dtype {
            Some(d) => d.kind(),
            None => originals.get(&name).and_then(|o| kinds.get(o)).copied().unwrap_or(Kind::Float),
        };
        tensors.push((name.clone(), mapped.load(&name, kind, Device::Cpu)?));
    }
    let meta = BTreeMap::from([("format".to_string(), "pt".to_string())]);
    let n = tensors.len();
    let bytes = write_file_atomically(output, overwrite, &tensors, &meta)?;
    Ok(VaeConvertReport { from, to, tensors: n, bytes })
}
