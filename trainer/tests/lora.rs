//! LoRA training on a synthetic latent cache, CPU f32: only the adapters train, the model starts
//! as its base computes, the base stays untouched, the loss falls, and resume is exact (with
//! adapter dropout too).

mod common;

use std::collections::BTreeMap;

use bwm_trainer::{Resume, Trainer};
use common::*;
use tch::{Kind, Tensor};

const LORA: &str = r#"lora = { rank = 4, alpha = 8.0, targets = ["blocks.*.self_attn.*", "blocks.*.ffn.*"] }"#;

fn all_params(t: &Trainer) -> BTreeMap<String, Tensor> {
    t.model.store.named_parameters().into_iter().map(|(n, p)| (n, p.detach().copy())).collect()
}

#[test]
fn only_the_adapters_train_from_the_base_model() {
    let dir = tmp_dir("lora-train");
    let cache = write_cache(&dir.join("cache"), 1, 11);
    let base = trainer(config(&cache, &dir.join("base"), "[train]\nsteps = 80"), Resume::No).unwrap();
    let extra = format!("[model]\n{LORA}\n[train]\nsteps = 150\n[optim]\nlr = 1e-2\ngrad_clip = 1.0");
    let mut t = trainer(config(&cache, &dir.join("lora"), &extra), Resume::No).unwrap();

    // The adapters sit on the 2 blocks' q, k, v, o and both FFN layers: 12 layers, A and B each.
    let trained: Vec<&str> = t.opt.params.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(trained.len(), 24, "{trained:?}");
    assert!(trained.iter().all(|n| bwm_model::lora::is_adapter_key(n)), "{trained:?}");
    assert!(trained.contains(&"blocks.1.self_attn.q.lora_A.weight") && trained.contains(&"blocks.0.ffn.2.lora_B.weight"), "{trained:?}");
    assert!(!trained.iter().any(|n| n.contains("cross_attn")), "cross-attention is not targeted: {trained:?}");

    // The base weights are those of the same run without adapters (same seed: the adapters' own
    // draws do not shift the others), and B = 0 makes the model compute what the base does.
    let before = all_params(&t);
    for (n, w) in base.model.store.named_parameters() {
        assert!(before[&n].equal(&w), "{n} differs from the model without adapters");
    }
    assert_eq!(before.len(), base.model.store.named_parameters().len() + 24);
    let base_loss = eval_loss(&base);
    let start_loss = eval_loss(&t);
    assert_eq!(base_loss, start_loss, "fresh adapters change the model's output");

    t.run().unwrap();
    let after = all_params(&t);
    for (n, w) in &before {
        if !bwm_model::lora::is_adapter_key(n) {
            assert!(after[n].equal(w), "frozen base tensor {n} changed");
        }
    }
    assert!(after.iter().any(|(n, w)| n.ends_with("lora_B.weight") && w.abs().sum(Kind::Float).double_value(&[]) > 0.0));
    let end_loss = eval_loss(&t);
    // Rank-4 adapters on a random 2-block base fit one clip more slowly than full training (2.05
    // -> 1.66 here, against a halving in training.rs), but they fit it.
    assert!(end_loss < 0.85 * start_loss, "loss on fixed draws went from {start_loss} to {end_loss}");
    // Only the adapters have optimizer state.
    let adapter_elements: i64 = t.opt.params.iter().map(|p| p.param.numel() as i64).sum();
    assert_eq!(t.opt.master.numel() as i64, adapter_elements);
}

