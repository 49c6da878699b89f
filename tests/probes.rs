//! Inputs an adversarial user feeds the CLI: each must end in a one-line error that names the
//! problem (or an episode error counted in the results), never a panic, a hang or a half-written
//! output. Loopback only; every command is bounded by its own limits.

mod common;

use std::path::Path;
use std::process::{Command, Output};

use common::{bwm, demo_data, temp_dir, write_cache, write_config, write_random_vae};

fn run(args: &[&str], cwd: &Path) -> Output {
    Command::new(bwm()).args(args).current_dir(cwd).output().unwrap()
}

/// The command failed cleanly: non-zero exit, no panic, and its last stderr line names `what`.
fn fails_naming(out: &Output, what: &[&str]) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "expected a failure:\n{stderr}");
    assert!(!stderr.contains("panicked") && !stderr.contains("RUST_BACKTRACE"), "a panic:\n{stderr}");
    let last = stderr.trim().lines().last().unwrap_or_default();
    assert!(last.starts_with("error: "), "not a one-line error: {last:?}\n{stderr}");
    for w in what {
        assert!(last.contains(w), "{last:?} does not name {w:?}");
    }
}

fn lerobot_without_episodes(root: &Path) {
    std::fs::create_dir_all(root.join("meta")).unwrap();
    std::fs::write(
        root.join("meta/info.json"),
        r#"{"codebase_version": "v2.1", "fps": 10, "total_episodes": 0, "chunks_size": 1000,
            "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
            "features": {"observation.state": {"dtype": "float32", "shape": [4]}}}"#,
    )
    .unwrap();
    std::fs::write(root.join("meta/episodes.jsonl"), "").unwrap();
}

#[test]
fn an_empty_dataset_is_named_by_stats_and_prepare() {
    let dir = temp_dir("probe-empty");
    lerobot_without_episodes(&dir.join("empty"));
    fails_naming(&run(&["stats", "--data", "empty", "--out", "stat.json"], &dir), &["empty", "no episodes"]);
    fails_naming(&run(&["prepare", "--data", "empty", "--random-vae", "--out", "latents"], &dir), &["no episodes"]);
    assert!(!dir.join("stat.json").exists() && !dir.join("latents/index.json").exists());
}

#[test]
fn stats_into_a_folder_that_cannot_be_created_writes_nothing() {
    let dir = temp_dir("probe-unwritable");
    std::fs::write(dir.join("file"), "not a folder").unwrap();
    let out = run(&["stats", "--data", demo_data().to_str().unwrap(), "--out", "file/stat.json"], &dir);
    fails_naming(&out, &["file/"]);
    assert_eq!(std::fs::read_dir(&*dir).unwrap().count(), 1, "nothing but the file is left");
}

#[test]
fn train_names_a_corrupted_cache_index_and_a_truncated_checkpoint() {
    let dir = temp_dir("probe-train");
    std::fs::create_dir_all(dir.join("cache")).unwrap();
    std::fs::write(dir.join("cache/index.json"), "{\"latent_shape\": [").unwrap();
    let config = write_config(&dir, "run.toml", &dir.join("run"), 2, 1);
    fails_naming(&run(&["train", "--config", config.to_str().unwrap()], &dir), &["index.json"]);

    std::fs::remove_dir_all(dir.join("cache")).unwrap();
    write_cache(&dir.join("cache"));
    let ok = run(&["train", "--config", config.to_str().unwrap()], &dir);
    assert!(ok.status.success(), "{}", String::from_utf8_lossy(&ok.stderr));
    let latest = std::fs::read_to_string(dir.join("run/checkpoints/latest")).unwrap();
    let weights = dir.join("run/checkpoints").join(latest.trim()).join("model.safetensors");
    let bytes = std::fs::read(&weights).unwrap();
    std::fs::write(&weights, &bytes[..bytes.len() / 3]).unwrap();
    let more = write_config(&dir, "more.toml", &dir.join("run"), 3, 1);
    fails_naming(&run(&["train", "--config", more.to_str().unwrap(), "--resume", "auto"], &dir), &["model.safetensors"]);
}

