//! `.pth` files written by PyTorch's own `torch.save` (the project virtualenv's torch, driven by
//! a small Python helper below) read by the Rust loader.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use bwm_model::pth;
use bwm_model::vae::{VaeConfig, WanVae};
use common::{rel_err, tmp_dir};
use tch::{Device, Kind, Tensor};

/// The project virtualenv's Python with torch (`bwm_testdir::python_with`: without it the test
/// fails where BWM_REQUIRE names python, and is logged as skipped elsewhere).
fn python() -> Option<PathBuf> {
    bwm_testdir::python_with(bwm_testdir::Dep::Python, &["torch", "safetensors"])
}

/// Runs a Python snippet with `py`; panics if it fails.
fn run_python(py: &Path, script: &str, args: &[&Path]) {
    let status = Command::new(py).arg("-c").arg(script).args(args).status().unwrap();
    assert!(status.success(), "python helper failed");
}

/// Converts a safetensors file to a `.pth` with torch.save; `extras` adds a bf16 tensor, a
/// transposed (non-contiguous) view and a view sharing its storage with another tensor.
fn torch_save(py: &Path, from: &Path, to: &Path, wrap: Option<&str>) {
    let script = r#"
import sys, collections, torch
from safetensors.torch import load_file
sd = collections.OrderedDict(sorted(load_file(sys.argv[1]).items()))
base = torch.arange(24, dtype=torch.float32).reshape(4, 6)
sd["extra.bf16"] = (base / 7).to(torch.bfloat16)
sd["extra.transposed"] = base.t()
sd["extra.row_view"] = base[2]
sd["extra.base"] = base
obj = {sys.argv[3]: sd} if sys.argv[3] != "-" else sd
torch.save(obj, sys.argv[2])
"#;
    run_python(py, script, &[from, to, Path::new(wrap.unwrap_or("-"))]);
}

#[test]
fn torch_saved_state_dicts_load() {
    let Some(py) = python() else { return };
    let dir = tmp_dir("pth");
    let cfg = VaeConfig::with_width(8, 8);
    let (vae, store) = WanVae::random(&cfg, Kind::Float, Device::Cpu, 9).unwrap();
    let st = dir.join("vae.safetensors");
    Tensor::write_safetensors(&store.named_parameters(), &st).unwrap();
    let pth = dir.join("Wan2.2_VAE.pth");
    torch_save(&py, &st, &pth, None);

    let source = pth::open(&pth).unwrap();
    let t = source.tensors();
    for (name, original) in store.named_parameters() {
        assert_eq!(rel_err(&t[&name], &original), 0.0, "{name}");
    }
    let base = Tensor::arange(24, (Kind::Float, Device::Cpu)).reshape([4, 6]);
    assert_eq!(t["extra.bf16"].kind(), Kind::BFloat16);
    assert_eq!(rel_err(&t["extra.transposed"], &base.tr()), 0.0);
    assert_eq!(rel_err(&t["extra.row_view"], &base.get(2)), 0.0);

    // The VAE loads straight from the .pth (extra keys make a strict load fail, so strip them).
    let clean = dir.join("clean.pth");
    let clean_st = dir.join("clean.safetensors");
    Tensor::write_safetensors(&store.named_parameters(), &clean_st).unwrap();
    let script = "import sys, torch\nfrom safetensors.torch import load_file\ntorch.save(load_file(sys.argv[1]), sys.argv[2])";
    run_python(&py, script, &[&clean_st, &clean]);
    let loaded = WanVae::load(&clean, &cfg, Kind::Float, Device::Cpu).unwrap();
    let video = bwm_model::vb::with_seed(1, || Tensor::rand([1, 3, 5, 32, 32], (Kind::Float, Device::Cpu))) * 2.0 - 1.0;
    let (a, b) = tch::no_grad(|| (vae.encode(&video).unwrap(), loaded.encode(&video).unwrap()));
    assert_eq!(rel_err(&a, &b), 0.0);
    let e = format!("{:#}", WanVae::load(&pth, &cfg, Kind::Float, Device::Cpu).err().unwrap());
    assert!(e.contains("unexpected key 'extra."), "{e}");

    // A state dict wrapped as {"state_dict": ...} is found.
    let wrapped = dir.join("wrapped.pth");
    torch_save(&py, &st, &wrapped, Some("state_dict"));
    assert!(pth::open(&wrapped).unwrap().tensors().contains_key("encoder.conv1.weight"));
}

#[test]
fn broken_pth_files_are_clear_errors() {
    let Some(py) = python() else { return };
    let dir = tmp_dir("pth-bad");
    let cfg = VaeConfig::with_width(8, 8);
    let (_, store) = WanVae::random(&cfg, Kind::Float, Device::Cpu, 10).unwrap();
    let st = dir.join("vae.safetensors");
    Tensor::write_safetensors(&store.named_parameters(), &st).unwrap();
    let pth = dir.join("vae.pth");
    torch_save(&py, &st, &pth, None);
    let bytes = std::fs::read(&pth).unwrap();
    let cut = dir.join("cut.pth");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let e = format!("{}", pth::open(&cut).err().unwrap());
    assert!(e.contains("cut.pth"), "{e}");
    let text = dir.join("text.pth");
    std::fs::write(&text, b"not a zip").unwrap();
    let e = format!("{}", pth::open(&text).err().unwrap());
    assert!(e.contains("text.pth") && e.contains("not a PyTorch zip archive"), "{e}");
}
