//! The training objective against the golden `objective_public.safetensors` (DiffSynth-Studio
//! 2.0.11 `FlowMatchScheduler("Wan")`, the BWM release's history noise; see scripts/golden.py): the
//! model input built from clean latents, noise, history noise and timestep index 700, and the
//! weighted loss of the `dit_public` model on it, both to relative 1e-5; also through the
//! recomputing backward path (same loss).

use std::path::Path;

use bwm_model::{weights, ActionConfig, BwmModel, DitConfig, Layout, ModelConfig};
use bwm_trainer::config::ObjectiveSection;
use bwm_trainer::objective::Objective;
use tch::{Device, Kind, Tensor};


fn rel(a: &Tensor, b: &Tensor) -> f64 {
    let (a, b) = (a.to_kind(Kind::Double), b.to_kind(Kind::Double));
    (&a - &b).norm().double_value(&[]) / b.norm().double_value(&[]).max(1e-30)
}

fn public_model(golden: &Path) -> BwmModel {
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(golden.join("dit_public.json")).unwrap()).unwrap();
    let mut dit = json["dit"].clone();
    let keep = ["dim", "in_dim", "out_dim", "ffn_dim", "freq_dim", "text_dim", "num_heads", "num_layers", "eps", "patch_size"];
    dit.as_object_mut().unwrap().retain(|k, _| keep.contains(&k.as_str()));
    let cfg = ModelConfig { dit: serde_json::from_value::<DitConfig>(dit).unwrap(), action: ActionConfig::default() };
    BwmModel::load(&golden.join("dit_public.weights.safetensors"), Layout::WanNative, &cfg, Kind::Float, Device::Cpu).unwrap()
}

#[test]
fn model_input_and_loss_match_the_reference() {
    // The golden files (scripts/setup.sh --tests computes them; BWM_SHARED=<folder with golden/>
    // swaps in others); without them bwm_testdir::need decides: a failure where BWM_REQUIRE names
    // reference, else a logged skip.
    let Some(golden) = bwm_testdir::reference("golden") else { return };
    let t = weights::read_all(golden.join("objective_public.safetensors")).unwrap();
    let objective = Objective::new(&ObjectiveSection::default(), 0);
    let sh = t["history_sigma"].double_value(&[0]);
    assert!((objective.history_sigma - sh).abs() < 1e-6, "history sigma {} vs {sh}", objective.history_sigma);
    let tid = t["timestep_index"].int64_value(&[0]) as usize;
    let p = objective.prepare(&t["clean_latents"], &t["noise"], &t["history_noise"], &[tid]).unwrap();
    let e_input = rel(&p.input, &t["model_input"]);
    println!("model_input rel err {e_input:.2e}");
    assert!(e_input < 1e-5, "model_input rel err {e_input}");

    let model = public_model(&golden);
    let pred = tch::no_grad(|| model.forward(&p.input, &p.frame_timesteps, &t["actions"])).unwrap();
    let e_v = rel(&pred, &t["velocity"]);
    let loss = objective.loss(&pred, &p);
    let e_loss = rel(&loss.reshape([1]), &t["loss"]);
    println!("velocity rel err {e_v:.2e}, loss {} vs {} rel err {e_loss:.2e}", loss.double_value(&[]), t["loss"].double_value(&[0]));
    assert!(e_v < 1e-4 && e_loss < 1e-5, "velocity {e_v}, loss {e_loss}");

    for (_, w) in model.store.named_parameters() {
        let _ = w.set_requires_grad(true);
    }
    let recomputed = bwm_trainer::recompute::forward_backward(&model, &p.input, &p.frame_timesteps, &t["actions"], None, bwm_trainer::recompute::Recompute::Blocks { keep_last: 0 }, &|v| objective.loss(v, &p), &mut bwm_trainer::recompute::GradsInParams::default())
        .unwrap();
    assert!(rel(&recomputed.reshape([1]), &t["loss"]) < 1e-5);
}
