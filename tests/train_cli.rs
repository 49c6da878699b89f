//! `bwm train` end to end as a user runs it (CPU, a synthetic latent cache written through the
//! real cache writer): a `kill -9` in the middle of a checkpoint write leaves the previous
//! checkpoint loadable and `--resume auto` continues from it; the TensorBoard event files are
//! read back by the `tensorboard` package's EventAccumulator with the expected tags and steps.

mod common;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};

use common::{assert_close, bwm, final_weights, free_port, python, temp_dir, write_cache, write_config};

#[test]
fn kill_during_checkpoint_write_then_resume_auto_and_tensorboard_read_back() {
    let dir = temp_dir("train-cli");
    write_cache(&dir.join("cache"));
    let config = write_config(&dir, "run.toml", &dir.join("run"), 3, 1);

    // First run: killed with SIGKILL while it writes its second checkpoint.
    let mut child = Command::new(bwm())
        .args(["train", "--config"])
        .arg(&config)
        .env("BWM_FAULT_SLOW_CHECKPOINT_MS", "3000")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut writes = 0;
    for line in BufReader::new(child.stderr.take().unwrap()).lines() {
        if line.unwrap().starts_with("checkpoint: writing") {
            writes += 1;
            if writes == 2 {
                child.kill().unwrap();
                break;
            }
        }
    }
    child.wait().unwrap();
    assert_eq!(writes, 2);
    let ckpts = dir.join("run/checkpoints");
    let names: Vec<String> = std::fs::read_dir(&ckpts).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().to_string()).collect();
    assert!(names.iter().any(|n| n.starts_with(".step-00000002.tmp")), "a partial checkpoint should be left: {names:?}");
    assert!(names.iter().any(|n| n == ".step-00000002.optimizer-shards"), "the optimizer shards' staging folder should be left: {names:?}");
    assert!(!names.iter().any(|n| n == "step-00000002"), "{names:?}");
    assert_eq!(std::fs::read_to_string(ckpts.join("latest")).unwrap().trim(), "step-00000001");

    // A fresh start is refused; --resume auto continues from step 1.
    let refused = Command::new(bwm()).args(["train", "--config"]).arg(&config).output().unwrap();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--resume auto"));
    let resumed = Command::new(bwm()).args(["train", "--resume", "auto", "--config"]).arg(&config).output().unwrap();
    let stdout = String::from_utf8_lossy(&resumed.stdout);
    assert!(resumed.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&resumed.stderr));
    assert!(stdout.contains("resumed from") && stdout.contains("at step 1"), "{stdout}");
    assert!(stdout.contains("step      3/3"), "{stdout}");
    let names: Vec<String> = std::fs::read_dir(&ckpts).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().to_string()).collect();
    assert!(!names.iter().any(|n| n.contains(".tmp") || n.ends_with(".optimizer-shards")), "stale temporary left: {names:?}");
    assert_eq!(std::fs::read_to_string(ckpts.join("latest")).unwrap().trim(), "step-00000003");

    // TensorBoard: both runs' event files, read by TensorBoard's own reader.
    let script = r#"
import json, sys
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
acc = EventAccumulator(sys.argv[1], size_guidance={"scalars": 0})
acc.Reload()
tags = acc.Tags()["scalars"]
print(json.dumps({t: [e.step for e in acc.Scalars(t)] for t in tags}))
"#;
    let out = Command::new(python()).arg("-c").arg(script).arg(dir.join("run/tensorboard")).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let tags: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for tag in ["train/loss", "train/lr", "train/grad_norm", "perf/tokens_per_s", "perf/tflops"] {
        let mut steps: Vec<u64> = tags[tag].as_array().unwrap_or_else(|| panic!("no {tag} in {tags}")).iter().map(|s| s.as_u64().unwrap()).collect();
        steps.sort();
        steps.dedup();
        assert_eq!(steps, vec![1, 2, 3], "{tag}");
    }
    assert!(tags.as_object().unwrap().keys().any(|k| k.starts_with("loss_by_t/")), "{tags}");
}


