//! The model-repository folder format shared by `export` (writing) and `open` (reading): file
//! names per layout, the top-level `config.json`, sharded safetensors with their
//! `*.safetensors.index.json`, and the dtype they are stored in (`ExportDtype`).
//!
//! ```text
//! wan / bwm-release                      diffusers
//! config.json        (BWM config)        config.json                 (BWM config)
//! model-00001-of-0000N.safetensors       transformer/config.json     (WanTransformer3DModel)
//! model.safetensors.index.json           transformer/diffusion_pytorch_model-0000i-of-0000N.safetensors
//! action_stats.json                      transformer/diffusion_pytorch_model.safetensors.index.json
//! README.md                              action_encoder/config.json
//!                                        action_encoder/model-00001-of-00001.safetensors (keys without
//!                                        action_encoder/model.safetensors.index.json      the prefix)
//!                                        action_stats.json, README.md
//! ```
//! In the wan and bwm-release layouts the action encoder sits in the same shards as the DiT
//! (under `action_encoder.` / `pipe.action_encoder.`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use bwm_model::weights::WeightSource;
use bwm_model::{ActionConfig, DitConfig, ModelConfig};
use serde::{Deserialize, Serialize};
use tch::{Device, Kind};

use crate::keymap::{self, DitLayout};
use crate::tensor_file::write_tensors;

pub const FORMAT_VERSION: u32 = 1;
pub const CONFIG_FILE: &str = "config.json";
pub const README_FILE: &str = "README.md";
pub const ACTION_STATS_FILE: &str = "action_stats.json";
pub const TRANSFORMER_DIR: &str = "transformer";
pub const ACTION_ENCODER_DIR: &str = "action_encoder";
/// Shard base name of the wan / bwm-release layouts and of the diffusers action encoder.
pub const MODEL_BASE: &str = "model";
/// Shard base name diffusers' `from_pretrained` looks for.
pub const DIFFUSERS_BASE: &str = "diffusion_pytorch_model";
pub const MODEL_TYPE: &str = "bwm-world-model";

/// What `config.json` says about the weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WeightsInfo {
    /// Shard index files, relative to the repository root.
    pub index_files: Vec<String>,
    /// `bfloat16` or `float32` (or `mixed` for a dtype-preserving conversion).
    pub dtype: String,
    pub tensors: usize,
    pub parameters: i64,
    /// Where the action encoder's keys live in the files.
    pub action_encoder_prefix: String,
    /// Wan-native keys of the model deliberately absent from the files.
    #[serde(default)]
    pub missing_keys: Vec<String>,
    #[serde(default)]
    pub missing_reason: Option<String>,
    /// Whether these are the EMA weights of the run.
    #[serde(default)]
    pub ema: bool,
}

/// The top-level `config.json` of an exported repository.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RepoConfig {
    pub model_type: String,
    pub bwm_format_version: u32,
    pub architecture: String,
    /// `wan`, `diffusers` or `bwm-release`.
    pub layout: String,
    pub dit: DitConfig,
    pub action: ActionConfig,
    pub weights: WeightsInfo,
    /// Clip structure the model was trained on: frames, condition latents, resolution, fps.
    #[serde(default)]
    pub conditioning: Option<serde_json::Value>,
    /// How raw actions become model inputs (formula, statistics file, group).
    #[serde(default)]
    pub action_normalization: Option<serde_json::Value>,
    /// Flow-matching settings used in training.
    #[serde(default)]
    pub schedule: Option<serde_json::Value>,
    #[serde(default)]
    pub base_model: Option<String>,
    #[serde(default)]
    pub training: Option<serde_json::Value>,
}

impl RepoConfig {
    pub fn model_config(&self) -> ModelConfig {
        ModelConfig { dit: self.dit.clone(), action: self.action.clone() }
    }

    pub fn layout(&self) -> Result<DitLayout> {
        self.layout.parse()
    }

