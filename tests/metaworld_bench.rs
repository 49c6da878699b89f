//! The Meta-World benchmark (bench/metaworld) end to end on CPU at toy sizes, through the same
//! recipe the GPU run uses: generate.py writes training and held-out datasets from MuJoCo, then
//! `bwm train-vae`, `bwm prepare`, `bwm train`, `bwm fidelity`, the truth of the policy variants in
//! the simulator, judge.py, study.py (policy_server.py + judge over `bwm evaluate`, and the judge
//! on the simulator's own frames of the same episodes), teacher.py (over `bwm serve`) and `bwm
//! rollout` (the data engine) on the recipe's checkpoint and VAE. The numbers
//! of a toy model mean nothing; the test checks that every stage runs on the real path and writes
//! what it promises, that the datasets keep the generator's contract (bench/metaworld/tests/
//! check_dataset.py) and that generation is deterministic whatever the worker count.

mod common;

use std::path::Path;
use std::process::Command;

use common::{bwm, python, temp_dir};
use serde_json::Value;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

fn run(cmd: &mut Command, what: &str) -> String {
    let out = cmd.output().unwrap_or_else(|e| panic!("{what}: {e}"));
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{what} failed ({}):\n{text}", out.status);
    text
}

/// Runs one of bench/metaworld/tests/'s Python test files.
fn python_tests(file: &str) {
    run(Command::new(python()).arg(Path::new(ROOT).join("bench/metaworld/tests").join(file)), file);
}

fn json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))).unwrap()
}

/// `bash SCRIPT` (a bench/metaworld script) on CPU at toy sizes into `runs`: 3 training episodes
/// of 100 frames at 64x64, a 2-step VAE of stride 8 with 16 latent channels, a one-block DiT of
/// width 48 with a 1x2x2 patch trained 2 steps.
fn toy(script: &str, runs: &Path) -> Command {
    let mut cmd = Command::new("bash");
    cmd.arg(Path::new(ROOT).join("bench/metaworld").join(script))
        .env("RUN", runs)
        .env("BWM", bwm())
        .env("PYTHON", python())
        .env("DEVICE", "cpu")
        .envs([("TRAIN_EPISODES", "3"), ("FRAMES", "100"), ("RESOLUTION", "64"), ("WORKERS", "2")])
        .envs([("VAE_STEPS", "2"), ("VAE_BATCH", "2"), ("VAE_STRIDE", "8"), ("VAE_Z_DIM", "16"), ("VAE_DIM", "16"), ("VAE_DEC_DIM", "16")])
        .envs([("TRAIN_STEPS", "2"), ("SAMPLE_STEPS", "2")])
        .env("TRAIN_SETS", TOY_DIT);
    cmd
}

/// The toy recipe and the transfer study each keep every core busy (libtorch's threads, the
/// generator's and study's processes); side by side on CI's two cores they took 327-406 s, one
/// after the other about 232 s, so they take turns.
static ONE_PIPELINE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

const TOY_DIT: &str = "model.dit.dim=48 model.dit.patch_size=[1,2,2] model.dit.ffn_dim=96 model.dit.num_heads=4 model.dit.num_layers=1 train.micro_batch=2 checkpoint.every=2 validation.every=2 validation.sample_steps=2";

/// The toy recipe's behaviour mix: every mode, the learned pool's episodes among them.
const TOY_MIX: &str = "expert=1,near=1,partial=1,explore=1,idle=1,learned=2";

/// The judge and the study at toy sizes (the judge stage also judges the study's episodes).
const TOY_STUDY: [(&str, &str); 5] =
    [("JUDGE_STEPS", "5"), ("STUDY_EPISODES", "1"), ("STUDY_JOBS", "2"), ("STUDY_HORIZON", "48"), ("STUDY_VARIANTS", TOY_VARIANTS)];
/// The toy study's variants: two of policies.py's, one of each family of families.py.
const TOY_VARIANTS: &str = "expert,wrong,bc-nn-1,lag-6,quit-50,wander-then-80";
/// Its rates: 6 variants x 2 tasks.
const TOY_RATES: u64 = 12;