#[test]
fn lora_resume_continues_exactly_with_dropout() {
    // Dropout draws from libtorch's generator: hold the tests' generator lock for the whole test
    // so that no other test's model initialization draws between the steps.
    let _guard = rng_lock();
    let dir = tmp_dir("lora-resume");
    let cache = write_cache_unlocked(&dir.join("cache"), 3, 12);
    let lora = r#"lora = { rank = 2, dropout = 0.2, targets = ["blocks.*.self_attn.q", "blocks.*.ffn.0"] }"#;
    let cfg = |out: &str, steps: u64| config(&cache, &dir.join(out), &format!("[model]\n{lora}\n[train]\nsteps = {steps}\nrecompute = false\n[checkpoint]\nevery = 2"));
    let mut straight = Trainer::new(cfg("straight", 5), Resume::No).unwrap();
    straight.run().unwrap();
    let mut a = Trainer::new(cfg("split", 2), Resume::No).unwrap();
    a.run().unwrap();
    let first: Vec<f64> = a.history.iter().map(|m| m.loss).collect();
    drop(a);
    let mut b = Trainer::new(cfg("split", 5), Resume::Auto).unwrap();
    assert_eq!(b.state.step, 2);
    b.run().unwrap();
    let split: Vec<f64> = first.into_iter().chain(b.history.iter().map(|m| m.loss)).collect();
    let whole: Vec<f64> = straight.history.iter().map(|m| m.loss).collect();
    assert_eq!(whole, split, "loss curves differ");
    assert!(straight.opt.master.equal(&b.opt.master), "adapter master weights differ");
    assert!(straight.opt.exp_avg_sq.equal(&b.opt.exp_avg_sq), "optimizer moments differ");
    // The checkpoint holds the adapters only (the base comes from model.init).
    let latest = b.checkpoints.latest().unwrap().unwrap().path;
    let held = bwm_checkpoints::run_info::CheckpointState::read(&latest).unwrap();
    assert!(held.trainable.iter().all(|n| bwm_model::lora::is_adapter_key(n)), "{:?}", held.trainable);
}

