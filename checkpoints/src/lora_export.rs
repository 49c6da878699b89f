//! A LoRA checkpoint's adapters alone, as diffusers and PEFT read them for
//! `WanTransformer3DModel` (`bwm export` of a LoRA checkpoint without `--merge-lora`), and the file
//! name they go in, which `open` reads back.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use bwm_model::weights::{SafetensorsSource, WeightSource};
use tch::{Device, Kind};

use crate::atomic_dir::write_dir_atomically;
use crate::keymap::{self, DitLayout};
use crate::repo::ExportDtype;
use crate::run_info::CheckpointState;
use crate::tensor_file::write_tensors;

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
        write_tensors(&tmp.join(LORA_WEIGHTS_FILE), &tensors, &BTreeMap::new())?;
        std::fs::write(tmp.join("adapter_config.json"), serde_json::to_string_pretty(&config)? + "\n").context("writing adapter_config.json")
    })?;
    Ok(AdapterExport { out: out.to_path_buf(), layers: modules.len(), parameters, left_out })
}
