//! Export -> load round trips in every layout, conversions, the 5B key-map bijection, and the
//! errors for bad input (another config, partial exports, name collisions).

mod common;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use bwm_checkpoints::convert::{convert_dit, convert_vae, ConvertOptions, VaeNaming};
use bwm_checkpoints::export::{export, ExportDtype, ExportOptions};
use bwm_checkpoints::keymap::{detect_layout, from_layout, to_layout, DitLayout};
use bwm_checkpoints::open::{load_model, open_any, training_record};
use bwm_checkpoints::repo::RepoConfig;
use bwm_checkpoints::write_tensors;
use bwm_model::{BwmModel, ModelConfig, ParamStore};
use common::*;
use tch::{Device, Kind, Tensor};

fn trained(model: &BwmModel) -> BTreeMap<String, Tensor> {
    params(model).into_iter().filter(|(n, _)| !n.starts_with("text_embedding.")).collect()
}

#[test]
fn key_maps_are_bijections_on_the_5b_tree() {
    let cfg = ModelConfig::preset("wan22_ti2v_5b").unwrap();
    let store = ParamStore::shapes_only(Kind::BFloat16);
    BwmModel::build(&store, &cfg).unwrap();
    let keys: Vec<String> = store.named_parameters().into_iter().map(|(n, _)| n).collect();
    assert_eq!(keys.len(), 825 + 8, "825 DiT tensors (spec 5.1) + 8 action-encoder tensors");
    for layout in DitLayout::ALL {
        let mapped: Vec<String> = keys.iter().map(|k| to_layout(layout, k).unwrap()).collect();
        let unique: BTreeSet<&String> = mapped.iter().collect();
        assert_eq!(unique.len(), keys.len(), "{layout}: two keys map to one name");
        for (k, m) in keys.iter().zip(&mapped) {
            assert_eq!(&from_layout(layout, m).unwrap(), k, "{layout}: {k} -> {m} does not map back");
        }
        assert_eq!(detect_layout(&mapped).unwrap(), layout, "{layout}: detection");
    }
    let diff: BTreeSet<String> = keys.iter().map(|k| to_layout(DitLayout::Diffusers, k).unwrap()).collect();
    for k in ["scale_shift_table", "blocks.29.scale_shift_table", "blocks.0.norm2.weight", "condition_embedder.time_proj.weight", "proj_out.bias"] {
        assert!(diff.contains(k), "{k}");
    }
    assert!(!diff.iter().any(|k| k.contains("norm3")), "diffusers has no weighted norm3");
}

