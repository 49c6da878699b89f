//! `bwm fidelity` end to end on CPU: the tiny model with random weights and a small random VAE
//! roll out three bundled episodes driven by their own and by another's actions. The report's
//! copy-last-frame scores are checked against PSNR computed here from the dataset's frames, the
//! horizon means and margins against the per-frame scores it lists, and its files must exist.

mod common;

use bwm_data::frames::{fit, frames_to_tensor};
use bwm_data::{open_dataset, CameraSelection};
use bwm_data::ResizeMode;
use bwm_metrics::image::psnr;
use common::{demo_data, temp_dir, tiny_world_model, write_random_vae};
use serde_json::Value;

fn fidelity(args: &[&str]) -> std::process::Output {
    tiny_world_model("fidelity", &[&["--max-frames", "9", "--horizons", "4,8", "--videos", "1"], args].concat())
}

#[test]
fn fidelity_report_scores_rollouts_and_baselines_per_frame_and_horizon() {
    let dir = temp_dir("fidelity-cli");
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 5);
    let data = demo_data();
    let out = dir.join("report");
    let run = fidelity(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(run.status.success());

    let report: Value = serde_json::from_str(&std::fs::read_to_string(out.join("fidelity.json")).unwrap()).unwrap();
    assert_eq!(report["episodes"], 3);
    assert_eq!(report["solver"], "euler", "the sampler is recorded: {report}");
    let lines: Vec<Value> = std::fs::read_to_string(out.join("episodes.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len(), 3);

    // Copy-last-frame: x0 against each real frame, as computed here from the dataset.
    let source = open_dataset(&data).unwrap();
    let real: Vec<_> = source.frames(0, 0..9, &CameraSelection::default()).unwrap().iter().map(|f| fit(f, 64, 32, ResizeMode::Crop)).collect();
    let real = frames_to_tensor(&real).unwrap();
    let x0 = real.narrow(1, 0, 1);
    let copy = lines[0]["psnr"]["copy_last_frame"].as_array().unwrap();
    assert_eq!(copy.len(), 8);
    for (k, v) in copy.iter().enumerate() {
        let want = psnr(&x0, &real.narrow(1, k as i64 + 1, 1));
        assert!((v.as_f64().unwrap() - want).abs() < 1e-6, "frame {}: {v} vs {want}", k + 1);
    }
    assert_eq!(lines[0]["other_episode_index"], 1);
    assert_eq!(lines[2]["other_episode_index"], 0);

    // Horizon 4: the mean over frames 1..4 of each episode, then over episodes; margins are differences.
    let task = source.episodes()[0].task.clone();
    let summary = &report["tasks"][&task];
    for predictor in ["model", "other_actions", "zero_actions", "copy_last_frame"] {
        let want: f64 = lines.iter().map(|l| l["psnr"][predictor].as_array().unwrap()[..4].iter().map(|v| v.as_f64().unwrap()).sum::<f64>() / 4.0).sum::<f64>() / 3.0;
        let got = summary["horizons"]["4"][predictor]["psnr"].as_f64().unwrap();
        assert!((got - want).abs() < 1e-9, "{predictor}: {got} vs {want}");
    }
    let h4 = &summary["horizons"]["4"];
    let margin = summary["margins"]["4"]["psnr_over_copy_last_frame_db"].as_f64().unwrap();
    assert!((margin - (h4["model"]["psnr"].as_f64().unwrap() - h4["copy_last_frame"]["psnr"].as_f64().unwrap())).abs() < 1e-9);
    let zero = summary["margins"]["4"]["psnr_over_zero_actions_db"].as_f64().unwrap();
    assert!((zero - (h4["model"]["psnr"].as_f64().unwrap() - h4["zero_actions"]["psnr"].as_f64().unwrap())).abs() < 1e-9);
    assert!(summary["horizons"]["full"]["model"]["ssim"].as_f64().unwrap().is_finite());
    assert_eq!(report["all"]["episodes"], 3);

    for f in [format!("psnr_{task}.svg"), format!("ssim_{task}.svg")] {
        assert!(out.join(&f).is_file(), "{f} missing");
    }
    let videos: Vec<_> = std::fs::read_dir(out.join("videos")).unwrap().collect();
    assert_eq!(videos.len(), 1, "one side-by-side video per task (--videos 1)");

    // Episodes rolled out two at a time (six rollouts: own, other and zero actions each, then
    // three) in three lanes taking turns score what they score alone.
    let together = fidelity(&[
        "--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", dir.join("together").to_str().unwrap(), "--episodes-in-flight", "2", "--streams", "3",
    ]);
    assert!(together.status.success(), "{}", String::from_utf8_lossy(&together.stderr));
    assert!(String::from_utf8_lossy(&together.stdout).contains("for 2 episodes together"));
    assert!(String::from_utf8_lossy(&together.stdout).contains("2 episode(s) in flight in 3 stream(s)"));
    let too_many = fidelity(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", dir.join("lanes").to_str().unwrap(), "--streams", "4"]);
    assert!(!too_many.status.success());
    assert!(String::from_utf8_lossy(&too_many.stderr).contains("3 episode(s) in flight cannot fill 4 streams"), "{}", String::from_utf8_lossy(&too_many.stderr));
    let together: Vec<Value> =
        std::fs::read_to_string(dir.join("together/episodes.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(together.len(), 3);
    for (a, b) in lines.iter().zip(&together) {
        assert_eq!(a["episode_index"], b["episode_index"]);
        for predictor in ["model", "other_actions", "zero_actions"] {
            for (x, y) in a["psnr"][predictor].as_array().unwrap().iter().zip(b["psnr"][predictor].as_array().unwrap()) {
                assert!((x.as_f64().unwrap() - y.as_f64().unwrap()).abs() < 1e-3, "episode {} {predictor}: {x} alone, {y} together", a["episode_index"]);
            }
        }
    }

    // A run cut short (two episodes scored, the third line half written) resumes: the scored
    // episodes are kept, the rest rolled out, and the report equals the uninterrupted one.
    let text = std::fs::read_to_string(out.join("episodes.jsonl")).unwrap();
    let kept: Vec<&str> = text.lines().take(2).collect();
    std::fs::write(out.join("episodes.jsonl"), format!("{}\n{}", kept.join("\n"), &text.lines().nth(2).unwrap()[..40])).unwrap();
    std::fs::remove_file(out.join("fidelity.json")).unwrap();
    let resumed = fidelity(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(resumed.status.success());
    let said = String::from_utf8_lossy(&resumed.stdout).into_owned();
    assert!(said.contains("resuming: 2 of 3 episodes already scored"), "{said}");
    assert_eq!(said.matches("PSNR model").count(), 1, "only the third episode is rolled out again: {said}");
    let again: Value = serde_json::from_str(&std::fs::read_to_string(out.join("fidelity.json")).unwrap()).unwrap();
    assert_eq!(again["all"], report["all"], "the resumed report equals the uninterrupted one");
    assert_eq!(again["tasks"], report["tasks"]);
    assert_eq!(std::fs::read_to_string(out.join("episodes.jsonl")).unwrap().lines().count(), 3);
    // Other settings into the same folder start over.
    let other = fidelity(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap(), "--seed", "7"]);
    assert!(other.status.success());
    let said = String::from_utf8_lossy(&other.stdout).into_owned();
    assert!(said.contains("scored with other settings; starting over") && said.matches("PSNR model").count() == 3, "{said}");
    // The same settings with the VAE written again at its path (weights trained again): their
    // episodes are scored again, not taken from the earlier file's run.
    write_random_vae(&vae, 6);
    let rewritten = fidelity(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap(), "--seed", "7"]);
    assert!(rewritten.status.success());
    let said = String::from_utf8_lossy(&rewritten.stdout).into_owned();
    assert!(said.contains("scored with other settings; starting over") && said.matches("PSNR model").count() == 3, "{said}");

    // One episode cannot be driven by another's actions: a clear error.
    let one = fidelity(&["--vae", vae.to_str().unwrap(), "--data", data.to_str().unwrap(), "--out", dir.join("one").to_str().unwrap(), "--episodes", "0"]);
    assert!(!one.status.success() && String::from_utf8_lossy(&one.stderr).contains("at least two episodes"));
    let _ = std::fs::remove_dir_all(&dir);
}
