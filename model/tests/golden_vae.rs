//! Parity of the Wan2.2 VAE with `../shared/golden/vae_public*.{json,weights,case}`, computed by
//! `shared/golden/make_golden.py` with DiffSynth-Studio 2.0.11's `VideoVAE38_` (the official
//! `WanVAE_` of Wan2.2) in f32 on CPU. Widths, frame counts and sizes come from the files.

mod common;

use bwm_model::vae::{VaeConfig, WanVae, WAN22_LATENTS_MEAN, WAN22_LATENTS_STD};
use bwm_model::weights;
use common::{golden, rel_err};
use tch::{Device, Kind, Tensor};

fn config(variant: &str) -> VaeConfig {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(golden(&format!("vae_{variant}.json"))).unwrap()).unwrap();
    let v = &json["vae"];
    assert!(v["attn_scales"].as_array().unwrap().is_empty());
    VaeConfig {
        dim: v["dim"].as_i64().unwrap(),
        dec_dim: v["dec_dim"].as_i64().unwrap(),
        z_dim: v["z_dim"].as_i64().unwrap(),
        dim_mult: v["dim_mult"].as_array().unwrap().iter().map(|x| x.as_i64().unwrap()).collect(),
        num_res_blocks: v["num_res_blocks"].as_i64().unwrap(),
        temporal_downsample: v["temperal_downsample"].as_array().unwrap().iter().map(|x| x.as_bool().unwrap()).collect(),
    }
}

fn check(variant: &str) {
    let cfg = config(variant);
    let vae = WanVae::load(&golden(&format!("vae_{variant}.weights.safetensors")), &cfg, Kind::Float, Device::Cpu).unwrap();
    let case = weights::read_all(golden(&format!("vae_{variant}.case.safetensors"))).unwrap();
    let mean = Tensor::from_slice(&WAN22_LATENTS_MEAN).to_kind(Kind::Float);
    let std = Tensor::from_slice(&WAN22_LATENTS_STD).to_kind(Kind::Float);
    assert_eq!(rel_err(&mean, &case["latents_mean"]), 0.0, "published latent mean");
    assert_eq!(rel_err(&std, &case["latents_std"]), 0.0, "published latent std");

    let latents = tch::no_grad(|| vae.encode(&case["video"])).unwrap();
    let e = rel_err(&latents, &case["latents"]);
    println!("{variant}: latents rel err {e:.2e}");
    assert!(e < 1e-4, "{variant}: latents rel err {e}");

    let decoded = tch::no_grad(|| vae.decode(&case["latents"])).unwrap();
    let e = rel_err(&decoded, &case["decoded"]);
    println!("{variant}: decoded rel err {e:.2e}");
    assert!(e < 1e-4, "{variant}: decoded rel err {e}");
}

#[test]
fn vae_public_matches_reference() {
    check("public");
}

#[test]
fn vae_public2_matches_reference() {
    check("public2");
}
