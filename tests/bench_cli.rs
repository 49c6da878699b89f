//! `bwm info`, the inference benchmarks and `bwm demo` end to end on the CPU at tiny sizes: each
//! runs its real path (random weights, the bundled episodes) and prints what its docs promise.
//! The timings themselves are not checked, only that the measurements are there and consistent.

mod common;

use std::process::Command;

use common::{bwm, demo_data, temp_dir, write_random_vae};

/// Runs `bwm ARGS` and returns its standard output; fails the test on a non-zero exit.
fn run(args: &[&str]) -> String {
    let out = Command::new(bwm()).args(args).current_dir(env!("CARGO_MANIFEST_DIR")).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "bwm {args:?}:\n{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    stdout
}

fn line<'a>(stdout: &'a str, prefix: &str) -> &'a str {
    stdout.lines().find(|l| l.trim_start().starts_with(prefix)).unwrap_or_else(|| panic!("no line starting '{prefix}' in:\n{stdout}"))
}

/// The number after `label` on `line`.
fn number_after(line: &str, label: &str) -> f64 {
    let at = line.find(label).unwrap_or_else(|| panic!("no '{label}' in '{line}'")) + label.len();
    line[at..].split_whitespace().next().unwrap().trim_end_matches(['s', ',']).parse().unwrap_or_else(|e| panic!("'{line}' after '{label}': {e}"))
}

#[test]
fn info_counts_add_up_to_the_total() {
    let out = run(&["info", "--preset", "tiny"]);
    let dit = number_after(line(&out, "DiT:"), "tensors");
    let action = number_after(line(&out, "action encoder:"), "tensors");
    let total = number_after(line(&out, "total:"), "tensors");
    assert!(dit > 0.0 && action > 0.0 && dit + action == total, "{out}");
}

#[test]
fn bench_forward_reports_the_clip_and_its_iterations() {
    let out = run(&["bench-forward", "--preset", "tiny", "--device", "cpu", "--dtype", "f32", "--frames", "9", "--height", "64", "--width", "64", "--warmup", "1", "--iters", "2"]);
    let l = line(&out, "bench-forward");
    // 9 frames -> 3 latent frames of 4x4, 1x2x2 patches: 3 x 2 x 2 tokens.
    assert!(l.contains("dtype=f32 clip=9x64x64 latents=[1,48,3,4,4] tokens=12"), "{l}");
    assert!(l.contains("over 2 iters"), "{l}");
    assert!(number_after(l, "mean") >= number_after(l, "min"), "{l}");
}

#[test]
fn bench_vae_encodes_decodes_and_streams() {
    let out = run(&["bench-vae", "--device", "cpu", "--dtype", "f32", "--frames", "5", "--height", "32", "--width", "32", "--iters", "1", "--stream-seconds", "1", "--fps", "8"]);
    assert!(line(&out, "bench-vae iter 0:").contains("encode 5x32x32 f32 -> [1, 48, 2, 2, 2]"), "{out}");
    // 8 frames at 8 fps: 1 + 4k latent chunks give 9 frames (the first chunk decodes to one).
    assert!(line(&out, "stream-decode:").starts_with("stream-decode: 9 frames"), "{out}");
}