#[test]
fn export_then_load_gives_identical_tensors_in_every_layout() {
    let root = tmp_dir("roundtrip");
    let cfg = tiny();
    let model = random_model(&cfg, 11);
    let ckpt = fake_run(&root, &model, &|c| run_toml("rt", "tiny", None, c));
    let want = trained(&model);
    let stats = root.join("stat.json");
    let group = |v: f64| serde_json::json!({"shape": [14], "min": vec![-v; 14], "max": vec![v; 14], "p01": vec![-v; 14], "p99": vec![v; 14], "mean": vec![0.0; 14], "std": vec![1.0; 14]});
    std::fs::write(&stats, serde_json::json!({"state_pose": group(1.0), "action_pose": group(2.0)}).to_string()).unwrap();
    for layout in DitLayout::ALL {
        for dtype in [ExportDtype::F32, ExportDtype::Bf16] {
            let out = root.join(format!("out-{layout}-{dtype:?}"));
            let opts = ExportOptions { layout, dtype, shard_size: 300_000, action_stats: Some(stats.clone()), ..Default::default() };
            let rep = export(ckpt.to_str().unwrap(), &out, &opts, &mut |_| {}).unwrap();
            assert_eq!(rep.tensors, want.len());
            assert_eq!(rep.declared_missing.len(), 4, "text_embedding.{{0,2}}.{{weight,bias}}");
            let shards = rep.files.iter().filter(|f| f.path.ends_with(".safetensors")).count();
            assert!(shards > 2, "{layout}: a 300 kB shard size gives several shards, got {shards}");
            let kind = dtype.kind();
            // The files: every tensor stored in the export dtype, under the layout's names.
            let opened = open_any(out.to_str().unwrap()).unwrap();
            assert_eq!(opened.layout, layout);
            assert_eq!(opened.config.as_ref(), Some(&cfg));
            assert!(opened.kinds.values().all(|k| *k == kind), "{layout} {dtype:?}: stored dtypes");
            assert_same(&read_all(&opened), &want, kind, &format!("{layout} {dtype:?} files"));
            // Through the model: load_model builds the BwmModel from the export alone.
            let back = load_model(out.to_str().unwrap(), None, Kind::Float, Device::Cpu).unwrap();
            let got: BTreeMap<String, Tensor> = params(&back);
            assert_same(&got, &want, kind, &format!("{layout} {dtype:?} model"));
            // Repository contents.
            let rc = RepoConfig::read(&out).unwrap().unwrap();
            assert_eq!(rc.layout, layout.name());
            assert_eq!(rc.weights.missing_keys.len(), 4);
            let stats_back: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("action_stats.json")).unwrap()).unwrap();
            assert_eq!(stats_back["state_pose"]["p99"][0], 1.0);
            assert!(stats_back.get("action_pose").is_none());
            assert_eq!(rc.conditioning.as_ref().unwrap()["pixel_frames"], 17);
            let card = std::fs::read_to_string(out.join("README.md")).unwrap();
            assert!(card.contains("| steps | 10"), "{card}");
            assert!(card.contains("final loss | 0.10000"), "{card}");
            match layout {
                DitLayout::Diffusers => {
                    assert!(out.join("transformer/config.json").is_file());
                    assert!(out.join("transformer/diffusion_pytorch_model.safetensors.index.json").is_file());
                    assert!(out.join("action_encoder/model.safetensors.index.json").is_file());
                }
                _ => assert!(out.join("model.safetensors.index.json").is_file()),
            }
            // No temporary folder left behind.
            let leftovers: Vec<String> = std::fs::read_dir(&root).unwrap().flatten().map(|e| e.file_name().to_string_lossy().to_string()).filter(|n| n.contains(".tmp-")).collect();
            assert!(leftovers.is_empty(), "{leftovers:?}");
        }
    }
}

#[test]
fn the_trained_residual_action_dropout_history_sigma_and_shift_travel_from_the_run_to_the_export() {
    let root = tmp_dir("residual");
    let model = random_model(&tiny(), 13);
    let ckpt = fake_run(&root, &model, &|c| {
        run_toml("res", "tiny", None, c).replace("dtype = \"f32\"\n", "dtype = \"f32\"\nresidual = \"model\"\n") + "\n[objective]\naction_dropout = 0.1\nhistory_sigma = 0.05\nshift = 2.0\n"
    });
    let record = |path: &Path| training_record(&open_any(path.to_str().unwrap()).unwrap()).unwrap();
    let residual = |path: &Path| record(path).residual;
    assert_eq!(residual(&ckpt).as_deref(), Some("model"), "the training checkpoint's run config");
    assert_eq!(record(&ckpt).action_dropout, Some(0.1));
    assert_eq!(record(&ckpt).history_sigma, Some(0.05));
    assert_eq!(record(&ckpt).shift, Some(2.0));
    // The checkpoint folder itself loads as a model, under its run's config.
    let back = load_model(ckpt.to_str().unwrap(), None, Kind::Float, Device::Cpu).unwrap();
    assert_same(&trained(&back), &trained(&model), Kind::Float, "training checkpoint folder");
    let out = root.join("out");
    export(ckpt.to_str().unwrap(), &out, &ExportOptions { dtype: ExportDtype::F32, ..Default::default() }, &mut |_| {}).unwrap();
    assert_eq!(residual(&out).as_deref(), Some("model"), "the export's config.json");
    assert_eq!(record(&out).action_dropout, Some(0.1));
    assert_eq!(record(&out).history_sigma, Some(0.05), "the export's schedule");
    assert_eq!(record(&out).shift, Some(2.0), "the export's schedule");
    // A run that does not set them (trained without action dropout), and weights that record nothing.
    let plain = fake_run(&root.join("plain"), &model, &|c| run_toml("plain", "tiny", None, c));
    assert_eq!(record(&plain), bwm_checkpoints::open::TrainingRecord { residual: None, action_dropout: Some(0.0), history_sigma: None, shift: None });
    let file = root.join("bare.safetensors");
    write_tensors(&file, &trained(&model).into_iter().collect::<Vec<_>>(), &BTreeMap::new()).unwrap();
    assert_eq!(record(&file), Default::default());
}

