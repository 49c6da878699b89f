//! Python interoperability: the exports load into the reference stack the BWM release and the
//! diffusers ecosystem use, with only the declared missing keys, and the reference forward
//! (`bwm_forward` of scripts/golden.py) on the exported weights matches the Rust forward.
//!
//! Needs the project virtualenv with `diffsynth==2.0.11`, `diffusers` and `einops` (scripts/setup.sh
//! --tests installs them; run through `source scripts/env.sh`): without them the test fails where
//! BWM_REQUIRE names reference (CI sets `all`) and is logged as skipped elsewhere
//! (`bwm_testdir::need`).

mod common;

use std::path::Path;
use std::process::Command;

use bwm_checkpoints::export::{export, ExportDtype, ExportOptions};
use bwm_checkpoints::DitLayout;
use bwm_model::frame_timesteps;
use bwm_testdir::Dep;
use common::*;
use tch::{Device, Kind, Tensor};

fn rel_err(a: &Tensor, b: &Tensor) -> f64 {
    let a = a.to_kind(Kind::Double);
    let b = b.to_kind(Kind::Double);
    (&a - &b).norm().double_value(&[]) / b.norm().double_value(&[]).max(1e-30)
}

#[test]
fn exports_load_in_diffsynth_and_diffusers_and_the_reference_forward_matches() {
    let Some(py) = bwm_testdir::python_with(Dep::Reference, &["diffsynth", "diffusers", "einops"]) else { return };
    let golden_py = bwm_testdir::golden_generator();

    let root = tmp_dir("pyinterop");
    let cfg = tiny();
    let model = random_model(&cfg, 31);
    let ckpt = fake_run(&root, &model, &|c| run_toml("py", "tiny", None, c));
    let mut dirs = Vec::new();
    for layout in DitLayout::ALL {
        let out = root.join(format!("export-{layout}"));
        let opts = ExportOptions { layout, dtype: ExportDtype::F32, shard_size: 400_000, ..Default::default() };
        export(ckpt.to_str().unwrap(), &out, &opts, &mut |_| {}).unwrap();
        dirs.push(out);
    }

    tch::manual_seed(5);
    let latents = Tensor::randn([1, 48, 5, 4, 6], (Kind::Float, Device::Cpu));
    let actions = Tensor::rand([1, 17, 14], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
    let t = Tensor::from_slice(&[700.0f32]);
    let v_rust = tch::no_grad(|| model.forward(&latents, &frame_timesteps(&t, 5, 3), &actions)).unwrap();
    let case = root.join("case.safetensors");
    bwm_checkpoints::write_tensors(
        &case,
        &[("latents".into(), latents), ("timestep".into(), t), ("actions".into(), actions)],
        &Default::default(),
    )
    .unwrap();
    let out = root.join("py-out.safetensors");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/interop.py");
    let res = Command::new(&py).arg(&script).arg(&golden_py).args(&dirs).arg(&case).arg(&out).output().unwrap();
    let stdout = String::from_utf8_lossy(&res.stdout);
    assert!(res.status.success(), "python failed:\n{stdout}\n{}", String::from_utf8_lossy(&res.stderr));
    let report: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    eprintln!("{}", serde_json::to_string_pretty(&report).unwrap());

    let text_emb: Vec<String> = ["0.bias", "0.weight", "2.bias", "2.weight"].iter().map(|s| format!("text_embedding.{s}")).collect();
    assert_eq!(report["wan"]["missing"], serde_json::json!(text_emb), "DiffSynth WanModel: only text_embedding.* missing");
    assert_eq!(report["wan"]["declared_missing"], serde_json::json!(text_emb), "and exactly those are declared");
    assert_eq!(report["wan"]["unexpected"], serde_json::json!([]));
    let fp = &report["diffusers"]["from_pretrained"];
    let diff_text: Vec<String> = ["linear_1.bias", "linear_1.weight", "linear_2.bias", "linear_2.weight"]
        .iter()
        .map(|s| format!("condition_embedder.text_embedder.{s}"))
        .collect();
    assert_eq!(fp["missing_keys"], serde_json::json!(diff_text), "WanTransformer3DModel.from_pretrained: only the text embedder missing");
    assert_eq!(fp["unexpected_keys"], serde_json::json!([]));
    assert_eq!(fp["mismatched_keys"], serde_json::json!([]));
    assert_eq!(report["diffusers"]["differs_from_wan_export"], serde_json::json!([]), "DiffSynth's diffusers->Wan map gives the Wan export's tensors");
    assert_eq!(report["release"]["missing"], serde_json::json!(text_emb));
    assert_eq!(report["release"]["unexpected"], serde_json::json!([]));

    let py_out = bwm_checkpoints::read_tensors(&out, Device::Cpu).unwrap();
    for tag in ["wan", "diffusers", "release"] {
        let e = rel_err(&v_rust, &py_out[tag]);
        eprintln!("{tag}: relative error Rust vs Python reference forward = {e:.2e}");
        // As the golden DiT parity (model/tests/golden_dit.rs): f32 on the CPU, measured 1.7e-7.
        assert!(e < 1e-6, "{tag}: relative error {e}");
    }
}