/// Ten `kill -9`s, half of them inside checkpoint writes (the fault hook holds each write open)
/// and half at moments drawn from a fixed seed, each followed by `--resume auto`: the final
/// weights equal an uninterrupted run's bit for bit, and no temporary is left behind.
#[test]
fn ten_kills_then_resume_auto_end_with_the_uninterrupted_weights() {
    let dir = temp_dir("train-kills");
    write_cache(&dir.join("cache"));
    let steps = 40;
    let straight = write_config(&dir, "straight.toml", &dir.join("straight"), steps, 1);
    let out = Command::new(bwm()).args(["train", "--config"]).arg(&straight).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));

    let config = write_config(&dir, "killed.toml", &dir.join("killed"), steps, 1);
    let ckpts = dir.join("killed/checkpoints");
    let mut rng = 0x9E37_79B9_7F4A_7C15_u64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    for kill in 0..10 {
        let mut child = Command::new(bwm())
            .args(["train", "--resume", "auto", "--config"])
            .arg(&config)
            .env("BWM_FAULT_SLOW_CHECKPOINT_MS", if kill % 2 == 0 { "1000" } else { "0" })
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // Even runs: inside their second checkpoint write (one step saved, the next half-written).
        // Odd runs: at a drawn moment, during start-up or a few milliseconds after their r-th
        // checkpoint write began (each run gets a few steps at most, so the kills end no run).
        let (writes_before_kill, pause_ms) = match (kill % 2, next() % 4) {
            (0, _) => (2, 0),
            (_, 0) => (0, next() % 500),
            (_, r) => (r, next() % 30),
        };
        let stderr = child.stderr.take().unwrap();
        let mut writes = 0;
        if writes_before_kill > 0 {
            for line in BufReader::new(stderr).lines() {
                if line.unwrap().starts_with("checkpoint: writing") {
                    writes += 1;
                    if writes == writes_before_kill {
                        break;
                    }
                }
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(pause_ms));
        child.kill().unwrap();
        child.wait().unwrap();
        assert_eq!(writes, writes_before_kill, "run {kill} ended before its kill");
    }
    let saved = std::fs::read_to_string(ckpts.join("latest")).unwrap();
    assert!(saved.trim() < format!("step-{steps:08}").as_str(), "the kills must interrupt the run (latest {saved})");

    let out = Command::new(bwm()).args(["train", "--resume", "auto", "--config"]).arg(&config).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("resumed from"), "{stdout}");
    let (a, b) = (final_weights(&dir.join("straight")), final_weights(&dir.join("killed")));
    assert_eq!(a.len(), b.len());
    for ((na, ta), (nb, tb)) in a.iter().zip(&b) {
        assert_eq!(na, nb);
        assert!(ta.equal(tb), "{na} differs from the uninterrupted run's");
    }
    let names: Vec<String> = std::fs::read_dir(&ckpts).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().to_string()).collect();
    assert!(!names.iter().any(|n| n.starts_with('.')), "temporaries left: {names:?}");
}