#[test]
fn the_metaworld_recipe_runs_every_stage_on_cpu() {
    let _turn = ONE_PIPELINE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("metaworld");
    let runs = dir.join("run");
    let full = || {
        let mut recipe = toy("recipe.sh", &runs);
        recipe
            .envs([("VAL_EPISODES", "1"), ("VAE_EPISODES", "6"), ("JUDGE_RECONSTRUCT_EPISODES", "4")])
            .envs(TOY_STUDY)
            .env("TEACHER_VARIANTS", "expert,wrong")
            .env("PROBE_VARIANTS", "wrong-0cm,wrong-6cm")
            // The own stage over one episode per task of each dataset, whatever its behaviour.
            .envs([("OWN_BEHAVIOURS", ""), ("OWN_EPISODES", "1")])
            // The DiT trained with action dropout, its own history noise and grid shift and an
            // average of its weights, every world-model stage guided by the actions and rolling
            // out that average; the data's behaviours in a mix of its own (the learned pool among
            // them), and its expert looking at the object only every 8-40 frames. The DiT draws the
            // commanded hand into its token grid (the hand map).
            .env(
                "TRAIN_SETS",
                format!("{TOY_DIT} objective.action_dropout=0.5 objective.history_sigma=0.1 objective.shift=3.0 model.action.hand_map={{hands=[[0,1,2]]}}"),
            )
            .env("EMA_DECAY", "0.5")
            .env("GUIDANCE", "1.5")
            .env("MIX", TOY_MIX)
            .env("OBSERVE_EVERY", "8,40");
        recipe
    };
    let log = run(&mut full(), "recipe.sh");

    // Training closes with its held-out rollout next to the copy-last-frame baseline, and the
    // loss of every step goes to losses.tsv (the loss curve's source).
    assert!(log.contains("predicted frames each:") && log.contains("holding the last given frame"), "{log}");
    let losses = std::fs::read_to_string(runs.join("losses.tsv")).unwrap();
    assert_eq!(losses.lines().map(|l| l.split('\t').next().unwrap()).collect::<Vec<_>>(), ["1", "2"], "{losses}");

    // The judge on the simulator's frames was measured in the judge stage, beside training; the
    // study found it cached.
    let study_log = log.split("recipe: study (").nth(1).and_then(|rest| rest.split("recipe: ").next()).expect("the study's log");
    assert!(!study_log.contains("judge on simulator frames"), "{study_log}");
    assert!(log.split("recipe: judged-reconstructed (").nth(1).is_some_and(|rest| rest.contains("judge on simulator frames")), "{log}");

    let timings = std::fs::read_to_string(runs.join("timings.tsv")).unwrap();
    for stage in ["data-train", "data-val", "vae", "latents", "train", "fidelity", "truth", "judge-reconstructed", "judged-reconstructed", "ceiling", "study", "teacher", "own-train", "own-val", "probe"] {
        assert!(timings.lines().any(|l| l.split('\t').next() == Some(stage)), "no {stage} in timings.tsv:\n{timings}\n{log}");
    }

    // The generator's contract, and training and validation seeds apart.
    let (train, val) = (runs.join("data/train"), runs.join("data/val"));
    let check = run(Command::new(python()).arg(Path::new(ROOT).join("bench/metaworld/tests/check_dataset.py")).arg(&train).arg(&val), "check_dataset.py");
    let report: Value = serde_json::from_str(check.trim()).unwrap_or_else(|e| panic!("{e}: {check}"));
    assert_eq!(report[train.to_str().unwrap()]["episodes"], 6, "{report}");
    assert_eq!(report[val.to_str().unwrap()]["frames"], 200, "{report}");

    // The same arguments give the same bytes with one worker as with two.
    let again = dir.join("val-again");
    run(
        Command::new(python())
            .arg(Path::new(ROOT).join("bench/metaworld/generate.py"))
            .args(["--tasks", "drawer-open-v3,button-press-topdown-v3", "--episodes", "1", "--seed-start", "100000"])
            .args(["--frames", "100", "--resolution", "64", "--mix", TOY_MIX, "--observe-every", "8,40", "--workers", "1"])
            .arg("--out")
            .arg(&again),
        "generate.py",
    );
    for episode in 0..2 {
        let file = format!("data/chunk-000/episode_{episode:06}.parquet");
        assert!(std::fs::read(val.join(&file)).unwrap() == std::fs::read(again.join(&file)).unwrap(), "{file} differs between worker counts");
    }

    // The data stage again keeps the data made with its settings, and refuses them under others
    // (here the recipe's own default of OBSERVE_EVERY) rather than train on them unnoticed.
    let data_again = |observe: &str| {
        toy("recipe.sh", &runs)
            .envs([("VAL_EPISODES", "1"), ("MIX", TOY_MIX), ("OBSERVE_EVERY", observe)])
            .arg("data")
            .output()
            .unwrap()
    };
    let same = data_again("8,40");
    assert!(same.status.success() && String::from_utf8_lossy(&same.stderr).contains("exists, made with these settings"), "{same:?}");
    let other = data_again("24,48");
    let said = String::from_utf8_lossy(&other.stderr);
    assert!(!other.status.success() && said.contains("observe_every: [8, 40] there, [24, 48] asked"), "{other:?}");

    // The VAE of stride 8 with 16 channels (an 8x8x16 latent at 64x64) carried through to the
    // latent cache, and the DiT the recipe trained on it widened to match.
    let index = json(&runs.join("latents/index.json"));
    assert_eq!(index["latent_shape"], serde_json::json!([16, 9, 8, 8]), "{index}");

    let fidelity = json(&runs.join("fidelity/fidelity.json"));
    assert_eq!(fidelity["episodes"], 2, "{fidelity}");
    assert_eq!(fidelity["guidance"], 1.5, "{fidelity}");
    assert_eq!(fidelity["history_sigma"], 0.1, "sampling follows the trained history noise: {fidelity}");
    assert_eq!(fidelity["shift"], 3.0, "sampling follows the trained grid shift: {fidelity}");
    let config = std::fs::read_to_string(runs.join("config.toml")).unwrap();
    assert!(config.contains("action_dropout = 0.5"), "{config}");
    assert!(config.contains("[model.action.hand_map]") && config.contains("periods = 6"), "{config}");

    // The recipe's judge learns from the simulator's frames and from the VAE's round trips of
    // training frames; it is scored on real held-out frames.
    let judge = json(&runs.join("judge-reconstructed.json"));
    for task in ["drawer-open-v3", "button-press-topdown-v3"] {
        let t = &judge["tasks"][task];
        let accuracy = t["held_out_frames"]["accuracy"].as_f64().unwrap_or_else(|| panic!("{judge}"));
        assert!((0.0..=1.0).contains(&accuracy), "{judge}");
        // The first four training episodes hold both tasks (interleaved by seed): two each.
        assert_eq!(t["train_reconstructed_frames"], 200, "{judge}");
        assert_eq!(t["train_frames"], 500, "three real episodes and two reconstructed: {judge}");
        assert_eq!(t["held_out_frames"]["n"], 100, "scored on the real held-out frames: {judge}");
    }

    // The judge on the held-out frames through the VAE (bwm reconstruct) beside the real ones.
    let ceiling = json(&runs.join("ceiling/judge-reconstructed.json"));
    assert_eq!(ceiling["judge"].as_str().map(|j| j.ends_with("judge-reconstructed.pt")), Some(true), "{ceiling}");
    for task in ["drawer-open-v3", "button-press-topdown-v3"] {
        let t = &ceiling["tasks"][task];
        for part in ["real", "reconstructed"] {
            assert_eq!(t[part]["frames"]["n"], 100, "every held-out frame of {task} ({part}): {ceiling}");
            assert_eq!(t[part]["episodes"]["n"], 1, "{ceiling}");
        }
        // The same judge on the same real frames as judge.json's held-out score (up to a frame
        // whose probability sits at 0.5 under another thread count).
        let (a, b) = (t["real"]["frames"]["accuracy"].as_f64().unwrap(), judge["tasks"][task]["held_out_frames"]["accuracy"].as_f64().unwrap());
        assert!((a - b).abs() <= 0.02, "{ceiling}\n{judge}");
        assert!(t["reconstruction_psnr_db"].as_f64().is_some_and(|p| p > 0.0 && p < 100.0), "{ceiling}");
        assert_eq!(t["object_position"]["episodes"], 1, "{ceiling}");
    }

    let study = json(&runs.join("study/study.json"));
    let rates = study["rates"].as_array().unwrap();
    assert_eq!(rates.len() as u64, TOY_RATES, "6 variants x 2 tasks: {study}");
    for r in rates {
        assert_eq!(r["episodes"], 1, "{r}");
        assert_eq!(r["errors"], 0, "no episode failed on an error: {r}");
        assert!(r["true"].as_f64().is_some_and(|v| (0.0..=1.0).contains(&v)), "{r}");
        assert!(r["estimated"].as_f64().is_some_and(|v| (0.0..=1.0).contains(&v)), "{r}");
        assert!(r["judged_simulator"].as_f64().is_some_and(|v| (0.0..=1.0).contains(&v)), "{r}");
        assert!(r["replayed"].as_f64().is_some_and(|v| (0.0..=1.0).contains(&v)), "each world-model episode's actions replayed: {r}");
    }
    assert_eq!(study["all"]["n"], TOY_RATES, "{study}");
    assert_eq!(study["replayed"]["per_episode"]["n"], TOY_RATES, "{study}");
    assert_eq!(study["replayed"]["estimated_vs_replayed"]["n"], TOY_RATES, "{study}");
    // Each task's six episodes (one per variant) sorted by both outcomes into the judge's bands.
    let by_probability = study["replayed"]["by_probability"].as_object().expect("replayed.by_probability");
    assert_eq!(by_probability.len(), 2, "{study}");
    for (task, kinds) in by_probability {
        let counted: u64 = kinds.as_object().unwrap().values().flat_map(|b| b.as_object().unwrap().values()).filter_map(Value::as_u64).sum();
        assert_eq!(counted, TOY_RATES / 2, "{task}: {kinds}");
    }
    let flags: Vec<&str> = study["world_model_flags"].as_array().unwrap().iter().filter_map(Value::as_str).collect();
    assert!(flags.windows(2).any(|w| w == ["--guidance", "1.5"]), "{flags:?}");
    // The world model is the newest checkpoint's average of weights, exported once for every stage.
    let ckpt = flags.windows(2).find(|w| w[0] == "--checkpoint").map(|w| Path::new(w[1])).expect("--checkpoint");
    assert_eq!(ckpt, runs.join("ema/step-00000002"), "{flags:?}");
    assert!(ckpt.join("config.json").is_file(), "{flags:?}");
    assert!(config.contains("ema_decay = 0.5"), "{config}");
    assert_eq!(timings.lines().filter(|l| l.starts_with("ema\t")).count(), 1, "{timings}");
    // The recipe's checkpoint and VAE work with the data engine as any checkpoint does: the
    // study's own world-model flags drive a held-out episode with its recorded commands.
    let engine = dir.join("rollout");
    run(
        Command::new(bwm())
            .arg("rollout")
            .args(&flags)
            .arg("--data")
            .arg(runs.join("data/val"))
            .args(["--actions", "observation.state:0-3", "--resolution", "64x64", "--episodes", "0", "--max-frames", "40", "--out"])
            .arg(&engine),
        "bwm rollout",
    );
    let generated = bwm_data::open_dataset(&engine).unwrap_or_else(|e| panic!("{e:#}"));
    assert_eq!(generated.episodes().iter().map(|e| e.length).collect::<Vec<_>>(), [40]);
    assert!(std::fs::read_to_string(engine.join("compare/metrics.jsonl")).is_ok_and(|m| m.contains("psnr")), "PSNR against the real episode");

    // The same world model on other held-out seeds, without training again (other-seeds.sh, with
    // the recipe's variables of this run); held-out seeds among the training ones are refused.
    let other = dir.join("run-other-seeds");
    let other_seeds = |start: &str| {
        let mut cmd = Command::new("bash");
        cmd.arg(Path::new(ROOT).join("bench/metaworld/other-seeds.sh")).arg(&runs).args(["data", "truth", "study"]);
        for (k, v) in full().get_envs() {
            if let Some(v) = v {
                cmd.env(k, v);
            }
        }
        cmd.env("RUN", &other).env("VAL_SEED_START", start);
        cmd
    };
    let refused = other_seeds("2").output().unwrap();
    let said = String::from_utf8_lossy(&refused.stderr);
    assert!(refused.status.code() == Some(2) && said.contains("VAL_SEED_START=2 must be a whole number of at least TRAIN_EPISODES=3"), "{said}");
    let other_log = run(&mut other_seeds("7"), "other-seeds.sh");
    assert!(!other_log.contains("recipe: train (") && !other_log.contains("recipe: vae ("), "{other_log}");
    let seeds: Vec<u64> = std::fs::read_to_string(other.join("data/val/meta/episodes.jsonl")).unwrap().lines().map(|l| serde_json::from_str::<Value>(l).unwrap()["seed"].as_u64().unwrap()).collect();
    assert_eq!(seeds, [7, 7], "one held-out episode per task from seed 7");
    let other_study = json(&other.join("study/study.json"));
    assert_eq!(other_study["all"]["n"], TOY_RATES, "{other_study}");
    let other_flags: Vec<&str> = other_study["world_model_flags"].as_array().unwrap().iter().filter_map(Value::as_str).collect();
    assert!(other_flags.windows(2).any(|w| w[0] == "--checkpoint" && Path::new(w[1]) == other.join("ema/step-00000002")), "the linked run's checkpoint: {other_flags:?}");
    assert_eq!(study["per_episode"]["n"], TOY_RATES, "one episode per rate, each paired with its truth: {study}");
    for r in rates {
        let e = &r["per_episode"];
        let counts: u64 = ["both_success", "missed", "invented", "both_fail"].iter().map(|k| e[k].as_u64().unwrap()).sum();
        assert_eq!(counts, 1, "{r}");
    }
    assert_eq!(study["judge_on_simulator_frames"]["n"], TOY_RATES, "{study}");
    // Scored per family (policies.py's own variants the development family `degraded`) and per
    // split, each with its invented and missed successes.
    let families = study["per_family"].as_object().unwrap_or_else(|| panic!("no per_family: {study}"));
    for (family, split, n) in [("degraded", "development", 4), ("learned", "test", 2), ("scripted", "development", 2), ("partial", "development", 2), ("wander", "test", 2)] {
        assert_eq!(families[family]["split"], split, "{family}: {study}");
        assert_eq!(families[family]["n"], n, "{family}: {study}");
        assert!(families[family]["per_episode"]["invented"].is_u64() && families[family]["per_episode"]["missed"].is_u64(), "{family}: {study}");
    }
    assert_eq!(study["per_split"]["test"]["n"], 4, "{study}");
    assert_eq!(study["per_split"]["development"]["n"], 8, "{study}");
    // Each task's episodes by the hand's closest approach in the simulator: one per variant.
    for task in ["drawer-open-v3", "button-press-topdown-v3"] {
        let bands = study["by_approach"][task].as_object().unwrap_or_else(|| panic!("no by_approach for {task}: {study}"));
        let episodes: u64 = bands.values().map(|c| c["episodes"].as_u64().unwrap()).sum();
        assert_eq!(episodes, TOY_RATES / 2, "{task}: {bands:?}");
    }
    // SAMPLER_GRAPH=1 reaches the world model's flags, which refuse CUDA graphs on the CPU by name.
    let elsewhere = dir.join("fidelity-graphed");
    let out = toy("recipe.sh", &runs).arg("fidelity").env("SAMPLER_GRAPH", "1").env("FIDELITY_DIR", &elsewhere).output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(!out.status.success() && text.contains("--cuda-graph needs a CUDA device"), "{text}");
    let out = toy("recipe.sh", &runs).arg("fidelity").env("SAMPLER_GRAPH", "yes").output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    let judged = json(&runs.join("study/judged.json"));
    assert_eq!(judged["judged"]["drawer-open-v3"]["wrong"].as_array().map(Vec::len), Some(1), "{judged}");
    assert!(study["per_task"]["drawer-open-v3"]["mae"].is_number(), "{study}");
    assert!(runs.join("study/study.svg").is_file() && runs.join("study/eval-1/episodes.jsonl").is_file());
    // Scored again from its episodes, without the world model: the same rates, the flags kept.
    run(
        Command::new(python())
            .arg(Path::new(ROOT).join("bench/metaworld/study.py"))
            .arg("--data")
            .arg(runs.join("data/val"))
            .args(["--episodes", "1", "--horizon", "48", "--resolution", "64", "--workers", "2", "--variants", TOY_VARIANTS, "--rescore", "--out"])
            .arg(runs.join("study")),
        "study.py --rescore",
    );
    let rescored = json(&runs.join("study/study.json"));
    assert_eq!(rescored["rates"], study["rates"], "{rescored}");
    assert_eq!(rescored["by_approach"], study["by_approach"], "{rescored}");
    assert_eq!(rescored["replayed"], study["replayed"], "{rescored}");
    assert_eq!(rescored["world_model_flags"], study["world_model_flags"], "{rescored}");

    // Teacher forcing: the study's variants and episodes in the simulator, each of their two
    // chunks (48 frames of 24) drawn by the served world model from the real history and judged
    // beside the simulator's; the episode's truth the same as the study's.
    let teacher = json(&runs.join("teacher/teacher.json"));
    let rates = teacher["rates"].as_array().unwrap();
    assert_eq!(rates.len(), 4, "2 variants x 2 tasks: {teacher}");
    for r in rates {
        let (task, variant) = (r["task"].as_str().unwrap(), r["variant"].as_str().unwrap());
        let in_study = study["rates"].as_array().unwrap().iter().find(|s| s["task"] == task && s["variant"] == variant).expect("the study's rate");
        assert_eq!(r["true"], in_study["true"], "{r}");
        assert!(r["teacher_forced"].as_f64().is_some_and(|v| (0.0..=1.0).contains(&v)), "{r}");
        let episodes = teacher["episodes"][task][variant].as_array().unwrap();
        assert_eq!(episodes.len(), 1, "{r}");
        for side in ["real", "drawn"] {
            let p: Vec<f64> = episodes[0][side].as_array().unwrap().iter().filter_map(Value::as_f64).collect();
            assert!(p.len() == 2 && p.iter().all(|v| (0.0..=1.0).contains(v)), "{side}: {}", episodes[0]);
        }
    }
    let chunks: u64 = ["invented", "missed", "both_success", "both_fail"].iter().map(|k| teacher["chunks"][k].as_u64().unwrap()).sum();
    assert_eq!(chunks, 8, "{teacher}");
    assert_eq!(teacher["all"]["teacher_forced"]["n"], 4, "{teacher}");

    // The own stage: each dataset's first episode per task teacher-forced from its own frames and
    // states, its truth the dataset's flags, placed by its commands replayed in the simulator.
    for split in ["train", "val"] {
        let own = json(&runs.join(format!("own/{split}/teacher.json")));
        assert_eq!(own["settings"]["own_episodes"], true, "{own}");
        assert_eq!(own["settings"]["horizon"], 48, "{own}");
        let episodes: Vec<&Value> = own["episodes"].as_object().unwrap().values().flat_map(|by| by.as_object().unwrap().values()).flat_map(|e| e.as_array().unwrap()).collect();
        assert_eq!(episodes.len(), 2, "one per task: {own}");
        for e in &episodes {
            assert_eq!(e["drawn"].as_array().unwrap().len(), 2, "{e}");
            assert_eq!(e["offset_at_closest_cm"].as_array().unwrap().len(), 3, "{e}");
        }
        let map = json(&runs.join(format!("own/{split}/contact_map.json")));
        let counted: u64 = map["tasks"].as_object().unwrap().values()
            .flat_map(|t| t["by_axis"].as_object().unwrap().values())
            .flat_map(|a| a.as_object().unwrap().values())
            .map(|c| c["episodes"].as_u64().unwrap())
            .sum();
        assert_eq!(counted, 2, "{map}");
    }

    // The probe: the graded `wrong` variants through the same study, in their own folder.
    let probe = json(&runs.join("probe/study.json"));
    let names: Vec<_> = probe["rates"].as_array().unwrap().iter().map(|r| format!("{}/{}", r["task"].as_str().unwrap(), r["variant"].as_str().unwrap())).collect();
    assert_eq!(names.len(), 4, "{probe}");
    for v in ["wrong-0cm", "wrong-6cm"] {
        assert!(names.iter().any(|n| n.ends_with(&format!("/{v}"))), "{v} missing: {names:?}");
    }

    // The data engine: the expert's commands planned from two new placements per task, drawn by
    // the world model into PNG cells (what builds without video write), and one real
    // demonstration cloned alone, with the generated episodes the judge passes, with all of them
    // and with two more real ones, each policy run twice in the simulator.
    let engine_envs = [("ENGINE_SEEDS", "1"), ("ENGINE_GENERATED", "2"), ("ENGINE_DEMOS", "1"), ("ENGINE_EPISODES", "2"), ("ENGINE_NET_STEPS", "5"), ("ENGINE_IN_FLIGHT", "2")];
    run(toy("recipe.sh", &runs).arg("engine").envs(TOY_STUDY).envs(engine_envs), "recipe.sh engine");
    let generated = json(&runs.join("engine/generated/meta/info.json"));
    assert_eq!(generated["total_episodes"], 4, "{generated}");
    assert_eq!(generated["features"]["observation.images.generated"]["dtype"], "image", "{generated}");
    let planned = json(&runs.join("engine/plan/plan.json"));
    assert!(planned["episodes"].as_array().unwrap().iter().all(|e| e["commands"].as_array().unwrap().len() == 100), "{planned}");
    let engine = json(&runs.join("engine/engine.json"));
    let rows = engine["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 8, "2 tasks x 4 arms: {engine}");
    for r in rows {
        let task = r["task"].as_str().unwrap();
        assert!(r["success_rate"].as_f64().is_some_and(|v| (0.0..=1.0).contains(&v)) && r["episodes"] == 2, "{r}");
        let judged = engine["judged"][task]["judged_success"].as_u64().unwrap();
        let expected = match r["arm"].as_str().unwrap() {
            "real" => 1,
            "real+judged" => 1 + judged,
            "real+generated" | "real+real" => 3,
            other => panic!("unknown arm {other}"),
        };
        assert_eq!(r["demonstrations"], expected, "{r}");
    }
    assert_eq!(engine["verdicts"].as_array().unwrap().len(), 4, "{engine}");
    let timings = std::fs::read_to_string(runs.join("timings.tsv")).unwrap();
    for stage in ["engine-plan", "engine-rollout", "engine-measure"] {
        assert!(timings.lines().any(|l| l.split('\t').next() == Some(stage)), "no {stage} in timings.tsv:\n{timings}");
    }

    // Cheaper sampling against the full path: a light decoder and a one-step student trained from
    // the recipe's model, the teacher at 2 and 1 steps and the student each decoded both ways, in
    // the open loop over both held-out episodes and, for two settings, in closed loop.
    let stage = |name: &str| {
        let mut cmd = toy("recipe.sh", &runs);
        cmd.arg(name).envs(TOY_STUDY).envs([
            ("VAL_EPISODES", "1"),
            ("VAE_EPISODES", "6"),
            ("LIGHT_STEPS", "2"),
            ("LIGHT_BATCH", "1"),
            ("REALTIME_STUDENT_STEPS", "2"),
            ("REALTIME_TEACHER_STEPS", "2 1"),
            ("REALTIME_STUDENTS", "1"),
            ("REALTIME_EPISODES", "2"),
            ("REALTIME_STUDIES", "t2-full,s1-light"),
            ("REALTIME_VARIANTS", "expert,wander-then-80"),
        ]);
        cmd
    };
    let realtime = || stage("realtime");
    // Settings it cannot measure are refused before anything trains.
    for (var, value, said) in [
        ("REALTIME_STUDIES", "t3-full", "REALTIME_STUDIES names 't3-full'"),
        ("REALTIME_STUDIES", "s1-light", "must include the reference, t2-full"),
        ("REALTIME_STUDENTS", "3", "make SAMPLE_STEPS a multiple of 3"),
        ("REALTIME_TEACHER_STEPS", "2 x", "not 'x'"),
    ] {
        let out = realtime().env(var, value).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.code() == Some(2) && stderr.contains(said), "{var}={value}: {stderr}");
        assert!(!runs.join("realtime").exists(), "{var}={value}: nothing made");
    }
    // The light decoder made first by the light stage (as beside the world model's training) is
    // the one the realtime stage keeps: it trains once.
    run(&mut stage("light"), "recipe.sh light");
    let light = std::fs::read(runs.join("realtime/light-decoder.safetensors")).unwrap();
    let log = run(&mut realtime(), "recipe.sh realtime");
    assert!(runs.join("realtime/student-1/checkpoints/latest").is_file());
    // Its truth and verdicts are the recipe's study's (over more variants, the same episodes and judge).
    for what in ["truth", "judged"] {
        assert!(log.contains(&format!("study: {what} of 2 variants taken from")), "{what} measured again:\n{log}");
    }
    assert_eq!(std::fs::read(runs.join("realtime/light-decoder.safetensors")).unwrap(), light, "the light stage's decoder kept");
    let light_trainings = std::fs::read_to_string(runs.join("timings.tsv")).unwrap().lines().filter(|l| l.starts_with("light-decoder\t")).count();
    assert_eq!(light_trainings, 1, "the light decoder trained once");
    let table = json(&runs.join("realtime/realtime.json"));
    let settings = table["settings"].as_object().unwrap();
    let mut names: Vec<&String> = settings.keys().collect();
    names.sort();
    assert_eq!(names, ["s1-full", "s1-light", "t1-full", "t1-light", "t2-full", "t2-light"], "{table}");
    assert_eq!(table["reference"], "t2-full");
    assert_eq!(settings["t2-full"]["open_loop"]["reference_h"], 100.0, "the reference against itself: {table}");
    for (name, row) in settings {
        let open = &row["open_loop"];
        assert!(open["episodes"] == 2 && open["recorded_h"].as_f64().is_some(), "{name}: {table}");
        let studied = row.get("closed_loop").is_some();
        assert_eq!(studied, name == "t2-full" || name == "s1-light", "{name}: {table}");
        if studied {
            assert_eq!(row["closed_loop"]["episodes"], 4, "2 variants x 2 tasks x 1 episode: {table}");
        }
    }
    let timings = std::fs::read_to_string(runs.join("timings.tsv")).unwrap();
    for stage in ["light-decoder", "student-1", "roll-t2-full", "roll-s1-light", "realtime-truth", "study-t2-full", "study-s1-light", "agreement"] {
        assert!(timings.lines().any(|l| l.split('\t').next() == Some(stage)), "no {stage} in timings.tsv:\n{timings}");
    }

    // The judge of real frames only, beside the recipe's (its own file, report and ceiling; the
    // recipe's judge left as it was).
    let before = std::fs::read(runs.join("judge-reconstructed.pt")).unwrap();
    let first_judge = judged["key"]["judge"].clone();
    let log = run(
        toy("recipe.sh", &runs).args(["judge", "ceiling"]).envs(TOY_STUDY).env("JUDGE_FRAMES", "real"),
        "recipe.sh judge ceiling (JUDGE_FRAMES=real)",
    );
    let second = json(&runs.join("judge.json"));
    for task in ["drawer-open-v3", "button-press-topdown-v3"] {
        let t = &second["tasks"][task];
        assert_eq!(t["train_reconstructed_frames"], 0, "{second}");
        assert_eq!(t["train_frames"], 300, "three real episodes: {second}");
        assert_eq!(t["held_out_frames"]["n"], 100, "{second}");
    }
    let ceiling = json(&runs.join("ceiling/judge.json"));
    assert_eq!(ceiling["judge"].as_str().map(|j| j.ends_with("/judge.pt")), Some(true), "{ceiling}");
    assert!(log.contains("ceiling/val.safetensors exists"), "the held-out round trip made again:\n{log}");
    assert_eq!(ceiling["tasks"]["drawer-open-v3"]["reconstructed"]["frames"]["n"], 100, "{ceiling}");
    assert!(std::fs::read(runs.join("judge-reconstructed.pt")).unwrap() == before, "the recipe's judge untouched");
    let timings = std::fs::read_to_string(runs.join("timings.tsv")).unwrap();
    for stage in ["judge", "judged"] {
        assert!(timings.lines().any(|l| l.split('\t').next() == Some(stage)), "no {stage}: {timings}\n{log}");
    }
    // Its verdicts on the simulator's frames, cached for a study with it.
    let judged = json(&runs.join("study/judged.json"));
    assert!(judged["key"]["judge"].as_str().is_some_and(|d| d.len() == 64) && judged["key"]["judge"] != first_judge, "{judged}");
    assert_eq!(judged["judged"]["drawer-open-v3"]["wrong"].as_array().map(Vec::len), Some(1), "{judged}");

    // Run again as they were made, the stages keep their outputs (and the DiT continues from its
    // last checkpoint, which is its last step); each output's record says how it was made.
    let again = run(full().args(["vae", "latents", "train", "judge", "ceiling", "teacher", "own"]), "recipe.sh again");
    for out in ["vae.safetensors", "latents/index.json", "checkpoints/latest", "judge-reconstructed.pt", "ceiling/val.safetensors", "teacher/teacher.json", "own/train/teacher.json", "own/val/teacher.json"] {
        assert!(again.contains(&format!("{}/{out} exists, made with these settings from these inputs; kept", runs.display())), "{out}:\n{again}");
    }
    for stage in ["vae", "latents", "judge-reconstructed", "teacher", "own-train", "own-val"] {
        assert!(!again.contains(&format!("recipe: {stage} (")), "{stage} ran again:\n{again}");
    }
    let record = std::fs::read_to_string(runs.join("latents/index.json.recipe")).unwrap();
    assert!(record.lines().any(|l| l.starts_with("--vae ") && l.contains("/vae.safetensors (sha256 ")), "{record}");
    assert!(record.lines().any(|l| l.starts_with("--data ") && l.contains("/data/train (sha256 ")), "{record}");
    assert!(!record.contains("--device") && !record.contains("--batch"), "{record}");
    // A setting of a stage changed: its output is refused, naming the setting.
    let out = full().arg("vae").env("VAE_STEPS", "3").output().unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{said}");
    assert!(said.contains("vae.safetensors exists but was made otherwise") && said.contains("there: --steps 2") && said.contains("now:   --steps 3"), "{said}");
    // A VAE made again (here from another seed): what was made from the first one is refused.
    std::fs::rename(runs.join("vae.safetensors"), runs.join("vae-first.safetensors")).unwrap();
    run(full().arg("vae").env("VAE_SEED", "9"), "recipe.sh vae (another seed)");
    for (stage, out) in [("latents", "latents/index.json"), ("train", "checkpoints/latest"), ("ceiling", "ceiling/val.safetensors")] {
        let refused = full().arg(stage).output().unwrap();
        let said = String::from_utf8_lossy(&refused.stderr);
        assert_eq!(refused.status.code(), Some(2), "{stage}: {said}");
        assert!(said.contains(&format!("{out} exists but was made otherwise")) && said.contains("now:   --vae "), "{stage}: {said}");
    }
}