#[test]
fn ema_export_reads_the_optimizer_state() {
    let root = tmp_dir("ema");
    let model = random_model(&tiny(), 12);
    let ckpt = fake_run(&root, &model, &|c| run_toml("ema", "tiny", None, c));
    let out = root.join("out");
    let opts = ExportOptions { ema: true, dtype: ExportDtype::F32, ..Default::default() };
    export(ckpt.to_str().unwrap(), &out, &opts, &mut |_| {}).unwrap();
    let got = read_all(&open_any(out.to_str().unwrap()).unwrap());
    let want: BTreeMap<String, Tensor> = trained(&model).into_iter().map(|(n, t)| (n, t * 0.5)).collect();
    assert_same(&got, &want, Kind::Float, "ema");
    assert!(RepoConfig::read(&out).unwrap().unwrap().weights.ema);
}

#[test]
fn conversions_between_layouts_keep_every_tensor() {
    let root = tmp_dir("convert");
    let cfg = tiny();
    let model = random_model(&cfg, 13);
    let all = params(&model);
    // A Wan-native single file with text_embedding (as a full DiT checkpoint has it).
    let wan_file = root.join("wan.safetensors");
    write_tensors(&wan_file, &all.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect::<Vec<_>>(), &BTreeMap::new()).unwrap();
    let mut prev = wan_file.display().to_string();
    for (i, to) in [DitLayout::Diffusers, DitLayout::WanNative, DitLayout::Diffusers, DitLayout::BwmRelease, DitLayout::WanNative].into_iter().enumerate() {
        let out = if i % 2 == 0 { root.join(format!("c{i}.safetensors")) } else { root.join(format!("c{i}")) };
        let opts = ConvertOptions { to, model: Some(cfg.clone()), shard_size: 200_000, ..Default::default() };
        let rep = convert_dit(&prev, &out, &opts, &mut |_| {}).unwrap();
        let opened = open_any(out.to_str().unwrap()).unwrap();
        assert_eq!(opened.layout, to, "step {i}");
        let want: BTreeMap<String, Tensor> = all
            .iter()
            .filter(|(n, _)| i < 3 || !n.starts_with("text_embedding."))
            .map(|(n, t)| (n.clone(), t.shallow_clone()))
            .collect();
        assert_same(&read_all(&opened), &want, Kind::Float, &format!("convert step {i} to {to}"));
        if to == DitLayout::BwmRelease {
            assert_eq!(rep.dropped.len(), 4);
        }
        prev = out.display().to_string();
    }
    // The single-file diffusers output holds the DiT under diffusers names and the action encoder.
    let keys = bwm_model::weights::SafetensorsSource::open(root.join("c0.safetensors")).unwrap();
    let names = bwm_model::weights::WeightSource::names(&keys);
    assert!(names.contains(&"scale_shift_table".to_string()) && names.contains(&"action_encoder.action_mlp2.0.weight".to_string()));
}

