//! Parity with the reference: the golden `dit_public*.{json,weights,case}` were computed by
//! `scripts/golden.py` with DiffSynth-Studio 2.0.11 (`WanModel` + the BWM action
//! encoder, `model_fn_wan_video_action` semantics) in f32 on CPU. Every shape comes from the files.

mod common;

use std::collections::BTreeMap;
use std::path::Path;

use bwm_model::{frame_timesteps, weights, ActionConfig, BwmModel, DitConfig, Layout, ModelConfig};
use common::{golden_dir, rel_err};
use tch::{Device, Kind, Tensor};

/// Relative error allowed against the reference, f32 on the CPU, for the velocity and every
/// intermediate (docs/architecture.md, Model notes): measured up to 3.9e-7 (f32 rounding in
/// another order of operations), so 1e-6 leaves a factor of 2.5 for other CPUs' kernels.
const DIT_BOUND: f64 = 1e-6;

struct Case {
    cfg: ModelConfig,
    condition_frames: i64,
    weights: std::path::PathBuf,
    tensors: BTreeMap<String, Tensor>,
}

fn load_case(golden: &Path, variant: &str) -> Case {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(golden.join(format!("dit_{variant}.json"))).unwrap()).unwrap();
    let d = &json["dit"];
    let int = |k: &str| d[k].as_i64().unwrap_or_else(|| panic!("dit.{k}"));
    let patch: Vec<i64> = d["patch_size"].as_array().unwrap().iter().map(|v| v.as_i64().unwrap()).collect();
    let dit = DitConfig {
        dim: int("dim"),
        in_dim: int("in_dim"),
        out_dim: int("out_dim"),
        ffn_dim: int("ffn_dim"),
        freq_dim: int("freq_dim"),
        text_dim: int("text_dim"),
        num_heads: int("num_heads"),
        num_layers: int("num_layers"),
        eps: d["eps"].as_f64().unwrap(),
        patch_size: [patch[0], patch[1], patch[2]],
        rope_theta: 10000.0,
    };
    let action = ActionConfig { action_dim: json["action_dim"].as_i64().unwrap(), ..ActionConfig::default() };
    Case {
        cfg: ModelConfig { dit, action },
        condition_frames: json["condition_latent_frames"].as_i64().unwrap(),
        weights: golden.join(format!("dit_{variant}.weights.safetensors")),
        tensors: weights::read_all(golden.join(format!("dit_{variant}.case.safetensors"))).unwrap(),
    }
}

/// Per-frame [F, ...] -> per-token [F*S, ...] (every token of a frame shares its frame's value).
fn per_token(t: &Tensor, tokens: i64) -> Tensor {
    let mut size = t.size();
    let f = size[0];
    let mut expanded = size.clone();
    expanded.insert(1, tokens / f);
    size[0] = tokens;
    t.unsqueeze(1).expand(&expanded, false).reshape(&size)
}

fn check_variant(variant: &str) {
    let Some(golden) = golden_dir() else { return };
    let case = load_case(&golden, variant);
    let t = &case.tensors;
    let model = BwmModel::load(&case.weights, Layout::WanNative, &case.cfg, Kind::Float, Device::Cpu).unwrap();
    let latents = &t["latents"];
    let frames = latents.size()[2];
    let ft = frame_timesteps(&t["timesteps"], frames, case.condition_frames);
    let mut seen: BTreeMap<String, Tensor> = BTreeMap::new();
    let v = tch::no_grad(|| {
        model.forward_traced(latents, &ft, &t["actions"], &mut |name, x| {
            seen.insert(name.to_string(), x.get(0));
        })
    })
    .unwrap();

    let e = rel_err(&v, &t["velocity"]);
    println!("{variant} velocity rel err {e:.2e}");
    assert!(e < DIT_BOUND, "{variant}: velocity rel err {e}");

    let tokens = t["sample0.tokens_in"].size()[0];
    let mut checked = 0;
    for (key, reference) in t.iter().filter(|(k, _)| k.starts_with("sample0.")) {
        let name = key.trim_start_matches("sample0.");
        let ours = seen.get(name).unwrap_or_else(|| panic!("{variant}: no intermediate '{name}'"));
        let ours = if name == "t_emb" || name == "t_mod" { per_token(ours, tokens) } else { ours.shallow_clone() };
        let e = rel_err(&ours, reference);
        println!("{variant} {name} rel err {e:.2e}");
        assert!(e < DIT_BOUND, "{variant}: {name} rel err {e}");
        checked += 1;
    }
    assert!(checked >= 6, "{variant}: only {checked} intermediates in the case file");
}

#[test]
fn dit_public_matches_reference() {
    check_variant("public");
}

#[test]
fn dit_public2_matches_reference() {
    check_variant("public2");
}

#[test]
fn flow_schedule_matches_reference() {
    let Some(golden) = golden_dir() else { return };
    let t = weights::read_all(golden.join("flow_schedule.safetensors")).unwrap();
    let train = bwm_model::FlowSchedule::training(1000, 5.0);
    let infer = bwm_model::FlowSchedule::inference(50, 5.0);
    let close = |ours: &[f64], key: &str| {
        let reference = Vec::<f32>::try_from(&t[key]).unwrap();
        assert_eq!(ours.len(), reference.len(), "{key} length");
        let worst = ours.iter().zip(&reference).map(|(a, b)| (a - *b as f64).abs()).fold(0.0, f64::max);
        println!("{key}: max abs diff {worst:.2e}");
        assert!(worst < 1e-6, "{key}: max abs diff {worst}");
    };
    close(&train.sigmas, "train_sigmas");
    close(&train.weights, "train_weights");
    close(&infer.sigmas, "infer50_sigmas");
    close(&[train.history_sigma()], "history_sigma");
    // Timesteps are sigma*1000: compare relatively (1e-6 of the 0..1000 range).
    let rel = |ours: &[f64], key: &str| {
        let reference = Vec::<f32>::try_from(&t[key]).unwrap();
        let worst = ours.iter().zip(&reference).map(|(a, b)| (a - *b as f64).abs() / 1000.0).fold(0.0, f64::max);
        assert!(worst < 1e-6, "{key}: max diff {worst} of the range");
    };
    rel(&train.timesteps, "train_timesteps");
    rel(&infer.timesteps, "infer50_timesteps");
}