#[test]
fn the_judge_learns_from_reconstructed_frames() {
    python_tests("test_judge.py");
}

/// Each episode's behaviour (generate.py's mode) in a generated dataset's episodes.jsonl.
fn behaviours(dataset: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(dataset.join("meta/episodes.jsonl")).unwrap_or_else(|e| panic!("{}: {e}", dataset.display()));
    text.lines().map(|l| serde_json::from_str::<Value>(l).unwrap()["behaviour"].as_str().unwrap().to_string()).collect()
}

#[test]
fn the_recipes_mix_reaches_the_generator() {
    // MIX=idle=1 makes every episode idle in both splits; a mix naming no behaviour is refused
    // before any data.
    let dir = temp_dir("metaworld-mix");
    let runs = dir.join("idle");
    run(toy("recipe.sh", &runs).arg("data").envs([("MIX", "idle=1"), ("TRAIN_EPISODES", "2"), ("VAL_EPISODES", "1"), ("FRAMES", "4")]), "recipe.sh data");
    for split in ["train", "val"] {
        let behaviours = behaviours(&runs.join(format!("data/{split}")));
        assert_eq!(behaviours.len(), if split == "train" { 4 } else { 2 }, "{behaviours:?}");
        assert!(behaviours.iter().all(|b| b == "idle"), "MIX=idle=1, {split}: {behaviours:?}");
    }
    let bad = toy("recipe.sh", &dir.join("bad")).arg("data").envs([("MIX", "sideways=1"), ("TRAIN_EPISODES", "1"), ("VAL_EPISODES", "1")]).output().unwrap();
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && err.contains("--mix") && err.contains("sideways=1"), "{err}");
    assert!(!dir.join("bad/data/train/meta").exists());
}