#[test]
fn vae_wan_and_diffusers_names_convert_both_ways() {
    let Some(weights) = bwm_testdir::reference("golden/vae_public.weights.safetensors") else { return };
    let golden = weights.parent().unwrap().to_path_buf();
    let root = tmp_dir("vae");
    let diff = root.join("vae-diffusers.safetensors");
    let r = convert_vae(&weights, &diff, VaeNaming::Diffusers, None, false).unwrap();
    assert_eq!(r.from, VaeNaming::Wan);
    let back = root.join("vae-wan.safetensors");
    let r2 = convert_vae(&diff, &back, VaeNaming::Wan, None, false).unwrap();
    assert_eq!(r2.from, VaeNaming::Diffusers);
    let a = bwm_checkpoints::read_tensors(&weights, Device::Cpu).unwrap();
    let b = bwm_checkpoints::read_tensors(&back, Device::Cpu).unwrap();
    assert_same(&b, &a, Kind::Float, "vae wan -> diffusers -> wan");
    // The diffusers file loads through the model crate's diffusers loader at the golden widths.
    let cfg_json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(golden.join("vae_public.json")).unwrap()).unwrap();
    let vcfg: bwm_model::vae::VaeConfig = serde_json::from_value(serde_json::json!({
        "dim": cfg_json["vae"]["dim"], "dec_dim": cfg_json["vae"]["dec_dim"], "z_dim": 48, "dim_mult": [1, 2, 4, 4],
        "num_res_blocks": 2, "temporal_downsample": [false, true, true]})).unwrap();
    bwm_model::vae::WanVae::load_diffusers(&diff, &vcfg, Kind::Float, Device::Cpu).unwrap();
    // A file that is not a VAE.
    let bogus = root.join("bogus.safetensors");
    write_tensors(&bogus, &[("blocks.0.self_attn.q.weight".to_string(), Tensor::zeros([2, 2], (Kind::Float, Device::Cpu)))], &BTreeMap::new()).unwrap();
    let e = convert_vae(&bogus, &root.join("x.safetensors"), VaeNaming::Wan, None, false).unwrap_err().to_string();
    assert!(e.contains("not a Wan2.2 VAE key"), "{e}");
}

/// A `.pth` of the VAE written by PyTorch's own `torch.save` (the project virtualenv's torch;
/// `bwm_testdir::python_with`) converts to the safetensors it was saved from.
#[test]
fn a_torch_saved_vae_pth_converts_to_safetensors() {
    let Some(py) = bwm_testdir::python_with(bwm_testdir::Dep::Python, &["torch", "safetensors"]) else { return };
    let Some(weights) = bwm_testdir::reference("golden/vae_public.weights.safetensors") else { return };
    let root = tmp_dir("vae-pth");
    let pth = root.join("vae.pth");
    let ok = std::process::Command::new(py)
        .args(["-c", "import sys, torch; from safetensors.torch import load_file; torch.save(load_file(sys.argv[1]), sys.argv[2])"])
        .arg(&weights)
        .arg(&pth)
        .status()
        .unwrap()
        .success();
    assert!(ok, "python torch.save failed");
    let a = bwm_checkpoints::read_tensors(&weights, Device::Cpu).unwrap();
    let st = root.join("from-pth.safetensors");
    let r = convert_vae(&pth, &st, VaeNaming::Wan, None, false).unwrap();
    assert_eq!(r.tensors, a.len());
    assert_same(&bwm_checkpoints::read_tensors(&st, Device::Cpu).unwrap(), &a, Kind::Float, "vae .pth -> safetensors");
    assert!(convert_vae(&pth, &st, VaeNaming::Wan, None, false).unwrap_err().to_string().contains("--overwrite"));
}