#[test]
fn lora_config_errors_name_the_key() {
    let dir = tmp_dir("lora-config");
    let cache = write_cache(&dir.join("cache"), 1, 13);
    let text = |lora: &str, recompute: &str| try_config(&cache, &dir.join("run"), &format!("[model]\nlora = {lora}\n[train]\nrecompute = {recompute}"));
    let e = format!("{:#}", text(r#"{ rank = 0, targets = ["blocks.*.ffn.*"] }"#, "false").unwrap_err());
    assert!(e.contains("lora.rank"), "{e}");
    let e = format!("{:#}", text(r#"{ rank = 4, targets = [] }"#, "false").unwrap_err());
    assert!(e.contains("lora.targets"), "{e}");
    let e = format!("{:#}", text(r#"{ rank = 4, dropout = 0.1, targets = ["blocks.*.ffn.*"] }"#, "true").unwrap_err());
    assert!(e.contains("model.lora.dropout") && e.contains("recompute"), "{e}");
    let e = format!("{:#}", text(r#"{ rank = 4, targets = ["blocks.*.ffn.*"], size = 3 }"#, "false").unwrap_err());
    assert!(e.contains("size"), "{e}");
    // Targets that match no linear layer leave nothing to train.
    let cfg = text(r#"{ rank = 4, targets = ["no_such_layer"] }"#, "false").unwrap();
    let e = format!("{:#}", trainer(cfg, Resume::No).err().unwrap());
    assert!(e.contains("selects no parameter"), "{e}");
}

#[test]
fn adapters_start_fresh_on_a_base_checkpoint() {
    let dir = tmp_dir("lora-base");
    let cache = write_cache(&dir.join("cache"), 1, 14);
    let base = trainer(config(&cache, &dir.join("base"), ""), Resume::No).unwrap();
    let params = base.model.store.named_parameters();
    let file = dir.join("base.safetensors");
    Tensor::write_safetensors(&params, &file).unwrap();
    let extra = format!("[model]\n{LORA}\ninit = {{ from = \"bwm-checkpoint\", path = \"{}\" }}", file.display());
    let t = trainer(config(&cache, &dir.join("lora"), &extra), Resume::No).unwrap();
    let loaded = all_params(&t);
    for (n, w) in &params {
        assert!(loaded[n].equal(w), "{n} not loaded from the base");
    }
    assert_eq!(eval_loss(&t), eval_loss(&base), "fresh adapters change the base model's output");
}

#[test]
fn a_lora_checkpoint_loads_merged_and_exports_merged() {
    let dir = tmp_dir("lora-merge");
    let cache = write_cache(&dir.join("cache"), 1, 15);
    let extra = format!("[model]\n{LORA}\n[train]\nsteps = 20\n[optim]\nlr = 1e-2");
    let mut t = trainer(config(&cache, &dir.join("run"), &extra), Resume::No).unwrap();
    t.run().unwrap();
    let trained_loss = eval_loss(&t);
    let ckpt = t.checkpoints.latest().unwrap().unwrap().path;
    let x = |m: &bwm_model::BwmModel| {
        let clip = t.cache.load(0, tch::Device::Cpu).unwrap();
        let d = t.objective.draw(10_000, &t.cache.index.latent_shape);
        let p = t.objective.prepare(&clip.latents.unsqueeze(0), &d.noise.unsqueeze(0), &d.history_noise.unsqueeze(0), &[d.timestep_index]).unwrap();
        tch::no_grad(|| m.forward(&p.input, &p.frame_timesteps, &clip.actions.unsqueeze(0))).unwrap()
    };
    let reference = x(&t.model);

    // The checkpoint holds the adapters only; opened (as rollout, evaluate and serve open it),
    // they are merged into the run's random base weights, drawn again from its seed.
    // Drawing the base again uses libtorch's generator: under the tests' lock (the dropout test
    // draws from it too).
    let merged = {
        let _guard = rng_lock();
        bwm_checkpoints::open::load_model(ckpt.to_str().unwrap(), None, Kind::Float, tch::Device::Cpu).unwrap()
    };
    assert!(merged.store.named_parameters().iter().all(|(n, _)| !bwm_model::lora::is_adapter_key(n)));
    let d = max_abs_diff(&x(&merged), &reference);
    assert!(d < 1e-4, "merged model differs from base + adapters by {d}");
    assert_ne!(trained_loss, 0.0);

    // `bwm export --merge-lora` writes the same merged weights; without it the export refuses.
    let out = dir.join("export");
    let opts = bwm_checkpoints::export::ExportOptions { dtype: bwm_checkpoints::export::ExportDtype::F32, ..Default::default() };
    let e = format!("{:#}", bwm_checkpoints::export::export(ckpt.to_str().unwrap(), &out, &opts, &mut |_| {}).unwrap_err());
    assert!(e.contains("--merge-lora"), "{e}");
    let opts = bwm_checkpoints::export::ExportOptions { merge_lora: true, ..opts };
    {
        let _guard = rng_lock();
        bwm_checkpoints::export::export(ckpt.to_str().unwrap(), &out, &opts, &mut |_| {}).unwrap();
    }
    let exported = bwm_checkpoints::open::load_model(out.to_str().unwrap(), None, Kind::Float, tch::Device::Cpu).unwrap();
    let merged_params: BTreeMap<String, Tensor> = merged.store.named_parameters().into_iter().collect();
    for (n, w) in exported.store.named_parameters() {
        assert!(w.equal(&merged_params[&n]), "{n}: the export differs from the merged checkpoint");
    }

    // A checkpoint of a run without adapters is no LoRA checkpoint.
    let mut full = trainer(config(&cache, &dir.join("full"), "[train]\nsteps = 1"), Resume::No).unwrap();
    full.run().unwrap();
    let full_ckpt = full.checkpoints.latest().unwrap().unwrap().path;
    let e = format!("{:#}", bwm_checkpoints::export::export(full_ckpt.to_str().unwrap(), &dir.join("export2"), &opts, &mut |_| {}).unwrap_err());
    assert!(e.contains("not a LoRA checkpoint"), "{e}");
}

/// A LoRA run from a base and its exports: the base and the merged checkpoint in the diffusers
/// layout, and the adapters alone.
struct LoraExports {
    /// Holds the files until the test ends.
    _dir: bwm_testdir::TestDir,
    trained: Trainer,
    base_file: std::path::PathBuf,
    base_out: std::path::PathBuf,
    merged_out: std::path::PathBuf,
    adapters: bwm_checkpoints::lora_export::AdapterExport,
}

fn lora_exports(tag: &str) -> LoraExports {
    use bwm_checkpoints::export::{export, ExportDtype, ExportOptions};
    use bwm_checkpoints::lora_export::export_lora_adapters;
    let dir = tmp_dir(tag);
    let cache = write_cache(&dir.join("cache"), 1, 16);
    // The base: the weights of a run without adapters, written as a file the LoRA run starts from.
    let base = trainer(config(&cache, &dir.join("base"), ""), Resume::No).unwrap();
    let base_file = dir.join("base.safetensors");
    Tensor::write_safetensors(&base.model.store.named_parameters(), &base_file).unwrap();
    let extra = format!("[model]\n{LORA}\ninit = {{ from = \"bwm-checkpoint\", path = \"{}\" }}\n[train]\nsteps = 10\n[optim]\nlr = 1e-2", base_file.display());
    let mut trained = trainer(config(&cache, &dir.join("lora"), &extra), Resume::No).unwrap();
    trained.run().unwrap();
    let ckpt = trained.checkpoints.latest().unwrap().unwrap().path;

    let diffusers = |out: &str, input: &str, opts: ExportOptions| {
        let path = dir.join(out);
        export(input, &path, &ExportOptions { layout: bwm_checkpoints::DitLayout::Diffusers, dtype: ExportDtype::F32, ..opts }, &mut |_| {}).unwrap();
        path
    };
    let base_out = diffusers("base-diffusers", base_file.to_str().unwrap(), ExportOptions { config: Some(dir.join("base/config.toml")), ..Default::default() });
    let merged_out = diffusers("merged-diffusers", ckpt.to_str().unwrap(), ExportOptions { merge_lora: true, ..Default::default() });
    let adapters = export_lora_adapters(ckpt.to_str().unwrap(), &dir.join("adapters"), ExportDtype::F32, false).unwrap();
    assert_eq!((adapters.layers, adapters.left_out.len()), (12, 0));
    LoraExports { _dir: dir, trained, base_file, base_out, merged_out, adapters }
}

#[test]
fn exported_adapters_load_onto_the_base_as_the_merged_checkpoint() {
    let e = lora_exports("lora-adapters");
    // Base + adapter folder (`--checkpoint BASE --lora ADAPTERS`) is the merged checkpoint.
    let ckpt = e.trained.checkpoints.latest().unwrap().unwrap().path;
    let opened = bwm_checkpoints::open::open_any(e.base_file.to_str().unwrap()).unwrap();
    let with_adapters = bwm_checkpoints::open::with_lora_adapters(opened, &e.adapters.out).unwrap();
    let from_adapters = bwm_checkpoints::open::build_model(with_adapters, Some(&e.trained.model.cfg), Kind::Float, tch::Device::Cpu).unwrap();
    let merged = bwm_checkpoints::open::load_model(ckpt.to_str().unwrap(), None, Kind::Float, tch::Device::Cpu).unwrap();
    let merged_params: BTreeMap<String, Tensor> = merged.store.named_parameters().into_iter().collect();
    for (n, w) in from_adapters.store.named_parameters() {
        let d = max_abs_diff(&w, &merged_params[&n]);
        assert!(d < 1e-6, "{n}: base + exported adapters differ from the merged checkpoint by {d}");
    }
}

/// diffusers' own LoRA loader (PEFT underneath) puts the exported adapters on the base export
/// and computes what the merged export computes (tests/python/lora_interop.py). Needs diffusers
/// and peft in the project's virtualenv (scripts/setup.sh --tests installs them; `bwm_testdir::need`).
#[test]
fn exported_adapters_load_in_diffusers_as_the_merged_export() {
    let Some(py) = bwm_testdir::python_with(bwm_testdir::Dep::Reference, &["diffusers", "peft"]) else { return };
    let e = lora_exports("lora-diffusers");
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/lora_interop.py");
    let out = std::process::Command::new(py)
        .arg(script)
        .args([&e.base_out, &e.adapters.out, &e.merged_out])
        .arg(e.adapters.layers.to_string())
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "lora_interop.py failed:\n{text}");
    assert!(text.contains("adapted layers 12"), "{text}");
}