/// `bwm train` as ranks 0..world of one job (torchrun's variables set by hand), waiting for all.
fn train_ranks(config: &Path, world: usize, resume: &str) {
    let port = free_port().to_string();
    let children: Vec<_> = (0..world)
        .map(|rank| {
            let mut c = Command::new(bwm());
            c.args(["train", "--resume", resume, "--config"]).arg(config);
            if world > 1 {
                c.env("RANK", rank.to_string())
                    .env("WORLD_SIZE", world.to_string())
                    .env("LOCAL_RANK", rank.to_string())
                    .env("MASTER_ADDR", "127.0.0.1")
                    .env("MASTER_PORT", &port)
                    .env("BWM_DIST_TIMEOUT", "60");
            }
            c.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap()
        })
        .collect();
    for (rank, child) in children.into_iter().enumerate() {
        let out = child.wait_with_output().unwrap();
        assert!(out.status.success(), "rank {rank}: {}\n{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    }
}



/// Adds `setting` to the `[train]` section of the config file `path`.
fn set_train(path: &Path, setting: &str) {
    let text = std::fs::read_to_string(path).unwrap().replace("[train]\n", &format!("[train]\n{setting}\n"));
    std::fs::write(path, text).unwrap();
}

/// `bwm train --config CONFIG --set S ...`, which must succeed.
fn train(config: &Path, sets: &[&str]) {
    let mut cmd = Command::new(bwm());
    cmd.args(["train", "--config"]).arg(config);
    for s in sets {
        cmd.args(["--set", s]);
    }
    let out = cmd.output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn two_ranks_train_the_weights_of_one_and_resume_across_world_sizes() {
    let dir = temp_dir("train-dist");
    write_cache(&dir.join("cache"));
    // One process, accumulation 2 == two ranks, accumulation 1: the same global batch of 2.
    let one = write_config(&dir, "one.toml", &dir.join("one"), 3, 2);
    train_ranks(&one, 1, "no");
    let two = write_config(&dir, "two.toml", &dir.join("two"), 3, 1);
    train_ranks(&two, 2, "no");
    assert_close(&final_weights(&dir.join("one")), &final_weights(&dir.join("two")), "2 ranks vs 1");
    // Each rank wrote its half of the optimizer state; replicated state gives the same weights.
    let last = |run: &str| dir.join(run).join("checkpoints").join(std::fs::read_to_string(dir.join(run).join("checkpoints/latest")).unwrap().trim());
    for shard in ["optimizer-00000-of-00002.safetensors", "optimizer-00001-of-00002.safetensors"] {
        assert!(last("two").join(shard).is_file(), "{shard} in {}", last("two").display());
    }
    let replicated = write_config(&dir, "replicated.toml", &dir.join("replicated"), 3, 1);
    set_train(&replicated, "shard_optimizer = false");
    train_ranks(&replicated, 2, "no");
    assert!(last("replicated").join("optimizer-00000-of-00001.safetensors").is_file(), "replicated state is written once");
    assert_close(&final_weights(&dir.join("two")), &final_weights(&dir.join("replicated")), "sharded vs replicated optimizer state");
    // The blocks' gradients are reduced during the backward walk by default; reduced after it,
    // and with accumulation (early reduction on the last micro-step only), the weights agree.
    let after_walk = write_config(&dir, "after_walk.toml", &dir.join("after_walk"), 3, 1);
    set_train(&after_walk, "overlap_grad_reduce = false");
    train_ranks(&after_walk, 2, "no");
    assert_close(&final_weights(&dir.join("two")), &final_weights(&dir.join("after_walk")), "reduction during vs after the walk");
    let four_one = write_config(&dir, "four_one.toml", &dir.join("four_one"), 2, 4);
    train_ranks(&four_one, 1, "no");
    let four_two = write_config(&dir, "four_two.toml", &dir.join("four_two"), 2, 2);
    train_ranks(&four_two, 2, "no");
    assert_close(&final_weights(&dir.join("four_one")), &final_weights(&dir.join("four_two")), "2 ranks x 2 micro-steps vs 1 x 4");
    let metrics = std::fs::read_to_string(dir.join("two/metrics.jsonl")).unwrap();
    for line in metrics.lines() {
        let m: serde_json::Value = serde_json::from_str(line).unwrap();
        assert!(m["collective_s"].as_f64().unwrap() > 0.0, "time in collectives is logged: {line}");
    }
    // The same 2 ranks started by `bwm launch`.
    let launched = write_config(&dir, "launched.toml", &dir.join("launched"), 3, 1);
    let port = free_port().to_string();
    let out = Command::new(bwm())
        .args(["launch", "--nproc-per-node", "2", "--master-port", &port, "--", "train", "--config"])
        .arg(&launched)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}\n{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert_close(&final_weights(&dir.join("one")), &final_weights(&dir.join("launched")), "bwm launch, 2 ranks vs 1");

    // 2 ranks for 2 steps, then 1 rank resumes to step 3; and 1 rank for 2 steps, then 2 ranks.
    let a2 = write_config(&dir, "a2.toml", &dir.join("a"), 2, 1);
    train_ranks(&a2, 2, "no");
    let a3 = write_config(&dir, "a3.toml", &dir.join("a"), 3, 2);
    train_ranks(&a3, 1, "auto");
    assert_close(&final_weights(&dir.join("one")), &final_weights(&dir.join("a")), "2 ranks then 1");
    let b2 = write_config(&dir, "b2.toml", &dir.join("b"), 2, 2);
    train_ranks(&b2, 1, "no");
    let b3 = write_config(&dir, "b3.toml", &dir.join("b"), 3, 1);
    train_ranks(&b3, 2, "auto");
    assert_close(&final_weights(&dir.join("one")), &final_weights(&dir.join("b")), "1 rank then 2");
}

#[test]
fn stats_writes_a_stat_json_that_normalization_reads() {
    let dir = temp_dir("stats-cli");
    let out = dir.join("stat.json");
    let data = bwm_testdir::demo_data();
    let run = Command::new(bwm()).args(["stats", "--data"]).arg(&data).arg("--out").arg(&out).output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let stats = bwm_data::ActionStats::read(&out, "state_pose").unwrap();
    assert_eq!(stats.p01.len(), 14);
    assert!(stats.p01.iter().zip(&stats.p99).all(|(a, b)| a <= b));
}

/// `bwm bench-train` of three steps of the tiny config at 64x32 with `extra` arguments, scratch in
/// `dir`; its stdout, after checking that it succeeded.
fn bench_train_tiny(dir: &Path, extra: &[&std::ffi::OsStr]) -> String {
    let out = Command::new(bwm())
        .args(["bench-train", "--config", "configs/tiny.toml", "--height", "32", "--width", "64", "--history", "4", "--future", "4", "--steps", "3"])
        .args(["--set", "objective.condition_latents=2", "--out"])
        .arg(dir)
        .args(extra)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    stdout
}

#[test]
fn bench_train_breakdown_accounts_for_the_step() {
    let dir = temp_dir("bench-breakdown");
    let stdout = bench_train_tiny(&dir, &["--breakdown".as_ref()]);
    let seconds = |label: &str| -> f64 {
        let line = stdout.lines().find(|l| l.trim_start().starts_with(label)).unwrap_or_else(|| panic!("no '{label}' line in {stdout}"));
        line.trim_start()[label.len()..].split_whitespace().next().unwrap().parse().unwrap()
    };
    let parts = ["attention cores (self + cross)", "linear layers (10 per block)", "norms, modulation, RoPE, gates, adds", "outside the blocks"].map(seconds);
    let step: f64 = stdout.lines().find(|l| l.starts_with("breakdown of a ")).unwrap()["breakdown of a ".len()..].split_whitespace().next().unwrap().parse().unwrap();
    // Timings of a tiny model, printed to the millisecond, can print 0.000: the test checks the
    // structure. Attention and linear layers are sums of measured times; the five figures (each
    // rounded by up to 0.0005 s) account for the whole step.
    assert!(parts[..2].iter().all(|&s| s >= 0.0), "{stdout}");
    assert!((parts.iter().sum::<f64>() - step).abs() <= 0.0025 + 1e-9, "{parts:?} vs {step}: {stdout}");
}

/// `--distill K`: the step timed is the distillation's (a random teacher's Euler steps, then the
/// student's velocity against them), not the flow-matching step of the same weights and data.
#[test]
fn bench_train_times_the_distillation_step() {
    let dir = temp_dir("bench-distill");
    let losses = |stdout: &str| -> Vec<String> {
        stdout.lines().filter(|l| l.starts_with("step ")).map(|l| l.split_whitespace().nth(3).unwrap().to_string()).collect()
    };
    let plain = bench_train_tiny(&dir.join("plain"), &[]);
    let distill = bench_train_tiny(&dir.join("distill"), &["--distill".as_ref(), "1".as_ref(), "--teacher-substeps".as_ref(), "2".as_ref()]);
    assert!(distill.contains("step distillation, a student of 1 step(s) from a frozen teacher of random weights taking 2 Euler steps"), "{distill}");
    let (a, b) = (losses(&plain), losses(&distill));
    assert_eq!((a.len(), b.len()), (3, 3), "{plain}\n{distill}");
    assert_ne!(a, b, "the same losses: the distillation's objective was not used\n{plain}\n{distill}");
    // The teacher's steps are given with a student's only.
    let out = Command::new(bwm()).args(["bench-train", "--teacher-substeps", "2"]).output().unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("--distill"), "{}", String::from_utf8_lossy(&out.stderr));
}

/// `--profile`: the steps after the first go into a Chrome trace of the host's operators (no GPU
/// here, so nothing is busy on one), and the step's summary says so.
#[test]
fn bench_train_profiles_the_steps_after_the_first() {
    let dir = temp_dir("bench-profile");
    let trace = dir.join("trace.json");
    let stdout = bench_train_tiny(&dir, &["--profile".as_ref(), trace.as_os_str()]);
    assert!(stdout.contains("profile of 2 step(s), per step: ") && stdout.contains("GPU busy 0.0 ms (0.0%)"), "{stdout}");
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&trace).unwrap()).unwrap();
    let events = json["traceEvents"].as_array().unwrap();
    let count = |name: &str| events.iter().filter(|e| e["name"] == name).count();
    // Two steps' optimizer updates and backward passes: the AdamW chain's lerp_ runs once per step.
    assert!(count("aten::lerp_") >= 2 && count("aten::lerp_") % 2 == 0, "{} lerp_ events", count("aten::lerp_"));
}