#[test]
fn a_checkpoint_of_another_config_is_refused() {
    let root = tmp_dir("otherconfig");
    let cfg = tiny();
    let model = random_model(&cfg, 14);
    let ckpt = fake_run(&root, &model, &|c| run_toml("a", "tiny", None, c));
    // 1. A run config of another model passed with the checkpoint.
    let other_cfg = root.join("other.toml");
    std::fs::write(&other_cfg, run_toml("b", "tiny", Some("dim = 120\nin_dim = 48\nout_dim = 48\nffn_dim = 240\nfreq_dim = 256\ntext_dim = 64\nnum_heads = 2\nnum_layers = 1\neps = 1e-6\npatch_size = [1, 2, 2]"), &root)).unwrap();
    let opts = ExportOptions { config: Some(other_cfg), ..Default::default() };
    let e = format!("{:#}", export(ckpt.to_str().unwrap(), &root.join("o1"), &opts, &mut |_| {}).unwrap_err());
    assert!(e.contains("another model config"), "{e}");
    // 2. A checkpoint whose weights do not match the config stored in it.
    let mut small = cfg.clone();
    small.dit.dim = 120;
    small.dit.ffn_dim = 240;
    let ckpt2 = fake_run(&root.join("b"), &random_model(&small, 1), &|c| run_toml("c", "tiny", None, c));
    let e = format!("{:#}", export(ckpt2.to_str().unwrap(), &root.join("o2"), &ExportOptions::default(), &mut |_| {}).unwrap_err());
    assert!(e.contains("another model config") && e.contains("shape"), "{e}");
    // 3. Loading an export with a different config.
    let out = root.join("o3");
    export(ckpt.to_str().unwrap(), &out, &ExportOptions::default(), &mut |_| {}).unwrap();
    let e = format!("{:#}", load_model(out.to_str().unwrap(), Some(&small), Kind::Float, Device::Cpu).err().unwrap());
    assert!(e.contains("exported for model config"), "{e}");
    // 4. A bare weights file with a preset of another size.
    let e = format!("{:#}", load_model(ckpt.join("model.safetensors").to_str().unwrap(), Some(&small), Kind::Float, Device::Cpu).err().unwrap());
    assert!(e.contains("another model config"), "{e}");
}