    /// Reads `dir/config.json` when it is a BWM repository config; `Ok(None)` when the file is
    /// absent or some other model's config.
    pub fn read(dir: &Path) -> Result<Option<Self>> {
        let path = dir.join(CONFIG_FILE);
        let Ok(text) = std::fs::read_to_string(&path) else { return Ok(None) };
        let value: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
        if value.get("bwm_format_version").is_none() {
            return Ok(None);
        }
        let cfg: Self = serde_json::from_value(value).with_context(|| format!("{}: not a valid BWM repository config", path.display()))?;
        ensure!(
            cfg.bwm_format_version <= FORMAT_VERSION,
            "{}: format version {} is newer than this build understands ({FORMAT_VERSION})",
            path.display(),
            cfg.bwm_format_version
        );
        Ok(Some(cfg))
    }
}

/// The diffusers `WanTransformer3DModel` config of a DiT (`transformer/config.json`).
pub fn diffusers_transformer_config(dit: &DitConfig) -> serde_json::Value {
    serde_json::json!({
        "_class_name": "WanTransformer3DModel",
        "_diffusers_version": "0.35.0",
        "added_kv_proj_dim": null,
        "attention_head_dim": dit.head_dim(),
        "cross_attn_norm": true,
        "eps": dit.eps,
        "ffn_dim": dit.ffn_dim,
        "freq_dim": dit.freq_dim,
        "image_dim": null,
        "in_channels": dit.in_dim,
        "num_attention_heads": dit.num_heads,
        "num_layers": dit.num_layers,
        "out_channels": dit.out_dim,
        "patch_size": dit.patch_size,
        "pos_embed_seq_len": null,
        "qk_norm": "rms_norm_across_heads",
        "rope_max_seq_len": 1024,
        "text_dim": dit.text_dim,
    })
}

/// A DiT config from a diffusers `WanTransformer3DModel` config (or an official `WanModel`
/// `config.json`), when it has the fields.
pub fn dit_config_from_foreign(cfg: &serde_json::Value) -> Option<DitConfig> {
    let i = |k: &str| cfg.get(k).and_then(|v| v.as_i64());
    let f = |k: &str| cfg.get(k).and_then(|v| v.as_f64());
    let class = cfg.get("_class_name").and_then(|c| c.as_str()).unwrap_or_default();
    let default = DitConfig::wan22_ti2v_5b();
    let patch = cfg
        .get("patch_size")
        .and_then(|p| p.as_array())
        .and_then(|a| (a.len() == 3).then(|| [a[0].as_i64(), a[1].as_i64(), a[2].as_i64()]))
        .and_then(|[a, b, c]| Some([a?, b?, c?]))
        .unwrap_or(default.patch_size);
    let dit = match class {
        "WanTransformer3DModel" => {
            let heads = i("num_attention_heads")?;
            DitConfig {
                dim: heads * i("attention_head_dim")?,
                in_dim: i("in_channels")?,
                out_dim: i("out_channels")?,
                ffn_dim: i("ffn_dim")?,
                freq_dim: i("freq_dim").unwrap_or(default.freq_dim),
                text_dim: i("text_dim").unwrap_or(default.text_dim),
                num_heads: heads,
                num_layers: i("num_layers")?,
                eps: f("eps").unwrap_or(default.eps),
                patch_size: patch,
                rope_theta: default.rope_theta,
            }
        }
        "WanModel" => DitConfig {
            dim: i("dim")?,
            in_dim: i("in_dim")?,
            out_dim: i("out_dim")?,
            ffn_dim: i("ffn_dim")?,
            freq_dim: i("freq_dim").unwrap_or(default.freq_dim),
            text_dim: i("text_dim").unwrap_or(default.text_dim),
            num_heads: i("num_heads")?,
            num_layers: i("num_layers")?,
            eps: f("eps").unwrap_or(default.eps),
            patch_size: patch,
            rope_theta: default.rope_theta,
        },
        _ => return None,
    };
    dit.validate().ok().map(|_| dit)
}

/// One tensor to write: its Wan-native name (to read it from the source), its name in the file,
/// its shape and the dtype to store.
#[derive(Debug, Clone)]
pub struct Planned {
    pub wan: String,
    pub file_key: String,
    pub shape: Vec<i64>,
    pub kind: Kind,
}

impl Planned {
    pub fn bytes(&self) -> u64 {
        self.shape.iter().product::<i64>().max(0) as u64 * self.kind.elt_size_in_bytes() as u64
    }
}

