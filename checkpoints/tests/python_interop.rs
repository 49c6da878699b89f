//! Python interoperability: the exports load into the reference stack the BWM release and the
//! diffusers ecosystem use, with only the declared missing keys, and the reference forward
//! (`bwm_forward` of shared/golden/make_golden.py) on the exported weights matches the Rust forward.
//!
//! Needs the project virtualenv with `diffsynth==2.0.11` and `diffusers` (scripts/setup.sh installs
//! them; run through `source scripts/env.sh`). Without them the test says so and passes, unless
//! BWM_REQUIRE_PY_INTEROP=1.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use bwm_checkpoints::export::{export, ExportDtype, ExportOptions};
use bwm_checkpoints::DitLayout;
use bwm_model::frame_timesteps;
use common::*;
use tch::{Device, Kind, Tensor};

fn python() -> Option<PathBuf> {
    for var in ["VIRTUAL_ENV", "BWM_VENV"] {
        if let Some(v) = std::env::var_os(var) {
            let p = Path::new(&v).join("bin/python");
            if p.exists() {
                return Some(p);
            }
        }
    }
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python");
    p.exists().then_some(p)
}

fn has_modules(py: &Path) -> Result<(), String> {
    let out = Command::new(py)
        .args(["-c", "import diffsynth, diffusers, einops; print(diffsynth.__file__, diffusers.__version__)"])
        .output()
        .map_err(|e| e.to_string())?;
    if out.status.success() {
        Ok(())
    } else {
        Err(String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or("").to_string())
    }
}

fn rel_err(a: &Tensor, b: &Tensor) -> f64 {
    let a = a.to_kind(Kind::Double);
    let b = b.to_kind(Kind::Double);
    (&a - &b).norm().double_value(&[]) / b.norm().double_value(&[]).max(1e-30)
}

#[test]
fn exports_load_in_diffsynth_and_diffusers_and_the_reference_forward_matches() {
    let required = std::env::var("BWM_REQUIRE_PY_INTEROP").is_ok_and(|v| v == "1");
    let Some(py) = python() else {
        assert!(!required, "no virtualenv python");
        eprintln!("SKIPPED: no virtualenv python (source scripts/env.sh)");
        return;
    };
    if let Err(e) = has_modules(&py) {
        assert!(!required, "python modules missing: {e}");
        eprintln!("SKIPPED: diffsynth/diffusers not importable in {} ({e}); scripts/setup.sh installs them", py.display());
        return;
    }
    let shared = std::env::var_os("BWM_SHARED").map(PathBuf::from).unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared"));
    let make_golden = shared.join("golden/make_golden.py");
    assert!(make_golden.is_file(), "{} missing (set BWM_SHARED)", make_golden.display());

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
    let res = Command::new(&py).arg(&script).arg(&make_golden).args(&dirs).arg(&case).arg(&out).output().unwrap();
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
        assert!(e < 1e-4, "{tag}: relative error {e}");
    }
}
