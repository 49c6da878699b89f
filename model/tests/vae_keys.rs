//! The real Wan2.2 VAE tree (shape-only) against the key table of
//! `../shared/design/wan22-ti2v-5b-spec.md` section 6.10 (the official module's state_dict, and its
//! diffusers `AutoencoderKLWan` names through `convert_vae_22`), and a diffusers-named file loading.

mod common;

use std::collections::BTreeMap;

use bwm_model::vae::{diffusers_key, VaeConfig, WanVae};
use bwm_model::ParamStore;
use common::{rel_err, tmp_dir};
use tch::{Device, Kind, Tensor};

fn spec_rows() -> Vec<(String, Vec<i64>, String)> {
    let shared = bwm_testdir::shared();
    let text = std::fs::read_to_string(shared.join("design/wan22-ti2v-5b-spec.md")).unwrap();
    let start = text.find("### 6.10").unwrap();
    text[start..]
        .lines()
        .filter_map(|l| {
            let c: Vec<&str> = l.split('|').map(str::trim).collect();
            if c.len() < 5 || c[1].parse::<usize>().is_err() {
                return None;
            }
            let shape = c[3].trim_matches(|ch| ch == '[' || ch == ']').split(',').map(|d| d.trim().parse().unwrap()).collect();
            Some((c[2].trim_matches('`').to_string(), shape, c[4].trim_matches('`').to_string()))
        })
        .collect()
}

#[test]
fn wan22_vae_keys_shapes_and_diffusers_names_match_the_spec() {
    let store = ParamStore::shapes_only(Kind::Float);
    WanVae::new(&store.root(), &VaeConfig::wan22()).unwrap();
    let ours: BTreeMap<String, Vec<i64>> = store.named_parameters().into_iter().map(|(n, t)| (n, t.size())).collect();
    let rows = spec_rows();
    assert_eq!(rows.len(), 196);
    assert_eq!(ours.len(), 196);
    let total: i64 = ours.values().map(|s| s.iter().product::<i64>()).sum();
    assert_eq!(total, 704_688_668);
    for (wan, shape, diffusers) in &rows {
        assert_eq!(ours.get(wan), Some(shape), "{wan}");
        assert_eq!(&diffusers_key(wan), diffusers, "{wan}");
    }
}

#[test]
fn diffusers_named_file_loads() {
    let dir = tmp_dir("vae-diffusers");
    let cfg = VaeConfig::with_width(8, 8);
    let (vae, store) = WanVae::random(&cfg, Kind::Float, Device::Cpu, 12).unwrap();
    let renamed: Vec<(String, Tensor)> = store.named_parameters().into_iter().map(|(n, t)| (diffusers_key(&n), t)).collect();
    let path = dir.join("diffusion_pytorch_model.safetensors");
    Tensor::write_safetensors(&renamed, &path).unwrap();
    let loaded = WanVae::load_diffusers(&path, &cfg, Kind::Float, Device::Cpu).unwrap();
    let video = bwm_model::vb::with_seed(2, || Tensor::rand([1, 3, 5, 32, 32], (Kind::Float, Device::Cpu))) * 2.0 - 1.0;
    let (a, b) = tch::no_grad(|| (vae.encode(&video).unwrap(), loaded.encode(&video).unwrap()));
    assert_eq!(rel_err(&a, &b), 0.0);
}