#[test]
fn partial_and_interrupted_exports_never_look_complete() {
    let root = tmp_dir("partial");
    let model = random_model(&tiny(), 15);
    let ckpt = fake_run(&root, &model, &|c| run_toml("p", "tiny", None, c));
    let out = root.join("out");
    // Interrupted after 2 shards: no output folder and no temporary folder remain.
    let opts = ExportOptions { shard_size: 200_000, fail_after_shards: Some(2), ..Default::default() };
    let e = export(ckpt.to_str().unwrap(), &out, &opts, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("interrupted"), "{e}");
    assert!(!out.exists());
    let names: Vec<String> = std::fs::read_dir(&root).unwrap().flatten().map(|e| e.file_name().to_string_lossy().to_string()).collect();
    assert!(!names.iter().any(|n| n.contains(".tmp-")), "{names:?}");
    // A killed exporter's temporary folder (another pid) is refused by the loader and cleaned up
    // by the next export.
    let stale = root.join(".out.tmp-999999999");
    std::fs::create_dir_all(&stale).unwrap();
    std::fs::copy(ckpt.join("model.safetensors"), stale.join("model-00001-of-00002.safetensors")).unwrap();
    let e = format!("{:#}", open_any(stale.to_str().unwrap()).unwrap_err());
    assert!(e.contains("unfinished export"), "{e}");
    let opts = ExportOptions { shard_size: 200_000, ..Default::default() };
    export(ckpt.to_str().unwrap(), &out, &opts, &mut |_| {}).unwrap();
    assert!(!stale.exists(), "stale temporary folder removed");
    // Existing output: an error without --overwrite; replaced with it.
    let e = export(ckpt.to_str().unwrap(), &out, &opts, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("--overwrite"), "{e}");
    export(ckpt.to_str().unwrap(), &out, &ExportOptions { overwrite: true, ..opts.clone() }, &mut |_| {}).unwrap();
    // The output may not replace the input.
    let e = export(ckpt.to_str().unwrap(), &ckpt, &ExportOptions { overwrite: true, ..opts.clone() }, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("would replace the input"), "{e}");
    // A copy missing one shard.
    let partial = root.join("partial-copy");
    std::fs::create_dir_all(&partial).unwrap();
    for e in std::fs::read_dir(&out).unwrap().flatten() {
        std::fs::copy(e.path(), partial.join(e.file_name())).unwrap();
    }
    let mut shards: Vec<String> = std::fs::read_dir(&out).unwrap().flatten().map(|e| e.file_name().to_string_lossy().to_string()).filter(|n| n.ends_with(".safetensors")).collect();
    shards.sort();
    assert!(shards.len() >= 3, "{shards:?}");
    let second = shards[1].clone();
    std::fs::remove_file(partial.join(&second)).unwrap();
    let e = format!("{:#}", open_any(partial.to_str().unwrap()).unwrap_err());
    assert!(e.contains("missing") && e.contains(&second), "{e}");
    // A copy without config.json (written last).
    std::fs::copy(out.join(&second), partial.join(&second)).unwrap();
    std::fs::remove_file(partial.join("config.json")).unwrap();
    let e = format!("{:#}", open_any(partial.to_str().unwrap()).unwrap_err());
    assert!(e.contains("did not finish"), "{e}");
    // A truncated shard.
    std::fs::copy(out.join("config.json"), partial.join("config.json")).unwrap();
    let shard = partial.join(&shards[0]);
    let bytes = std::fs::read(&shard).unwrap();
    std::fs::write(&shard, &bytes[..bytes.len() / 2]).unwrap();
    let e = format!("{:#}", open_any(partial.to_str().unwrap()).unwrap_err());
    assert!(e.contains(&shards[0]) && e.contains("not a valid safetensors"), "{e}");
    // A checkpoint save that was interrupted.
    let tmp_ckpt = root.join(".step-00000020.tmp-1234");
    std::fs::create_dir_all(&tmp_ckpt).unwrap();
    let e = export(tmp_ckpt.to_str().unwrap(), &root.join("o9"), &opts, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("interrupted checkpoint"), "{e}");
}

#[test]
fn name_collisions_are_errors() {
    let root = tmp_dir("collide");
    let z = |s: &[i64]| Tensor::zeros(s, (Kind::Float, Device::Cpu));
    // The action encoder twice, under both prefixes.
    let f = root.join("both.safetensors");
    write_tensors(
        &f,
        &[
            ("head.modulation".to_string(), z(&[1, 2, 96])),
            ("action_encoder.action_mlp1.0.bias".to_string(), z(&[96])),
            ("pipe.action_encoder.action_mlp1.0.bias".to_string(), z(&[96])),
        ],
        &BTreeMap::new(),
    )
    .unwrap();
    let e = format!("{:#}", open_any(f.to_str().unwrap()).unwrap_err());
    assert!(e.contains("twice"), "{e}");
    // Wan-native and diffusers names for one tensor.
    let f = root.join("mixed.safetensors");
    write_tensors(&f, &[("head.modulation".to_string(), z(&[1, 2, 96])), ("scale_shift_table".to_string(), z(&[1, 2, 96]))], &BTreeMap::new()).unwrap();
    let e = format!("{:#}", open_any(f.to_str().unwrap()).unwrap_err());
    assert!(e.contains("mix"), "{e}");
    // A diffusers export whose action_encoder/ component repeats a tensor the transformer holds.
    let model = random_model(&tiny(), 16);
    let ckpt = fake_run(&root, &model, &|c| run_toml("c", "tiny", None, c));
    let out = root.join("diff");
    export(ckpt.to_str().unwrap(), &out, &ExportOptions { layout: DitLayout::Diffusers, ..Default::default() }, &mut |_| {}).unwrap();
    std::fs::remove_file(out.join("config.json")).unwrap();
    let shard = out.join("transformer/diffusion_pytorch_model-00001-of-00001.safetensors");
    let mut t = bwm_checkpoints::read_tensors(&shard, Device::Cpu).unwrap();
    t.insert("action_encoder.action_mlp1.0.bias".to_string(), z(&[96]));
    let index = out.join("transformer/diffusion_pytorch_model.safetensors.index.json");
    let mut idx: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&index).unwrap()).unwrap();
    idx["weight_map"]["action_encoder.action_mlp1.0.bias"] = "diffusion_pytorch_model-00001-of-00001.safetensors".into();
    std::fs::write(&index, idx.to_string()).unwrap();
    write_tensors(&shard, &t.into_iter().collect::<Vec<_>>(), &BTreeMap::new()).unwrap();
    let e = format!("{:#}", open_any(out.to_str().unwrap()).unwrap_err());
    assert!(e.contains("name collision") && e.contains("action_encoder.action_mlp1.0.bias"), "{e}");
}