/// Greedy shards in order: a new shard starts when the next tensor would push the current one
/// past `max_bytes` (a tensor larger than that gets a shard of its own).
pub fn plan_shards(items: &[Planned], max_bytes: u64) -> Vec<Vec<usize>> {
    let mut shards: Vec<Vec<usize>> = Vec::new();
    let mut size = 0u64;
    for (i, it) in items.iter().enumerate() {
        let b = it.bytes();
        match shards.last_mut() {
            Some(cur) if size + b <= max_bytes || cur.is_empty() => {
                cur.push(i);
                size += b;
            }
            _ => {
                shards.push(vec![i]);
                size = b;
            }
        }
    }
    shards
}

/// A file written, relative to the repository root, with its size.
#[derive(Debug, Clone, PartialEq)]
pub struct WrittenFile {
    pub path: String,
    pub bytes: u64,
}

/// Writes `items` as `{base}-0000i-of-0000N.safetensors` plus `{base}.safetensors.index.json` in
/// `root/sub` (always with an index, also for one shard). Tensors are read from `source` (Wan-native
/// names) one shard at a time; `fail_after` stops after that many shards (tests of interrupted
/// exports). Returns the files written, the index last.
#[allow(clippy::too_many_arguments)]
pub fn write_sharded(
    root: &Path,
    sub: &str,
    base: &str,
    items: &[Planned],
    source: &dyn WeightSource,
    layout: DitLayout,
    max_bytes: u64,
    fail_after: Option<usize>,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<WrittenFile>> {
    ensure!(!items.is_empty(), "nothing to write under {}", if sub.is_empty() { "the repository root" } else { sub });
    let dir = if sub.is_empty() { root.to_path_buf() } else { root.join(sub) };
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let rel = |name: &str| if sub.is_empty() { name.to_string() } else { format!("{sub}/{name}") };
    let shards = plan_shards(items, max_bytes);
    let n = shards.len();
    let mut weight_map = serde_json::Map::new();
    let mut written = Vec::new();
    let mut total = 0u64;
    let meta = BTreeMap::from([("format".to_string(), "pt".to_string())]);
    for (s, members) in shards.iter().enumerate() {
        if fail_after.is_some_and(|f| s >= f) {
            bail!("export interrupted after {s} of {n} shards (fault injection)");
        }
        let file = format!("{base}-{:05}-of-{n:05}.safetensors", s + 1);
        let mut tensors = Vec::with_capacity(members.len());
        let mut bytes = 0u64;
        for &i in members {
            let it = &items[i];
            let t = source
                .load(&it.wan, it.kind, Device::Cpu)
                .with_context(|| format!("reading '{}' from {}", it.wan, source.describe()))?;
            ensure!(t.size() == it.shape, "'{}' has shape {:?} in {}, expected {:?}", it.wan, t.size(), source.describe(), it.shape);
            tensors.push((it.file_key.clone(), keymap::transform_tensor(layout, &it.wan, t)));
            weight_map.insert(it.file_key.clone(), serde_json::Value::String(file.clone()));
            bytes += it.bytes();
        }
        let path = dir.join(&file);
        write_tensors(&path, &tensors, &meta)?;
        drop(tensors);
        total += bytes;
        let size = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(bytes);
        progress(&format!("wrote {} ({} tensors, {})", rel(&file), members.len(), human_bytes(size)));
        written.push(WrittenFile { path: rel(&file), bytes: size });
    }
    let index = serde_json::json!({ "metadata": { "total_size": total }, "weight_map": weight_map });
    let index_name = format!("{base}.safetensors.index.json");
    let index_path = dir.join(&index_name);
    let text = serde_json::to_string_pretty(&index)?;
    std::fs::write(&index_path, &text).with_context(|| format!("writing {}", index_path.display()))?;
    written.push(WrittenFile { path: rel(&index_name), bytes: text.len() as u64 });
    Ok(written)
}

/// Every shard a `*.safetensors.index.json` lists, checked to exist: an error names the first
/// absent one (a partial download or export).
pub fn index_shards(index: &Path) -> Result<Vec<PathBuf>> {
    let text = std::fs::read_to_string(index).with_context(|| format!("reading {}", index.display()))?;
    let value: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", index.display()))?;
    let map = value
        .get("weight_map")
        .and_then(|m| m.as_object())
        .with_context(|| format!("{}: no \"weight_map\" object", index.display()))?;
    let dir = index.parent().unwrap_or(Path::new("."));
    let mut shards: Vec<PathBuf> = Vec::new();
    for file in map.values() {
        let file = file.as_str().with_context(|| format!("{}: a weight_map value is not a file name", index.display()))?;
        let path = dir.join(file);
        if !shards.contains(&path) {
            shards.push(path);
        }
    }
    for s in &shards {
        ensure!(
            s.is_file(),
            "{} lists {} but that shard is missing: a partial download or an interrupted export",
            index.display(),
            s.display()
        );
    }
    Ok(shards)
}

pub fn human_bytes(b: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = b as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{b} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}

/// Parses a byte size: `5GB`, `500MB`, `10MiB`, `1e9`, `123` (decimal units as the Hub uses them:
/// GB = 10^9; binary ones with `iB`).
pub fn parse_size(s: &str) -> Result<u64> {
    let t = s.trim();
    // A bare number (`1e9` too: its `e` is an exponent, not a unit) is bytes.
    let split = if t.parse::<f64>().is_ok() { t.len() } else { t.find(|c: char| c.is_ascii_alphabetic()).unwrap_or(t.len()) };
    let (num, unit) = t.split_at(split);
    let value: f64 = num.trim().parse().with_context(|| format!("'{s}' is not a size (e.g. 5GB, 500MB, 10MiB)"))?;
    let mult: f64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "kb" | "k" => 1e3,
        "mb" | "m" => 1e6,
        "gb" | "g" => 1e9,
        "tb" | "t" => 1e12,
        "kib" => 1024.0,
        "mib" => 1024.0 * 1024.0,
        "gib" => 1024.0 * 1024.0 * 1024.0,
        "tib" => 1024.0f64.powi(4),
        other => bail!("'{s}': unknown size unit '{other}' (B, KB, MB, GB, TB, KiB, MiB, GiB, TiB)"),
    };
    let bytes = value * mult;
    ensure!(bytes.is_finite() && bytes >= 1.0, "'{s}' is not a positive size");
    Ok(bytes as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_and_shard_plans() {
        assert_eq!(parse_size("5GB").unwrap(), 5_000_000_000);
        assert_eq!(parse_size("10MiB").unwrap(), 10 * 1024 * 1024);
        assert_eq!(parse_size("1234").unwrap(), 1234);
        assert_eq!(parse_size("1e9").unwrap(), 1_000_000_000);
        assert!(parse_size("5 parsecs").is_err());
        assert!(parse_size("0").is_err());
        let p = |n: i64| Planned { wan: String::new(), file_key: String::new(), shape: vec![n], kind: Kind::Float };
        let items = vec![p(10), p(10), p(30), p(5), p(1)];
        assert_eq!(plan_shards(&items, 80), vec![vec![0, 1], vec![2], vec![3, 4]]);
        assert_eq!(plan_shards(&items, 1), vec![vec![0], vec![1], vec![2], vec![3], vec![4]]);
        assert_eq!(plan_shards(&items, 10_000), vec![vec![0, 1, 2, 3, 4]]);
    }

    #[test]
    fn foreign_configs() {
        let d = serde_json::json!({"_class_name": "WanModel", "dim": 3072, "eps": 1e-06, "ffn_dim": 14336, "freq_dim": 256,
            "in_dim": 48, "model_type": "ti2v", "num_heads": 24, "num_layers": 30, "out_dim": 48, "text_len": 512});
        assert_eq!(dit_config_from_foreign(&d).unwrap(), DitConfig::wan22_ti2v_5b());
        let t = diffusers_transformer_config(&DitConfig::tiny());
        assert_eq!(dit_config_from_foreign(&t).unwrap(), DitConfig::tiny());
        assert!(dit_config_from_foreign(&serde_json::json!({"_class_name": "Other"})).is_none());
    }
}

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
