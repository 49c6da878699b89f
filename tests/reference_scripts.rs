//! The PyTorch reference's training step (tests/reference/train_step.py, DiffSynth's WanModel)
//! in its tiny CPU form: full fine-tuning and DiffSynth's LoRA training (PEFT adapters on
//! q, k, v, o, ffn.0, ffn.2), the comparison docs/performance.md runs on the GPU.

mod common;

use std::process::Command;

/// Runs one tiny reference step with `py`; returns (parameters, trained parameters) from its
/// header line.
fn reference_step(py: &std::path::Path, extra: &[&str]) -> (u64, u64) {
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/reference/train_step.py");
    let out = Command::new(py)
        .arg(&script)
        .args(["--tiny", "--device", "cpu", "--steps", "2", "--warmup", "1"])
        .args(extra)
        .output()
        .expect("run python");
    let text = String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "train_step.py {extra:?} failed:\n{text}");
    for line in text.lines().filter(|l| l.starts_with("train step ")) {
        let loss: f64 = line.split("loss ").nth(1).and_then(|r| r.split(',').next()).and_then(|v| v.parse().ok()).unwrap_or(f64::NAN);
        assert!(loss.is_finite(), "non-finite loss in {line:?}");
    }
    let header = text.lines().find(|l| l.contains(" parameters (") && l.contains(" trained)")).unwrap_or_else(|| panic!("no header in:\n{text}"));
    let number = |s: &str| -> u64 { s.trim().replace(',', "").parse().unwrap_or_else(|_| panic!("bad number {s:?} in {header:?}")) };
    let all = header.split("WanModel ").nth(1).and_then(|r| r.split(" parameters").next()).map(number).unwrap();
    let trained = header.split(" parameters (").nth(1).and_then(|r| r.split(" trained").next()).map(number).unwrap();
    (all, trained)
}

#[test]
fn the_reference_trains_lora_adapters_on_every_attention_and_ffn_linear() {
    // DiffSynth and peft in the project's virtualenv (scripts/setup.sh --tests): else a failure where
    // BWM_REQUIRE names reference (CI), a logged skip elsewhere.
    let Some(py) = bwm_testdir::python_with(bwm_testdir::Dep::Reference, &["diffsynth", "peft"]) else { return };
    let (all, trained) = reference_step(&py, &["--mode", "plain"]);
    let (all4, trained4) = reference_step(&py, &["--mode", "plain", "--lora-rank", "4"]);
    let (all8, trained8) = reference_step(&py, &["--mode", "master", "--lora-rank", "8"]);
    // The tiny DiT: 2 blocks of width 96, FFN 256 (common.DIT_TINY); rank r puts r * (in + out)
    // on each of q, k, v, o of both attentions and on ffn.0 / ffn.2.
    let per_rank = 2 * (8 * (96 + 96) + 2 * (96 + 256));
    assert_eq!(all4 - all, 4 * per_rank as u64, "rank-4 adapters");
    assert_eq!(all8 - all, 8 * per_rank as u64, "rank-8 adapters");
    // Only the adapters and the action encoder train; the encoder is what full training trains
    // outside the DiT (all but text_embedding, which the action model never runs).
    assert_eq!(trained8 - trained4, all8 - all4);
    assert!(trained4 < trained, "LoRA trains {trained4} of {all4}, full training {trained} of {all}");
    let encoder = trained4 - (all4 - all);
    assert!(encoder > 0 && encoder < trained4);
}
