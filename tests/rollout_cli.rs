//! `bwm rollout` (data engine) end to end on CPU: the tiny model with random weights and a small
//! random VAE drive episode 0 of the bundled dataset with its recorded actions; the output is a
//! LeRobot v2.1 dataset that pyarrow and ffprobe read (frame count = row count, actions equal to
//! the recorded ones row by row, source fps), that the project's own LeRobot reader opens, with a
//! side-by-side video and PSNR/SSIM; `--resume` adds episodes without touching finished ones.

mod common;

use std::process::Command;

use bwm_data::{open_dataset, CameraSelection};
use bwm_data::ActionSpec;
use common::{bwm, demo_data, python, temp_dir, tiny_world_model, write_random_vae};





fn rollout(args: &[&str]) -> std::process::Output {
    tiny_world_model("rollout", &[&["--max-frames", "11"], args].concat())
}

#[test]
fn data_engine_writes_a_lerobot_dataset_aligned_row_by_row() {
    let dir = temp_dir("rollout-cli");
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 5);
    let data = demo_data();
    let out = dir.join("generated");
    let common = ["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap()];
    let first = rollout(&[&common[..], &["--episodes", "0"]].concat());
    assert!(first.status.success());

    // The recorded actions of episode 0, as the model was driven with them.
    let source = open_dataset(&data).unwrap();
    let recorded = source.vectors(0, &ActionSpec::eef_abs()).unwrap();
    let fps = source.fps(0).unwrap();

    let check = format!(
        r#"
import json, subprocess, sys, pyarrow.parquet as pq
root = sys.argv[1]
t = pq.read_table(f"{{root}}/data/chunk-000/episode_000000.parquet").to_pydict()
info = json.load(open(f"{{root}}/meta/info.json"))
assert info["codebase_version"] == "v2.1" and info["total_episodes"] == 1 and info["total_frames"] == 11, info
assert t["frame_index"] == list(range(11)) and t["index"] == list(range(11)), t["frame_index"]
assert all(abs(ts - i / {fps}) < 1e-4 for i, ts in enumerate(t["timestamp"]))
video = f"{{root}}/videos/chunk-000/observation.images.generated/episode_000000.mp4"
probe = subprocess.run(["ffprobe", "-v", "error", "-count_frames", "-select_streams", "v:0", "-show_entries",
    "stream=nb_read_frames,width,height,r_frame_rate", "-of", "json", video], capture_output=True, text=True, check=True)
s = json.loads(probe.stdout)["streams"][0]
num, den = map(int, s["r_frame_rate"].split("/"))
assert int(s["nb_read_frames"]) == len(t["action"]) == 11 and (s["width"], s["height"]) == (64, 32), s
assert abs(num / den - {fps}) < 1e-3, s
print(json.dumps(t["action"]))
"#
    );
    let py = Command::new(python()).args(["-c", &check, out.to_str().unwrap()]).output().unwrap();
    assert!(py.status.success(), "{}", String::from_utf8_lossy(&py.stderr));
    let actions: Vec<Vec<f32>> = serde_json::from_slice(&py.stdout).unwrap();
    assert_eq!(actions.len(), 11);
    for (t, (a, r)) in actions.iter().zip(&recorded).enumerate() {
        assert!(a.iter().zip(r).all(|(x, y)| (x - y).abs() < 1e-6), "row {t}: {a:?} vs recorded {r:?}");
    }

    // The project's own LeRobot reader opens it; frame 0 is the real x0.
    let generated = open_dataset(&out).unwrap();
    assert_eq!(generated.episodes()[0].length, 11);
    let frames = generated.frames(0, 0..11, &CameraSelection::default()).unwrap();
    assert_eq!(frames.len(), 11);
    let metrics = std::fs::read_to_string(out.join("compare/metrics.jsonl")).unwrap();
    let m: serde_json::Value = serde_json::from_str(metrics.lines().next().unwrap()).unwrap();
    assert!(m["psnr"].as_f64().unwrap().is_finite() && m["ssim"].as_f64().is_some(), "{m}");
    assert!(out.join("compare/episode_000000.mp4").exists());

    // A fresh run refuses to overwrite; --resume adds episode 1 and keeps episode 0's files.
    let before = std::fs::read(out.join("data/chunk-000/episode_000000.parquet")).unwrap();
    let again = rollout(&[&common[..], &["--episodes", "0,1"]].concat());
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("already holds a dataset"));
    // --resume with a list that does not begin with the episode written, or with other sampler
    // settings, is refused: it would relabel episode 0 as another's.
    for other in [&["--episodes", "1,0", "--resume"][..], &["--episodes", "0,1", "--seed", "3", "--resume"][..]] {
        let refused = rollout(&[&common[..], other].concat());
        let said = String::from_utf8_lossy(&refused.stderr);
        assert!(!refused.status.success() && said.contains("its 1 episodes were rolled out from other weights or settings"), "{other:?}: {said}");
    }
    let resumed = rollout(&[&common[..], &["--episodes", "0,1", "--resume"]].concat());
    assert!(resumed.status.success());
    assert_eq!(open_dataset(&out).unwrap().episodes().len(), 2);
    assert_eq!(before, std::fs::read(out.join("data/chunk-000/episode_000000.parquet")).unwrap());

    // Episodes 0 and 1 generated together (one batch per chunk): each scores what it scores alone.
    let together = dir.join("together");
    let t = rollout(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", together.to_str().unwrap(), "--episodes", "0,1", "--episodes-in-flight", "2"]);
    assert!(t.status.success());
    assert!(String::from_utf8_lossy(&t.stdout).contains("2 episode(s) in flight"));
    let scores = |root: &std::path::Path| -> Vec<(String, f64)> {
        std::fs::read_to_string(root.join("compare/metrics.jsonl"))
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .map(|m| (m["source"].as_str().unwrap().to_string(), m["psnr"].as_f64().unwrap()))
            .collect()
    };
    let (alone, batched) = (scores(&out), scores(&together));
    assert_eq!(alone.len(), 2);
    assert_eq!(alone.iter().map(|s| &s.0).collect::<Vec<_>>(), batched.iter().map(|s| &s.0).collect::<Vec<_>>(), "written in order");
    for (a, b) in alone.iter().zip(&batched) {
        assert!((a.1 - b.1).abs() < 1e-3, "{}: PSNR {} alone, {} together", a.0, a.1, b.1);
    }

    // Perturbed actions stay within the recorded range's normalization and differ from it; this
    // dataset stores its frames as PNG cells in the parquet (what a build without video writes),
    // losslessly: its x0 is the video dataset's x0 as decoded from the source, pixel for pixel.
    let perturbed = dir.join("perturbed");
    let p = rollout(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", perturbed.to_str().unwrap(), "--episodes", "0", "--drive", "perturbed", "--perturb-std", "0.1", "--frame-storage", "image"]);
    assert!(p.status.success());
    assert!(String::from_utf8_lossy(&p.stdout).contains("frames stored as image features"));
    assert!(!perturbed.join("videos").exists());
    let got = open_dataset(&perturbed).unwrap();
    let x0 = source.frames(0, 0..1, &CameraSelection::default()).unwrap();
    let x0 = bwm_data::frames::fit(&x0[0], 64, 32, bwm_data::frames::ResizeMode::default());
    let cells = got.frames(0, 0..11, &CameraSelection::default()).unwrap();
    assert_eq!(cells.len(), 11);
    assert!(cells[0] == x0, "x0 changed on its way through the PNG cell");
    let spec = ActionSpec { column: "action".into(), indices: (0..14).collect(), stats_group: "state_pose".into(), quat_to_euler: vec![], absolute_to_delta: vec![] };
    let rows = got.vectors(0, &spec).unwrap();
    assert!(rows.iter().zip(&recorded).any(|(a, r)| a.iter().zip(r).any(|(x, y)| (x - y).abs() > 1e-4)));

    // DPM-Solver++(2M) in place of Euler: the same episode, other frames (its last step is second
    // order); an unknown solver is refused by name.
    let dpm = dir.join("dpm");
    let d = rollout(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", dpm.to_str().unwrap(), "--episodes", "0", "--solver", "dpm++2m"]);
    assert!(d.status.success());
    let psnr = |root: &std::path::Path| -> f64 {
        let text = std::fs::read_to_string(root.join("compare/metrics.jsonl")).unwrap();
        serde_json::from_str::<serde_json::Value>(text.lines().next().unwrap()).unwrap()["psnr"].as_f64().unwrap()
    };
    assert!(psnr(&dpm).is_finite() && psnr(&dpm) != psnr(&out), "dpm++2m {} vs euler {}", psnr(&dpm), psnr(&out));
    let bad = rollout(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", dir.join("bad").to_str().unwrap(), "--solver", "unipc"]);
    assert!(!bad.status.success() && String::from_utf8_lossy(&bad.stderr).contains("dpm++2m"));

    // Bad input: clear errors, nothing written.
    let bad = rollout(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", dir.join("bad").to_str().unwrap(), "--drive", "file"]);
    assert!(!bad.status.success() && String::from_utf8_lossy(&bad.stderr).contains("--actions-dir"));
    let bad = rollout(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", dir.join("bad").to_str().unwrap(), "--episodes", "7"]);
    assert!(!bad.status.success() && String::from_utf8_lossy(&bad.stderr).contains("3 episodes"));
    assert!(!dir.join("bad/meta/info.json").exists());
}

/// A --resolution no memory can hold is an error naming it, before any frame is resized (the
/// resize's allocation would abort the process) and before the output is created.
#[test]
fn an_impossible_resolution_is_an_error_naming_it() {
    let dir = temp_dir("rollout-huge");
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 5);
    let out = dir.join("generated");
    let run = Command::new(bwm())
        .arg("rollout")
        .args(["--random-weights", "tiny", "--history", "4", "--future", "4", "--sample-steps", "1", "--resolution", "1048576x1048576", "--device", "cpu"])
        .args(["--max-frames", "5", "--episodes", "0", "--vae", vae.to_str().unwrap(), "--data", demo_data().to_str().unwrap(), "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{err}");
    assert!(err.contains("1048576x1048576") && err.contains("cannot be allocated"), "the error names the size: {err}");
    assert!(!out.exists(), "nothing was written");
}