#[test]
fn bench_rollout_times_each_chunk() {
    let dir = temp_dir("bench-rollout");
    let vae = dir.path().join("vae.safetensors");
    write_random_vae(&vae, 3);
    let out = run(&[
        "bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--height", "32", "--width", "32", "--history", "4", "--future", "4",
        "--sample-steps", "2", "--chunks", "2",
    ]);
    assert!(line(&out, "bench-rollout:").contains("1 rollout(s) at once in 1 stream(s), x0 + 4 history frames, 4 frames per chunk, 2 euler steps, attention backend auto"), "{out}");
    for i in 0..2 {
        let l = line(&out, &format!("chunk {i}:"));
        assert!(l.contains("; 4 frames;"), "{l}");
        let parts = ["encode", "DiT", "decode"].map(|p| number_after(l, &format!("{p} ")));
        assert!(number_after(l, &format!("chunk {i}:")) + 0.02 + 1e-9 >= parts.iter().sum::<f64>(), "the parts exceed the chunk: {l}");
    }
    // Several rollouts advance as one batch per chunk.
    let out = run(&[
        "bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--height", "32", "--width", "32", "--history", "4", "--future", "4",
        "--sample-steps", "2", "--chunks", "1", "--batch", "3",
    ]);
    assert!(line(&out, "bench-rollout:").contains("3 rollout(s) at once"), "{out}");
    assert!(line(&out, "chunk 0:").contains("; 4 frames;"), "{out}");
    let failed = Command::new(bwm()).args(["bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--batch", "0"]).output().unwrap();
    assert!(!failed.status.success() && String::from_utf8_lossy(&failed.stderr).contains("--batch must be at least 1"), "{failed:?}");
    // In two lanes taking turns: each chunk's line says when the last lane finished it.
    let out = run(&[
        "bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--height", "32", "--width", "32", "--history", "4", "--future", "4",
        "--sample-steps", "2", "--chunks", "2", "--batch", "3", "--streams", "2",
    ]);
    assert!(line(&out, "bench-rollout:").contains("3 rollout(s) at once in 2 stream(s)"), "{out}");
    assert!(line(&out, "chunk 0:").contains("all 3 rollouts' frames at") && line(&out, "chunk 0:").contains("after the start"), "{out}");
    assert!(line(&out, "chunk 1:").contains("after chunk 0's"), "{out}");
    let failed = Command::new(bwm())
        .args(["bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--batch", "1", "--streams", "2"])
        .output()
        .unwrap();
    assert!(!failed.status.success() && String::from_utf8_lossy(&failed.stderr).contains("cannot fill 2 streams"), "{failed:?}");
}

/// Sizes no memory can hold are errors naming them (exit 1), not panics (exit 101): on the CPU the
/// first allocation they size fails at once, before any memory is touched.
#[test]
fn impossible_clip_sizes_are_errors_naming_them_not_panics() {
    let dir = temp_dir("bench-impossible");
    let vae = dir.path().join("vae.safetensors");
    write_random_vae(&vae, 3);
    let huge = "1048576";
    let forward = ["bench-forward", "--preset", "tiny", "--device", "cpu", "--dtype", "f32", "--height", huge, "--width", huge, "--warmup", "0", "--iters", "1"];
    let rollout = [
        "bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--height", huge, "--width", huge, "--history", "4", "--future", "4",
        "--sample-steps", "1", "--chunks", "1",
    ];
    for args in [&forward[..], &rollout[..]] {
        let out = Command::new(bwm()).args(args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "bwm {args:?}: {err}");
        assert!(err.contains("1048576x1048576") && err.contains("cannot be allocated"), "the error names the size: {err}");
        assert!(!err.contains("panicked"), "{err}");
    }
}

#[test]
fn bench_rollout_runs_the_block_linears_in_fp8_when_asked() {
    let dir = temp_dir("bench-rollout-fp8");
    let vae = dir.path().join("vae.safetensors");
    write_random_vae(&vae, 3);
    let args = |fp8: &'static str| {
        vec![
            "bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--height", "32", "--width", "32", "--history", "4",
            "--future", "4", "--sample-steps", "2", "--chunks", "1", "--fp8", fp8,
        ]
    };
    let out = run(&args("tensor"));
    assert!(line(&out, "bench-rollout:").ends_with("block linears in FP8 (tensor scaling), sampler forward eager, decoded by the VAE's decoder"), "{out}");
    assert!(line(&out, "chunk 0:").contains("; 4 frames;"), "{out}");
    let failed = Command::new(bwm()).args(args("row")).output().unwrap();
    let err = String::from_utf8_lossy(&failed.stderr);
    assert!(!failed.status.success() && err.contains("--fp8") && err.contains("needs a CUDA device"), "{err}");
    let mut graphed = args("tensor");
    graphed.push("--cuda-graph");
    let failed = Command::new(bwm()).args(graphed).output().unwrap();
    let err = String::from_utf8_lossy(&failed.stderr);
    assert!(!failed.status.success() && err.contains("--cuda-graph needs a CUDA device"), "{err}");
}