#[test]
fn evaluate_counts_a_policy_that_refuses_connections_as_an_episode_error() {
    let dir = temp_dir("probe-evaluate");
    write_random_vae(&dir.join("vae.safetensors"), 3);
    let stats = run(&["stats", "--data", demo_data().to_str().unwrap(), "--out", "stat.json"], &dir);
    assert!(stats.status.success(), "{}", String::from_utf8_lossy(&stats.stderr));
    // Port 9 (discard) on loopback: nothing listens there, so connecting is refused at once.
    std::fs::write(
        dir.join("eval.toml"),
        format!(
            "horizon = 8\nresolution = \"64x32\"\ntimeout_s = 5\n[[policies]]\nname = \"gone\"\nurl = \"ws://127.0.0.1:9\"\n\
             [[tasks]]\nname = \"t\"\ndataset = \"{}\"\nepisodes = [0]\n[judge]\nkind = \"http\"\nurl = \"http://127.0.0.1:9/judge\"\n",
            demo_data().display()
        ),
    )
    .unwrap();
    let evaluate = |stats: &str| {
        Command::new(bwm())
            .args(["evaluate", "--random-weights", "tiny", "--vae", "vae.safetensors", "--stats", stats, "--history", "4", "--future", "4"])
            .args(["--sample-steps", "2", "--device", "cpu", "--config", "eval.toml", "--out", "out"])
            .current_dir(&dir)
            .output()
            .unwrap()
    };
    // Statistics cut short, or of the wrong shape, are named before anything runs.
    std::fs::write(dir.join("cut.json"), "{\"state_pose\": {\"p01\": [1, 2]").unwrap();
    fails_naming(&evaluate("cut.json"), &["cut.json", "not JSON"]);
    let text = std::fs::read_to_string(dir.join("stat.json")).unwrap();
    let mut stats: serde_json::Value = serde_json::from_str(&text).unwrap();
    stats["state_pose"]["p99"].as_array_mut().unwrap().truncate(3);
    std::fs::write(dir.join("short.json"), stats.to_string()).unwrap();
    fails_naming(&evaluate("short.json"), &["short.json", "group 'state_pose'", "has 3 values, 'p01' 14"]);
    assert!(!dir.join("out").exists(), "nothing written for a refused start");

    // The results are written, and the run fails: its one episode ended on a connection error.
    let out = evaluate("stat.json");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("0/1 = 0.000, 1 errors"), "{stdout}");
    assert!(stdout.contains("connection: 1 episode; first: gone / t #0"), "{stdout}");
    let record: serde_json::Value = serde_json::from_str(std::fs::read_to_string(dir.join("out/episodes.jsonl")).unwrap().trim()).unwrap();
    let err = record["error"].as_str().unwrap();
    assert!(err.contains("policy 'gone'") && err.contains("ws://127.0.0.1:9") && err.contains("refused"), "{err}");
}

#[test]
fn a_second_prepare_into_a_folder_being_written_is_refused() {
    let dir = temp_dir("probe-two-prepares");
    let out = dir.join("latents");
    std::fs::create_dir_all(&out).unwrap();
    // The running prepare's claim (rank 0 of 1), held here the way it holds it.
    let held = std::fs::File::create(out.join(".lock.rank-0-of-1")).unwrap();
    held.try_lock().unwrap();
    let data = demo_data();
    let args = ["prepare", "--data", data.to_str().unwrap(), "--random-vae", "--resolution", "64x32", "--history", "4", "--future", "4"];
    let second = Command::new(bwm()).args(args).args(["--device", "cpu", "--out", "latents"]).current_dir(&dir).output().unwrap();
    fails_naming(&second, &["latents", "another `bwm prepare`"]);
    assert!(!out.join("index.json").exists());
    drop(held);
}
