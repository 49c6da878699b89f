//! Helpers shared by the checkpoint interchange tests.
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use bwm_checkpoints::write_tensors;
use bwm_model::{BwmModel, ModelConfig};
use tch::{Device, Kind, Tensor};

#[allow(unused_imports)]
pub use bwm_testdir::tmp_dir;

/// A run config TOML for `preset` (with an optional `[model.dit]` override block).
pub fn run_toml(name: &str, preset: &str, dit_override: Option<&str>, cache: &Path) -> String {
    let mut s = format!(
        "[run]\nname = \"{name}\"\nseed = 5\n\n[model]\npreset = \"{preset}\"\ndtype = \"f32\"\n\n[data]\nlatent_cache = \"{}\"\nholdout_clips = 1\n\n[optim]\nlr = 0.0001\nema_decay = 0.99\n\n[train]\nsteps = 10\nmicro_batch = 2\ngrad_accum = 1\n",
        cache.display()
    );
    if let Some(d) = dit_override {
        s.push_str(&format!("\n[model.dit]\n{d}\n"));
    }
    s
}

/// The model's parameters by name.
pub fn params(model: &BwmModel) -> BTreeMap<String, Tensor> {
    model.store.named_parameters().into_iter().map(|(n, t)| (n, t.detach().copy())).collect()
}

/// A training run folder as the trainer writes it: `run/checkpoints/step-00000010/` with
/// model.safetensors (every parameter but text_embedding, the trainer's default frozen set),
/// optimizer.safetensors (masters, moments, `ema.*` = 0.5 x the weights), config.toml and
/// state.json; `run/metrics.jsonl`; a latent cache index. Returns the checkpoint folder.
pub fn fake_run(root: &Path, model: &BwmModel, toml_for: &dyn Fn(&Path) -> String) -> PathBuf {
    let run = root.join("run");
    let cache = root.join("cache");
    std::fs::create_dir_all(&cache).unwrap();
    std::fs::write(
        cache.join("index.json"),
        r#"{"version": 1, "latent_shape": [48, 5, 4, 6], "action_dim": 14, "pixel_frames": 17, "history_frames": 8, "future_frames": 8, "resolution": [96, 64], "fps": 30.0, "vae": "test", "has_frames": false, "clips": [{"file": "a", "episode": 0, "frames": []}, {"file": "b", "episode": 1, "frames": []}]}"#,
    )
    .unwrap();
    let ckpt = run.join("checkpoints").join("step-00000010");
    std::fs::create_dir_all(&ckpt).unwrap();
    let trained: Vec<(String, Tensor)> = params(model).into_iter().filter(|(n, _)| !n.starts_with("text_embedding.")).collect();
    write_tensors(&ckpt.join("model.safetensors"), &trained, &BTreeMap::from([("format".to_string(), "pt".to_string())])).unwrap();
    let mut opt = Vec::new();
    for (n, t) in &trained {
        opt.push((format!("master.{n}"), t.to_kind(Kind::Float)));
        opt.push((format!("exp_avg.{n}"), t.zeros_like()));
        opt.push((format!("exp_avg_sq.{n}"), t.zeros_like()));
        opt.push((format!("ema.{n}"), t.to_kind(Kind::Float) * 0.5));
    }
    write_tensors(&ckpt.join("optimizer.safetensors"), &opt, &BTreeMap::new()).unwrap();
    let toml = toml_for(&cache);
    std::fs::write(ckpt.join("config.toml"), &toml).unwrap();
    let state = serde_json::json!({
        "step": 10, "optimizer_step": 10, "samples_seen": 20, "nonfinite_in_row": 0, "nonfinite_total": 0, "world_size": 1,
        "trainable": trained.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>(), "config": toml,
    });
    std::fs::write(ckpt.join("state.json"), serde_json::to_string_pretty(&state).unwrap()).unwrap();
    let mut metrics = String::new();
    for step in 1..=10u64 {
        metrics.push_str(&format!("{{\"step\": {step}, \"loss\": {}, \"samples_per_s\": 3.5}}\n", 1.0 / step as f64));
    }
    std::fs::write(run.join("metrics.jsonl"), metrics).unwrap();
    ckpt
}

pub fn tiny() -> ModelConfig {
    ModelConfig::preset("tiny").unwrap()
}

pub fn random_model(cfg: &ModelConfig, seed: i64) -> BwmModel {
    BwmModel::random(cfg, Kind::Float, Device::Cpu, seed).unwrap()
}

/// Asserts `got` holds exactly `want` (same names, bit-identical values in `kind`).
pub fn assert_same(got: &BTreeMap<String, Tensor>, want: &BTreeMap<String, Tensor>, kind: Kind, what: &str) {
    let a: Vec<&String> = got.keys().collect();
    let b: Vec<&String> = want.keys().collect();
    assert_eq!(a, b, "{what}: key sets differ");
    for (n, t) in want {
        let g = &got[n];
        assert_eq!(g.size(), t.size(), "{what}: {n} shape");
        assert!(g.to_kind(kind).equal(&t.to_kind(kind)), "{what}: {n} differs");
    }
}

/// Every tensor of an opened source, in its stored dtype.
pub fn read_all(opened: &bwm_checkpoints::OpenedWeights) -> BTreeMap<String, Tensor> {
    opened
        .source
        .names()
        .into_iter()
        .map(|n| {
            let k = opened.kinds.get(&n).copied().unwrap_or(Kind::Float);
            let t = opened.source.load(&n, k, Device::Cpu).unwrap();
            (n, t)
        })
        .collect()
}