#[test]
fn frozen_tensors_come_from_the_base_weights() {
    let root = tmp_dir("base");
    let cfg = tiny();
    let model = random_model(&cfg, 17);
    // Base weights: the full model in the official Wan layout (text_embedding included).
    let base = root.join("base.safetensors");
    write_tensors(&base, &params(&model).into_iter().collect::<Vec<_>>(), &BTreeMap::new()).unwrap();
    let ckpt = fake_run(&root, &model, &|c| {
        format!("{}\n[model.init]\nfrom = \"wan-pretrained\"\npath = \"{}\"\n", run_toml("b", "tiny", None, c), base.display())
    });
    // A run that also froze the head: the checkpoint lacks head.*.
    let model_file = ckpt.join("model.safetensors");
    let mut t = bwm_checkpoints::read_tensors(&model_file, Device::Cpu).unwrap();
    t.retain(|n, _| !n.starts_with("head."));
    write_tensors(&model_file, &t.into_iter().collect::<Vec<_>>(), &BTreeMap::new()).unwrap();
    let out = root.join("out");
    let rep = export(ckpt.to_str().unwrap(), &out, &ExportOptions { dtype: ExportDtype::F32, ..Default::default() }, &mut |_| {}).unwrap();
    assert_eq!(rep.from_base, 3, "head.head.{{weight,bias}} and head.modulation");
    assert_eq!(rep.declared_missing.len(), 4, "text_embedding is not filled from the base");
    assert_same(&read_all(&open_any(out.to_str().unwrap()).unwrap()), &trained(&model), Kind::Float, "with base");
    let card = std::fs::read_to_string(out.join("README.md")).unwrap();
    assert!(card.contains("base_model: Wan-AI/Wan2.2-TI2V-5B"), "{card}");
    // Without a base (random init), the lacking tensors cannot be recovered.
    let ckpt2 = fake_run(&root.join("r"), &model, &|c| run_toml("r", "tiny", None, c));
    let model_file = ckpt2.join("model.safetensors");
    let mut t = bwm_checkpoints::read_tensors(&model_file, Device::Cpu).unwrap();
    t.retain(|n, _| !n.starts_with("head."));
    write_tensors(&model_file, &t.into_iter().collect::<Vec<_>>(), &BTreeMap::new()).unwrap();
    let e = export(ckpt2.to_str().unwrap(), &root.join("o2"), &ExportOptions::default(), &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("--base") && e.contains("cannot be recovered"), "{e}");
    // `convert`, which takes no base, refuses the checkpoint that lacks them and names `export --base`.
    let opts = ConvertOptions { to: DitLayout::Diffusers, model: Some(cfg.clone()), ..Default::default() };
    let e = convert_dit(model_file.to_str().unwrap(), &root.join("c"), &opts, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("lacks 3 tensors of the model") && e.contains("--base BASE"), "{e}");
    assert!(!root.join("c").exists());
}