#[test]
fn bench_rollout_runs_on_the_attention_backend_asked_for() {
    let dir = temp_dir("bench-rollout-sdp");
    let vae = dir.path().join("vae.safetensors");
    write_random_vae(&vae, 3);
    let args = |backend: &'static str| {
        vec![
            "--sdp-backend", backend, "bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--height", "32", "--width", "32",
            "--history", "4", "--future", "4", "--sample-steps", "1", "--chunks", "1",
        ]
    };
    let out = run(&args("math"));
    assert!(line(&out, "bench-rollout:").contains("attention backend math (math)"), "{out}");
    // cuDNN has no CPU kernel: the math path takes the attentions, and the header says so.
    let out = run(&args("cudnn"));
    assert!(line(&out, "bench-rollout:").contains("attention backend cudnn (math)"), "{out}");
    let out = Command::new(bwm()).args(args("flash3")).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("unknown attention backend 'flash3'"), "{err}");
}

#[test]
fn bench_rollout_runs_with_the_cpu_threads_asked_for() {
    let dir = temp_dir("bench-rollout-threads");
    let vae = dir.path().join("vae.safetensors");
    write_random_vae(&vae, 3);
    let rollout = ["bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--height", "32", "--width", "32", "--history", "4", "--future", "4", "--sample-steps", "1", "--chunks", "1"];
    let threads = |flag: Option<&str>, env: &[(&str, &str)]| {
        let mut cmd = Command::new(bwm());
        cmd.env_remove("OMP_NUM_THREADS").env_remove("BWM_CPU_THREADS").envs(env.iter().copied());
        if let Some(n) = flag {
            cmd.args(["--cpu-threads", n]);
        }
        let out = cmd.args(rollout).output().unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
        number_after(line(&stdout, "bench-rollout:"), "libtorch CPU threads ")
    };
    assert_eq!(threads(Some("1"), &[]), 1.0);
    assert_eq!(threads(None, &[("BWM_CPU_THREADS", "3")]), 3.0);
    // Without the flag and without a CUDA device, libtorch's own choice stands, OMP_NUM_THREADS included.
    assert_eq!(threads(None, &[("OMP_NUM_THREADS", "2")]), 2.0);
    assert_eq!(threads(Some("1"), &[("OMP_NUM_THREADS", "2")]), 1.0);
    let out = Command::new(bwm()).args(["--cpu-threads", "0"]).args(rollout).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("--cpu-threads"), "{err}");
}

#[test]
fn bench_rollout_samples_with_the_default_steps_and_takes_cudnn_autotuning() {
    let dir = temp_dir("bench-rollout-defaults");
    let vae = dir.path().join("vae.safetensors");
    write_random_vae(&vae, 3);
    let out = Command::new(bwm())
        .args([
            "--cudnn-benchmark", "bench-rollout", "--random-weights", "tiny", "--vae", vae.to_str().unwrap(), "--device", "cpu", "--height", "32", "--width", "32",
            "--history", "4", "--future", "4", "--chunks", "1",
        ])
        .output()
        .unwrap();
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{stdout}\n{stderr}");
    // Random weights record no sampler: the reference's 50 Euler steps, and the command says so.
    let steps = bwm_checkpoints::sampler::UNRECORDED_STEPS;
    assert!(line(&stdout, "bench-rollout:").contains(&format!("4 frames per chunk, {steps} euler steps")), "{stdout}");
    assert!(stdout.contains("these weights record no sampler"), "{stdout}");
    assert!(stderr.contains("cuDNN convolution autotuning on"), "{stderr}");
}

#[test]
fn demo_samples_the_clip_and_keeps_the_condition() {
    let data = demo_data();
    let out = run(&["demo", "--data", data.to_str().unwrap(), "--steps", "3"]);
    assert!(out.contains("clip: x0 + 8 history + 8 future frames = 17 action frames"), "{out}");
    assert_eq!(out.lines().filter(|l| l.trim_start().starts_with("step ")).count(), 3, "{out}");
    assert!(line(&out, "condition prefix kept exactly").ends_with("max |diff| = 0e0"), "{out}");
    let err = Command::new(bwm()).args(["demo", "--data", data.to_str().unwrap(), "--episode", "99"]).output().unwrap();
    assert!(!err.status.success() && String::from_utf8_lossy(&err.stderr).contains("--episode 99 out of range"), "{err:?}");
}