#[test]
fn the_recipes_vae_graph_and_candidates_reach_train_vae() {
    // On the CPU the recipe leaves CUDA graphs off and trains one VAE by default (the toy recipe
    // trains its VAE so); CUDA graphs asked for reach `bwm train-vae`, which refuses them there by name.
    let dir = temp_dir("metaworld-vae-graph");
    let runs = dir.join("run");
    run(toy("recipe.sh", &runs).arg("data").envs([("TRAIN_EPISODES", "1"), ("VAL_EPISODES", "1")]), "recipe.sh data");
    let out = toy("recipe.sh", &runs).arg("vae").env("VAE_GRAPH", "1").output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(!out.status.success(), "VAE_GRAPH=1 on the CPU must fail:\n{text}");
    assert!(text.contains("CUDA graphs (--cuda-graph) need a CUDA device"), "{text}");
    assert!(!runs.join("vae.safetensors").exists(), "no VAE may be written");
    // VAE_CANDIDATES and VAE_CHOOSE_AT reach it as --candidates and --choose-at: two VAEs from
    // seeds VAE_SEED and VAE_SEED + 1 one step each, then the better on to the toy's second step.
    let log = run(toy("recipe.sh", &runs).arg("vae").envs([("VAE_CANDIDATES", "2"), ("VAE_SEED", "4"), ("VAE_CHOOSE_AT", "1")]), "recipe.sh vae");
    assert!(log.contains("candidate 1/2: seed 4") && log.contains("candidate 2/2: seed 5"), "{log}");
    assert!(log.contains("held-out reconstruction PSNR") && log.contains("dB at step 1"), "{log}");
    assert!(log.contains(" goes on from step 1 to 2"), "{log}");
    assert!(log.contains("the best of 2 seeds, seed "), "{log}");
    assert!(runs.join("vae.safetensors").exists());
    // By default the CPU trains one.
    std::fs::remove_file(runs.join("vae.safetensors")).unwrap();
    let log = run(toy("recipe.sh", &runs).arg("vae"), "recipe.sh vae");
    assert!(!log.contains("candidate") && log.contains("train-vae: reconstruction PSNR"), "{log}");
    assert!(!log.contains("CUDA graph"), "the CPU trains eagerly by default: {log}");
    std::fs::remove_file(runs.join("vae.safetensors")).unwrap();
    // On a CUDA device the default (VAE_GRAPH=auto) tries the graph and, when the graph fails,
    // trains the VAE again eagerly: here through a bwm whose CUDA graphs fail and whose "cuda"
    // is the CPU.
    let graphless = dir.join("bwm-graphless");
    std::fs::write(
        &graphless,
        format!(
            "#!/usr/bin/env bash\nfor a in \"$@\"; do [ \"$a\" = --cuda-graph ] && {{ echo 'error: the training step as a CUDA graph (--cuda-graph): recording failed' >&2; exit 1; }}; done\nargs=(); for a in \"$@\"; do [ \"$a\" = cuda ] && a=cpu; args+=(\"$a\"); done\nexec '{}' \"${{args[@]}}\"\n",
            bwm().display()
        ),
    )
    .unwrap();
    std::fs::set_permissions(&graphless, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
    let _ = std::fs::remove_file(runs.join("timings.tsv"));
    let log = run(toy("recipe.sh", &runs).arg("vae").env("DEVICE", "cuda").env("BWM", &graphless), "recipe.sh vae (graph fails)");
    assert!(log.contains("recording failed") && log.contains("training it eagerly"), "{log}");
    assert!(runs.join("vae.safetensors").exists(), "the eager VAE is written");
    let timings = std::fs::read_to_string(runs.join("timings.tsv")).unwrap();
    assert!(timings.contains("vae-failed\t") && timings.contains("vae-eager\t"), "both attempts' times are kept: {timings}");
    std::fs::remove_file(runs.join("vae.safetensors")).unwrap();
    // Any other failure stops the recipe without a second attempt: here no CUDA device at all
    // (none visible to the recipe's processes, also on a machine that has one).
    let out = toy("recipe.sh", &runs).arg("vae").env("DEVICE", "cuda").env("CUDA_VISIBLE_DEVICES", "").output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(!out.status.success() && text.contains("CUDA is not available"), "{text}");
    assert!(!text.contains("training it eagerly") && !text.contains("recipe: vae-eager"), "{text}");
    assert!(!runs.join("vae.safetensors").exists(), "no VAE may be written");
    let out = toy("recipe.sh", &runs).arg("vae").env("VAE_GRAPH", "yes").output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    assert!(String::from_utf8_lossy(&out.stderr).contains("VAE_GRAPH must be 0, 1 or auto"), "{out:?}");
}

#[test]
fn the_generators_behaviour_mix_is_drawn_as_declared() {
    python_tests("test_generate.py");
}

#[test]
fn policy_families_act_and_end_as_their_variants_say() {
    python_tests("test_families.py");
}

#[test]
fn the_study_scores_rates_and_episodes() {
    python_tests("test_study.py");
}

#[test]
fn world_model_episodes_are_set_beside_the_simulators_frames_of_their_actions() {
    python_tests("test_side_by_side.py");
}

#[test]
fn trainings_are_compared_rate_for_rate() {
    python_tests("test_trainings.py");
}

#[test]
fn world_model_contact_is_mapped_by_where_the_hand_came_closest() {
    python_tests("test_contact_map.py");
}

#[test]
fn teacher_forcing_lays_chunks_out_and_scores_them() {
    python_tests("test_teacher.py");
}

#[test]
fn what_the_commands_tell_of_the_outcome_is_measured() {
    python_tests("test_tells.py");
}

#[test]
fn the_sampler_sweep_picks_the_fewest_steps_within_bounds() {
    python_tests("test_sweep.py");
}

#[test]
fn cheaper_settings_are_scored_against_a_reference_rollout() {
    python_tests("test_agreement.py");
}

#[test]
fn the_realtime_table_sets_each_setting_against_the_reference_and_its_bounds() {
    python_tests("test_realtime.py");
}

#[test]
fn the_policy_server_speaks_openpi() {
    python_tests("test_policy_server.py");
}

#[test]
fn results_are_written_whole_or_not_at_all() {
    python_tests("test_files.py");
}

/// bench/metaworld/transfer.sh at toy sizes: a base on one task, post-trained onto the other in
/// full, with LoRA and from scratch, each scored by `bwm fidelity` and, against one truth and one
/// judge of the new task, by the evaluator.
#[test]
fn the_transfer_study_runs_its_three_arms_on_cpu() {
    let _turn = ONE_PIPELINE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("transfer");
    let runs = dir.join("run");
    let log = run(
        // 72-frame episodes (the VAE needs 33 training frames beside its 33 held out): the three
        // arms' whole-episode rollouts are most of this test's time.
        toy("transfer.sh", &runs)
            .envs([("TARGET_EPISODES", "3"), ("VAL_EPISODES", "2"), ("VAE_TASK_EPISODES", "2"), ("POST_STEPS", "2"), ("LORA_RANK", "2")])
            .envs([("JUDGE_STEPS", "5"), ("STUDY_EPISODES", "1"), ("STUDY_JOBS", "2"), ("STUDY_HORIZON", "48"), ("TRANSFER_VARIANTS", "bc-nn-1,wander-then-80")])
            .env("FRAMES", "72"),
        "transfer.sh",
    );
    // The LoRA arm trains its adapters and the action encoder only; the others every tensor.
    let trained: Vec<&str> = log.lines().filter(|l| l.starts_with("run metaworld:")).collect();
    assert_eq!(trained.len(), 4, "{log}");
    let fraction = |l: &str| {
        let words: Vec<&str> = l.split_whitespace().collect();
        let k = words.iter().position(|w| *w == "of").unwrap();
        words[k - 1].parse::<f64>().unwrap() / words[k + 1].parse::<f64>().unwrap()
    };
    assert!(fraction(trained[2]) < 0.5 && fraction(trained[1]) > 0.9 && fraction(trained[3]) > 0.9, "{trained:?}");
    let report = json(&runs.join("transfer.json"));
    for arm in ["full", "lora", "scratch"] {
        for h in ["8", "32", "full"] {
            let psnr = report[arm][h]["model"]["psnr"].as_f64();
            assert!(psnr.is_some_and(f64::is_finite), "{arm} h={h}: {report}");
        }
        // The new task's two variants, one episode each, drawn by the arm and judged.
        let closed = &report["closed_loop"][arm];
        assert!(closed["episodes"] == 2 && closed["mae"].as_f64().is_some_and(|m| (0.0..=1.0).contains(&m)), "{arm}: {report}");
        assert!(closed["families"].get("learned").is_some() && closed["families"].get("wander").is_some(), "{arm}: {report}");
        let study = json(&runs.join(arm).join("study/study.json"));
        assert!(study["rates"].as_array().unwrap().iter().all(|r| r["task"] == "drawer-open-v3"), "{arm}: {study}");
    }
    // One truth and one judge for every arm: the truth (1 task x 2 variants) and the judge's
    // verdicts on the simulator's frames measured once, in the target's folder.
    assert_eq!(log.matches("study: truth: ").count(), 2, "{log}");
    assert_eq!(log.matches("study: judge on simulator frames: ").count(), 2, "{log}");
    assert!(runs.join("target/judge-reconstructed.pt").is_file());
}