#[test]
fn a_lora_run_exports_and_rolls_out_through_the_cli() {
    let dir = temp_dir("lora-cli");
    write_cache(&dir.join("cache"));
    // The base: one step of full training, exported as a user would download a base model.
    train(&write_config(&dir, "base.toml", &dir.join("base-run"), 1, 1), &[]);
    let base = dir.join("base-export");
    let base_ckpt = dir.join("base-run/checkpoints/step-00000001");
    let out = Command::new(bwm()).args(["export", "--checkpoint"]).arg(&base_ckpt).arg("--out").arg(&base).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let config = write_config(&dir, "run.toml", &dir.join("run"), 2, 1);
    let init = format!(r#"model.init={{from="bwm-checkpoint", path="{}"}}"#, base.display());
    train(&config, &[r#"model.lora={rank=2, alpha=4.0, targets=["blocks.*.ffn.*"]}"#, &init]);
    let ckpt = dir.join("run/checkpoints").join(std::fs::read_to_string(dir.join("run/checkpoints/latest")).unwrap().trim());

    let export = |args: &[&str]| {
        let out = Command::new(bwm()).args(["export", "--checkpoint"]).arg(&ckpt).args(args).output().unwrap();
        (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
    };
    let adapters = dir.join("adapters");
    let (ok, text) = export(&["--out", adapters.to_str().unwrap()]);
    assert!(ok && text.contains("exported the LoRA adapters of"), "{text}");
    let tensors = tch::Tensor::read_safetensors(adapters.join("pytorch_lora_weights.safetensors")).unwrap();
    assert!(!tensors.is_empty() && tensors.len() % 2 == 0, "{} adapter tensors", tensors.len());
    assert!(tensors.iter().all(|(n, _)| n.starts_with("transformer.blocks.") && n.contains(".ffn.net.") && n.contains(".lora_")), "{:?}", tensors.iter().map(|(n, _)| n).collect::<Vec<_>>());
    let config: serde_json::Value = serde_json::from_slice(&std::fs::read(adapters.join("adapter_config.json")).unwrap()).unwrap();
    assert_eq!((config["r"].as_i64(), config["peft_type"].as_str()), (Some(2), Some("LORA")), "{config}");
    // The action encoder trained beside the adapters cannot go into an adapter file: said so.
    assert!(!text.contains("left out") || text.contains("--merge-lora"), "{text}");
    // Flags an adapter file cannot honour are refused, not dropped.
    let (ok, text) = export(&["--ema", "--out", dir.join("ema-adapters").to_str().unwrap()]);
    assert!(!ok && text.contains("--ema: a LoRA checkpoint's adapters are exported alone"), "{text}");

    let merged = dir.join("merged");
    let (ok, text) = export(&["--merge-lora", "--layout", "diffusers", "--out", merged.to_str().unwrap()]);
    assert!(ok, "{text}");
    assert!(merged.join("transformer").is_dir() && merged.join("config.json").is_file(), "{text}");
    let (ok, text) = export(&["--merge-lora", "--push", "someone/model", "--out", dir.join("x").to_str().unwrap()]);
    assert!(!ok, "{text}");
    // `bwm push` uploads a finished export alone (a failed push is retried without exporting
    // again): a folder that is not a complete export, a bad repo id and a missing token are each
    // refused before anything is sent.
    let push = |args: &[&str]| {
        let out = Command::new(bwm()).arg("push").args(args).env_remove("HF_TOKEN").env("HF_HOME", dir.join("no-hf-home")).output().unwrap();
        (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    let (ok, text) = push(&["--dir", dir.join("cache").to_str().unwrap(), "--repo", "someone/model"]);
    assert!(!ok && text.contains("not a complete `bwm export` folder"), "{text}");
    let (ok, text) = push(&["--dir", merged.to_str().unwrap(), "--repo", "someone"]);
    assert!(!ok && text.contains("--repo expects OWNER/NAME"), "{text}");
    let (ok, text) = push(&["--dir", merged.to_str().unwrap(), "--repo", "someone/model"]);
    assert!(!ok && text.contains("HF_TOKEN"), "{text}");

    // The world-model commands take the LoRA checkpoint folder, or the base plus the adapters.
    let roll = |args: &[&str]| {
        let out = Command::new(bwm())
            .arg("bench-rollout")
            .args(args)
            .args(["--random-vae", "--device", "cpu", "--sample-steps", "1", "--height", "32", "--width", "64", "--chunks", "1"])
            .output()
            .unwrap();
        (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
    };
    let (ok, text) = roll(&["--checkpoint", ckpt.to_str().unwrap()]);
    assert!(ok, "{text}");
    let (ok, text) = roll(&["--checkpoint", base.to_str().unwrap(), "--lora", adapters.to_str().unwrap()]);
    assert!(ok, "{text}");
    let (ok, text) = roll(&["--checkpoint", base.to_str().unwrap(), "--lora", dir.join("nope").to_str().unwrap()]);
    assert!(!ok && text.contains("--lora"), "{text}");
}

/// Issue 69 removed `model.action.fourier_bands`, `model.action.temporal_rope` and
/// `objective.motion_weight` (measured worse or without effect, docs/fidelity.md, "Tried and
/// rejected"). A run config, a checkpoint's stored run config and an export's `config.json` written
/// before hold them at their old defaults: they still train, export and roll out. One that switches
/// a key on is refused, naming the key and saying that it was removed and why, before a run folder
/// or export is made.
#[test]
fn removed_keys_load_at_their_old_defaults_and_are_refused_by_name_otherwise() {
    let dir = temp_dir("removed-keys");
    write_cache(&dir.join("cache"));
    let config = write_config(&dir, "run.toml", &dir.join("run"), 1, 1);
    let run = |args: &[&str]| -> (bool, String) {
        let out = Command::new(bwm()).args(args).output().unwrap();
        (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
    };
    let path = |p: &Path| p.to_str().unwrap().to_string();
    for (set, why) in [("model.action.fourier_bands=3", "run 28"), ("model.action.temporal_rope=true", "run 39"), ("objective.motion_weight=4.0", "run 33")] {
        let (ok, text) = run(&["train", "--config", &path(&config), "--set", set]);
        let key = set.split('=').next().unwrap().trim_start_matches("model.");
        assert!(!ok && text.contains(key) && text.contains("was removed") && text.contains(why), "{set}: {text}");
        assert!(!text.contains("panicked") && !dir.join("run").exists(), "{set}: {text}");
    }
    train(&config, &["model.action.fourier_bands=0", "model.action.temporal_rope=false", "objective.motion_weight=0.0"]);

    // The checkpoint's stored config as a run before the removal wrote it.
    let ckpt = dir.join("run/checkpoints/step-00000001");
    let state_path = ckpt.join("state.json");
    let state_text = std::fs::read_to_string(&state_path).unwrap();
    let stored_config = |objective: &str, action: &str| {
        let mut state: serde_json::Value = serde_json::from_str(&state_text).unwrap();
        let config = state["config"].as_str().unwrap();
        assert!(config.contains("[objective]\n") && config.contains("[model.action]\n") && !config.contains("motion_weight"), "{config}");
        let old = config.replace("[objective]\n", &format!("[objective]\n{objective}\n")).replace("[model.action]\n", &format!("[model.action]\n{action}\n"));
        state["config"] = old.into();
        std::fs::write(&state_path, serde_json::to_string_pretty(&state).unwrap()).unwrap();
    };
    let export = |out: &Path| run(&["export", "--checkpoint", &path(&ckpt), "--layout", "diffusers", "--out", &path(out)]);
    stored_config("motion_weight = 4.0", "fourier_bands = 0");
    let (ok, text) = export(&dir.join("refused"));
    assert!(!ok && text.contains("objective.motion_weight = 4") && text.contains("was removed") && !dir.join("refused").exists(), "{text}");
    stored_config("motion_weight = 0.0", "fourier_bands = 0\ntemporal_rope = false");
    let exported = dir.join("export");
    let (ok, text) = export(&exported);
    assert!(ok, "{text}");

    // The export's config.json as an export before the removal wrote it.
    let repo_config = exported.join("config.json");
    let mut json: serde_json::Value = serde_json::from_slice(&std::fs::read(&repo_config).unwrap()).unwrap();
    assert!(json["action"].get("fourier_bands").is_none() && json["action"].get("temporal_rope").is_none(), "{json}");
    let roll = |model: &Path| {
        let sizes = ["--sample-steps", "1", "--height", "32", "--width", "64", "--chunks", "1"];
        run(&[&["bench-rollout", "--checkpoint", &path(model), "--random-vae", "--device", "cpu"][..], &sizes].concat())
    };
    for (bands, ok_wanted) in [(0, true), (3, false)] {
        json["action"]["fourier_bands"] = bands.into();
        json["action"]["temporal_rope"] = false.into();
        std::fs::write(&repo_config, serde_json::to_string_pretty(&json).unwrap()).unwrap();
        let (ok, text) = roll(&exported);
        assert_eq!(ok, ok_wanted, "fourier_bands = {bands}: {text}");
        assert!(ok || (text.contains("action.fourier_bands = 3") && text.contains("was removed") && text.contains("run 28")), "{text}");
    }
}

#[test]
fn fp8_training_follows_the_exact_run_closely_but_not_exactly() {
    let dir = temp_dir("fp8-train");
    write_cache(&dir.join("cache"));
    let losses = |name: &str, sets: &[&str]| -> Vec<f64> {
        train(&write_config(&dir, &format!("{name}.toml"), &dir.join(name), 4, 1), sets);
        let metrics = std::fs::read_to_string(dir.join(name).join("metrics.jsonl")).unwrap();
        metrics.lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["loss"].as_f64().unwrap()).collect()
    };
    let exact = losses("exact", &[]);
    // The tiny model's products are all small: every one in FP8 here.
    let fp8 = losses("fp8", &["train.fp8=true", "train.fp8_min_rows=0"]);
    assert_eq!((exact.len(), fp8.len()), (4, 4));
    for (step, (e, f)) in exact.iter().zip(&fp8).enumerate() {
        assert!(f.is_finite() && ((f - e) / e).abs() < 0.05, "step {}: FP8 loss {f} against {e}", step + 1);
    }
    assert_ne!(exact, fp8, "the FP8 run's products went through float8");
    let (we, wf) = (final_weights(&dir.join("exact")), final_weights(&dir.join("fp8")));
    let moved = we.iter().zip(&wf).filter(|((_, a), (_, b))| !a.equal(b)).count();
    assert!(moved > 0, "FP8 gradients moved the block weights differently");
}

/// The input contract (issue 71): training writes it into every checkpoint from what its cache
/// records, `bwm info --checkpoint` shows it, `bwm export` carries it (with `--action-stats`'
/// normalization), and the world-model commands take their defaults from it and refuse what
/// contradicts it, in one line naming the value and the contract's: an action definition of
/// another width, another frame size, another history length.
#[test]
fn training_writes_the_input_contract_and_the_commands_hold_to_it() {
    let dir = temp_dir("contract");
    write_cache(&dir.join("cache"));
    train(&write_config(&dir, "run.toml", &dir.join("run"), 1, 1), &[]);
    let ckpt = dir.join("run/checkpoints/step-00000001");
    let contract: serde_json::Value = serde_json::from_slice(&std::fs::read(ckpt.join("contract.json")).unwrap()).unwrap();
    // The cache of `write_cache`: 14-D actions, 64x64 frames at 30 fps, H 8, K 4.
    assert_eq!(contract["actions"]["dim"], 14, "{contract}");
    assert_eq!((contract["frames"]["width"].as_u64(), contract["frames"]["height"].as_u64(), contract["frames"]["fps"].as_f64()), (Some(64), Some(64), Some(30.0)), "{contract}");
    assert_eq!((contract["chunk"]["history"].as_u64(), contract["chunk"]["future"].as_u64()), (Some(8), Some(4)), "{contract}");
    assert!(contract["sampler"].is_null() && contract["observation_keys"]["serve POST /v1/chunk"].is_array(), "{contract}");

    let run = |args: &[&std::ffi::OsStr]| {
        let out = Command::new(bwm()).args(args).output().unwrap();
        (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
    };
    let os = |s: &str| std::ffi::OsString::from(s);
    let (ok, text) = run(&[&os("info"), &os("--checkpoint"), ckpt.as_os_str()]);
    assert!(ok && text.contains("actions: 14 values per frame") && text.contains("frames: 64x64") && text.contains("x0 + 8 history frames, 4 generated"), "{text}");

    let stats = common::demo_data().join("stat.json");
    let export = dir.join("export");
    let (ok, text) = run(&[&os("export"), &os("--checkpoint"), ckpt.as_os_str(), &os("--action-stats"), stats.as_os_str(), &os("--out"), export.as_os_str()]);
    assert!(ok, "{text}");
    let exported: serde_json::Value = serde_json::from_slice(&std::fs::read(export.join("contract.json")).unwrap()).unwrap();
    assert_eq!((&exported["frames"], &exported["chunk"]), (&contract["frames"], &contract["chunk"]), "{exported}");
    assert_eq!(exported["actions"]["normalization"]["group"], "state_pose", "{exported}");
    let (ok, text) = run(&[&os("info"), &os("--checkpoint"), export.as_os_str(), &os("--json")]);
    assert!(ok && serde_json::from_str::<serde_json::Value>(&text).unwrap() == exported, "{text}");

    // A rollout of the bundled episodes (14-D eef_abs actions): one line naming what contradicts
    // the contract, before any episode is read.
    let rollout = |extra: &[&str]| {
        let mut args: Vec<std::ffi::OsString> = ["rollout", "--checkpoint"].map(os).to_vec();
        args.push(export.clone().into_os_string());
        args.extend(["--random-vae", "--device", "cpu", "--sample-steps", "1", "--max-frames", "5", "--episodes", "0", "--data"].map(os));
        args.push(common::demo_data().into_os_string());
        args.push(os("--out"));
        args.push(dir.join("rollout").into_os_string());
        args.extend(extra.iter().map(|s| os(s)));
        run(&args.iter().map(|s| s.as_os_str()).collect::<Vec<_>>())
    };
    let refused = |extra: &[&str], wanted: &[&str]| {
        let (ok, text) = rollout(extra);
        let error = text.lines().find(|l| l.starts_with("error:")).unwrap_or_default().to_string();
        assert!(!ok && wanted.iter().all(|w| error.contains(w)), "{extra:?}: {text}");
    };
    refused(&["--actions", "observation.state:0-6"], &["--actions observation.state:0-6: 7-D actions, but this model takes 14-D actions"]);
    refused(&["--resolution", "128x128"], &["--resolution 128x128: 128x128 frames, but this model was trained on 64x64"]);
    refused(&["--history", "4"], &["--history 4: this model was trained with 8"]);
    // What the contract says is taken without flags: the export's statistics normalize the raw
    // actions, frames come at 64x64.
    let (ok, text) = rollout(&[]);
    assert!(ok && text.contains("action statistics: the weights' input contract (group 'state_pose')"), "{text}");
}
