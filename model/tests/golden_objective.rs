//! The BWM sampler against the golden `objective_public.safetensors` (DiffSynth-Studio
//! 2.0.11 `FlowMatchScheduler("Wan")`, 4 Euler steps at shift 5, prefix re-imposed every step),
//! on the `dit_public` weights.

mod common;

use bwm_model::{sampler::{sample_chunk, Eager}, weights, ActionConfig, BwmModel, DitConfig, FlowSchedule, Layout, ModelConfig};
use common::{golden_dir, rel_err};
use std::path::Path;
use tch::{Device, Kind};

fn public_model(golden: &Path) -> BwmModel {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(golden.join("dit_public.json")).unwrap()).unwrap();
    let mut dit: serde_json::Value = json["dit"].clone();
    let keep = ["dim", "in_dim", "out_dim", "ffn_dim", "freq_dim", "text_dim", "num_heads", "num_layers", "eps", "patch_size"];
    dit.as_object_mut().unwrap().retain(|k, _| keep.contains(&k.as_str()));
    let dit: DitConfig = serde_json::from_value(dit).unwrap();
    let cfg = ModelConfig { dit, action: ActionConfig::default() };
    BwmModel::load(&golden.join("dit_public.weights.safetensors"), Layout::WanNative, &cfg, Kind::Float, Device::Cpu).unwrap()
}

#[test]
fn euler_sampler_with_prefix_matches_reference() {
    let Some(golden) = golden_dir() else { return };
    let t = weights::read_all(golden.join("objective_public.safetensors")).unwrap();
    let model = public_model(&golden);
    let steps = t["sampler_steps"].int64_value(&[0]) as usize;
    let schedule = FlowSchedule::inference(steps, 5.0);
    let sig = Vec::<f32>::try_from(&t["sampler_sigmas"]).unwrap();
    assert!(schedule.sigmas.iter().zip(&sig).all(|(a, b)| (a - *b as f64).abs() < 1e-6));
    let prefix = &t["sampler_prefix"];
    let mut steps_seen = 0;
    let out = tch::no_grad(|| {
        sample_chunk(&mut Eager, &model, prefix, &t["sampler_init_noise"], &t["actions"], &schedule, 1.0, &mut |_, _, _| steps_seen += 1)
    })
    .unwrap();
    assert_eq!(steps_seen, steps);
    let e = rel_err(&out, &t["sampler_out"]);
    println!("sampler_out rel err {e:.2e}");
    // Four forwards of the model, each within 1e-6 of the reference (golden_dit.rs): measured 3.5e-7.
    assert!(e < 1e-6, "sampler rel err {e}");
    assert_eq!(rel_err(&out.narrow(2, 0, prefix.size()[2]), prefix), 0.0, "prefix intact");
}
