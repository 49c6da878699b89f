//! Parity of the Wan2.2 VAE with DiffSynth-Studio 2.0.11's `VideoVAE38_` (the official `WanVAE_`
//! of Wan2.2) in f32 on CPU: on the golden `vae_public*.{json,weights,case}` (computed by
//! `scripts/golden.py`; 5 and 9 frames), and on a 33-frame video whose reference this
//! test computes with the same code in the project's Python environment (the causal feature cache
//! over more chunks than the golden files hold). Widths, frame counts and sizes come from the files.

mod common;

use std::path::{Path, PathBuf};

use bwm_model::vae::{VaeConfig, WanVae, WAN22_LATENTS_MEAN, WAN22_LATENTS_STD};
use bwm_model::weights;
use common::{golden_dir, rel_err, tmp_dir};
use tch::{Device, Kind, Tensor};

/// Relative error allowed against the reference, f32 on the CPU, for the latents and the decoded
/// frames (docs/architecture.md, VAE notes): measured up to 1.3e-6 (the decoder's many
/// convolutions summing in another order), so 5e-6 leaves a factor of about 4 for other CPUs'
/// kernels.
const VAE_BOUND: f64 = 5e-6;

fn config(json: &Path) -> VaeConfig {
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
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

/// `vae_{variant}.{json,weights.safetensors,case.safetensors}` as `file(name)` finds them.
fn check(variant: &str, file: impl Fn(&str) -> PathBuf) {
    let cfg = config(&file(&format!("vae_{variant}.json")));
    let vae = WanVae::load(&file(&format!("vae_{variant}.weights.safetensors")), &cfg, Kind::Float, Device::Cpu).unwrap();
    let case = weights::read_all(file(&format!("vae_{variant}.case.safetensors"))).unwrap();
    let mean = Tensor::from_slice(&WAN22_LATENTS_MEAN).to_kind(Kind::Float);
    let std = Tensor::from_slice(&WAN22_LATENTS_STD).to_kind(Kind::Float);
    assert_eq!(rel_err(&mean, &case["latents_mean"]), 0.0, "published latent mean");
    assert_eq!(rel_err(&std, &case["latents_std"]), 0.0, "published latent std");

    let latents = tch::no_grad(|| vae.encode(&case["video"])).unwrap();
    let e = rel_err(&latents, &case["latents"]);
    println!("{variant}: latents {:?}, rel err {e:.2e}", latents.size());
    assert!(e < VAE_BOUND, "{variant}: latents rel err {e}");

    let decoded = tch::no_grad(|| vae.decode(&case["latents"])).unwrap();
    let e = rel_err(&decoded, &case["decoded"]);
    println!("{variant}: decoded rel err {e:.2e}");
    assert!(e < VAE_BOUND, "{variant}: decoded rel err {e}");
}

#[test]
fn vae_public_matches_reference() {
    let Some(golden) = golden_dir() else { return };
    check("public", |name| golden.join(name));
}

#[test]
fn vae_public2_matches_reference() {
    let Some(golden) = golden_dir() else { return };
    check("public2", |name| golden.join(name));
}

/// scripts/golden.py's VAE case (random parameters at scale 0.1, a random video in [-1, 1],
/// normalized latents), at 33 frames of 32x48: nine latent frames, so the feature cache carries
/// over eight chunk boundaries.
const LONG_CASE: &str = r#"
import json, sys, torch
from safetensors.torch import save_file
from diffsynth.models.wan_video_vae import VideoVAE38_, WanVideoVAE38
out = sys.argv[1]
torch.manual_seed(0)
cfg = dict(dim=8, z_dim=48, dec_dim=8, dim_mult=[1, 2, 4, 4], num_res_blocks=2, attn_scales=[], temperal_downsample=[False, True, True])
vae = VideoVAE38_(**cfg).eval()
with torch.no_grad():
    for p in vae.parameters():
        p.copy_(torch.randn_like(p) * 0.1)
ref = WanVideoVAE38(z_dim=48, dim=8)
mean, std = ref.mean.clone(), ref.std.clone()
video = torch.rand(1, 3, 33, 32, 48) * 2 - 1
with torch.no_grad():
    z = vae.encode(video, [mean, 1.0 / std])
    rec = vae.decode(z, [mean, 1.0 / std])
save_file({k: v.contiguous() for k, v in vae.state_dict().items()}, f"{out}/vae_long.weights.safetensors")
save_file({"video": video, "latents": z.contiguous(), "decoded": rec.contiguous(), "latents_mean": mean, "latents_std": std}, f"{out}/vae_long.case.safetensors")
json.dump({"vae": cfg}, open(f"{out}/vae_long.json", "w"))
"#;

#[test]
fn vae_matches_reference_over_nine_latent_frames() {
    let Some(py) = bwm_testdir::python_with(bwm_testdir::Dep::Reference, &["diffsynth", "safetensors"]) else { return };
    let dir = tmp_dir("vae-long-parity");
    let out = std::process::Command::new(py).args(["-c", LONG_CASE]).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "reference run failed: {}", String::from_utf8_lossy(&out.stderr));
    check("long", |name| dir.join(name));
}
