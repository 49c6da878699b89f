//! The GPU hosts' orchestration scripts on the CPU: scripts/gpu/variants.sh with a stub recipe and a
//! stub nvidia-smi (which variants make data, which share it, and when they start),
//! scripts/gpu/metaworld-stages.sh over a stub bench/metaworld/recipe.sh (which judge each stage
//! and study gets, and where each study writes), scripts/gpu/sweep_split.sh over a stub
//! scripts/gpu/metaworld.sh (which GPU each chain of settings gets, and that the later chains start
//! once the model is trained, with its truth and verdicts), and scripts/gpu/detached.sh's
//! start/wait protocol (exit codes, the logs' progress, the archive), common.sh's `unpack` (a
//! binary unpacked over the copy another script on the host is running) and `mem` (a measured
//! command that fails fails the script), fp8_train.sh's steps
//! against the reference's (stub binaries), and unit.sh, which fails where CUDA is missing.

mod common;

use std::fs;
use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::process::{Command, Output};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// A stub of scripts/gpu/metaworld.sh: makes each missing split as generate.py does (written
/// beside, then renamed into place) and records what it made and whether its data were there
/// when it started; fails before any data with FAIL=1.
const STUB_RECIPE: &str = r#"
[ "${FAIL:-0}" = 1 ] && { echo "stub: failing"; exit 1; }
RUN=${RUN:-runs/metaworld}
[ -f "$RUN/data/val/meta/info.json" ] && echo "$RUN found its data" >> "$MADE"
for split in train val; do
  [ -f "$RUN/data/$split/meta/info.json" ] && continue
  mkdir -p "$RUN/data/$split.tmp/meta"; sleep 1; echo "{}" > "$RUN/data/$split.tmp/meta/info.json"
  mv "$RUN/data/$split.tmp" "$RUN/data/$split"; echo "$RUN made $split" >> "$MADE"
done
echo "stub: $RUN on GPU ${CUDA_VISIBLE_DEVICES:-} with MIX=${MIX:-} VAE_SEED=${VAE_SEED:-} JUDGE_FRAMES=${JUDGE_FRAMES:-} stages $*"
"#;

fn write_executable(path: &Path, text: &str) {
    fs::write(path, text).unwrap();
    fs::set_permissions(path, fs::Permissions::from_mode(0o755)).unwrap();
}

/// variants.sh copied into `dir` beside the stub recipe, run there with a stub nvidia-smi of 4 GPUs.
fn variants(dir: &Path, args: &[&str]) -> Output {
    variants_with(dir, args, &[])
}

fn variants_with(dir: &Path, args: &[&str], vars: &[(&str, &str)]) -> Output {
    fs::create_dir_all(dir.join("scripts/gpu")).unwrap();
    fs::create_dir_all(dir.join("bin")).unwrap();
    fs::copy(Path::new(ROOT).join("scripts/gpu/variants.sh"), dir.join("scripts/gpu/variants.sh")).unwrap();
    fs::create_dir_all(dir.join("bench/metaworld")).unwrap();
    fs::copy(Path::new(ROOT).join("bench/metaworld/data-settings.sh"), dir.join("bench/metaworld/data-settings.sh")).unwrap();
    fs::write(dir.join("scripts/gpu/metaworld.sh"), STUB_RECIPE).unwrap();
    write_executable(&dir.join("bin/nvidia-smi"), "#!/bin/sh\nfor i in 0 1 2 3; do echo \"GPU $i: stub\"; done\n");
    let path = format!("{}:{}", dir.join("bin").display(), std::env::var("PATH").unwrap_or_default());
    Command::new("bash")
        .arg(dir.join("scripts/gpu/variants.sh"))
        .args(args)
        .current_dir(dir)
        .env("PATH", path)
        .env("OUT", dir.join("out"))
        .env("MADE", dir.join("made.txt"))
        .env_remove("STAGES")
        .env_remove("JUDGE_FRAMES")
        .envs(vars.iter().copied())
        .output()
        .unwrap()
}

fn lines(path: &Path) -> Vec<String> {
    let mut v: Vec<String> = fs::read_to_string(path).unwrap_or_default().lines().map(String::from).collect();
    v.sort();
    v
}

#[test]
fn variants_with_the_same_data_variables_share_one_dataset() {
    let dir = common::temp_dir("gpu-variants");
    let d = dir.path();
    let out = variants(d, &["a", "MIX=near=1 FRAMES=60", "b", "FRAMES=60 MIX=near=1 VAE_SEED=1", "c", "MIX=idle=1", "e", "MIX=idle=1 OBSERVE_EVERY=8,40"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("variants: b uses a's data"), "{stdout}");
    // Three datasets made (a's, c's and e's, whose expert looks otherwise); b started once a's were
    // written and found them.
    assert_eq!(
        lines(&d.join("made.txt")),
        ["runs/a made train", "runs/a made val", "runs/b found its data", "runs/c made train", "runs/c made val", "runs/e made train", "runs/e made val"],
        "{stdout}"
    );
    assert_eq!(fs::read_link(d.join("runs/b/data")).unwrap(), d.join("runs/a/data"));
    assert!(!fs::symlink_metadata(d.join("runs/c/data")).unwrap().file_type().is_symlink());
    let b_log = fs::read_to_string(d.join("out/b/log")).unwrap();
    assert!(b_log.contains("stub: runs/b on GPU 1 with MIX=near=1 VAE_SEED=1 JUDGE_FRAMES= stages"), "{b_log}");

    // A data variable set to the recipe's default (bench/metaworld/data-settings.sh) gives the
    // shared data, made once; other data variables are refused as the recipe would refuse them.
    let dir = common::temp_dir("gpu-variants-defaults");
    let d = dir.path();
    let defaults = Command::new("bash")
        .args(["-c", "source bench/metaworld/data-settings.sh && echo \"$OBSERVE_EVERY $FRAMES\""])
        .current_dir(ROOT)
        .output()
        .unwrap();
    let defaults = String::from_utf8_lossy(&defaults.stdout).trim().to_string();
    let (observe, frames) = defaults.split_once(' ').unwrap_or_else(|| panic!("{defaults}"));
    let (first, second) = (format!("OBSERVE_EVERY={observe} VAE_SEED=1"), format!("FRAMES={frames} VAE_SEED=2"));
    let out = variants(d, &["a", &first, "b", &second, "c", "VAE_SEED=3"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(
        lines(&d.join("made.txt")),
        ["runs/a found its data", "runs/b found its data", "runs/c found its data", "runs/metaworld made train", "runs/metaworld made val"],
        "{stdout}"
    );
    for v in ["a", "b", "c"] {
        assert_eq!(fs::read_link(d.join(format!("runs/{v}/data"))).unwrap(), d.join("runs/metaworld/data"), "{v}: {stdout}");
    }
    let out = variants(d, &["a", "VAL_SEED_START=1"]);
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    assert!(String::from_utf8_lossy(&out.stderr).contains("VAL_SEED_START=1 must be a whole number of at least TRAIN_EPISODES"), "{out:?}");

    // A lead that fails before its data takes the variants waiting on them down with it.
    let dir = common::temp_dir("gpu-variants-failed");
    let d = dir.path();
    let out = variants(d, &["a", "MIX=near=1 FAIL=1", "b", "MIX=near=1 VAE_SEED=1"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success() && stdout.contains("variants: a failed") && stdout.contains("variants: b failed"), "{stdout}");
    let b_log = fs::read_to_string(d.join("out/b/log")).unwrap();
    assert!(b_log.contains("a ended without its data"), "{b_log}");
    assert!(!d.join("made.txt").exists());

    // Some stages only: one judge of real frames made first for all (the recipe's own would need
    // each variant's VAE), which the variants use unless they name theirs.
    let dir = common::temp_dir("gpu-variants-stages");
    let d = dir.path();
    let out = variants_with(d, &["a", "VAE_SEED=1", "b", "JUDGE_FRAMES=reconstructed"], &[("STAGES", "vae ceiling")]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let shared = fs::read_to_string(d.join("out/shared.log")).unwrap();
    assert!(shared.contains("stub: runs/metaworld on GPU  with MIX= VAE_SEED= JUDGE_FRAMES=real stages data judge"), "{shared}");
    let a_log = fs::read_to_string(d.join("out/a/log")).unwrap();
    assert!(a_log.contains("stub: runs/a on GPU 0 with MIX= VAE_SEED=1 JUDGE_FRAMES=real stages vae ceiling"), "{a_log}");
    let b_log = fs::read_to_string(d.join("out/b/log")).unwrap();
    assert!(b_log.contains("JUDGE_FRAMES=reconstructed stages vae ceiling"), "{b_log}");
    assert_eq!(fs::read_link(d.join("runs/a/judge.pt")).unwrap(), d.join("runs/metaworld/judge.pt"));
}

/// A stub of bench/metaworld/recipe.sh: records each call's stages with the judge and study folder
/// it would use (recipe.sh's defaults), and leaves a study.json naming the judge in that folder,
/// and a truth.json naming the folder it was measured in where none is there yet.
const STUB_STAGES: &str = r#"
study=${STUDY_DIR:-$RUN/study} judge=${JUDGE_FRAMES:-reconstructed}
echo "$* judge=$judge study=$study ema=${EMA_DECAY:-}" >> "$CALLS"
[ -z "${STUDY_STREAMS:-}" ] || echo "streams $STUDY_STREAMS study=$study" >> "$CALLS"
[ -z "${HISTORY_SIGMA:-}" ] || echo "history-sigma $HISTORY_SIGMA study=$study" >> "$CALLS"
[ -z "${GUIDANCE:-}" ] || echo "guidance $GUIDANCE study=$study" >> "$CALLS"
[ -z "${SAMPLE_SEED:-}" ] || echo "sample-seed $SAMPLE_SEED study=$study" >> "$CALLS"
for s in "$@"; do
  if [ "$s" = study ]; then
    mkdir -p "$study"; echo "{\"judge\": \"$judge\"}" > "$study/study.json"
    [ -z "${STUDY_FROM:-}" ] || [ -f "$study/truth.json" ] || cp "$STUDY_FROM/truth.json" "$study/truth.json"
    [ -f "$study/truth.json" ] || echo "$study" > "$study/truth.json"
  fi
done
"#;

/// A stub of bench/metaworld/other-seeds.sh: records its call with the run and study folder.
const STUB_OTHER_SEEDS: &str = r#"
echo "other-seeds $* VAL_SEED_START=$VAL_SEED_START RUN=$RUN study=${STUDY_DIR:-}" >> "$CALLS"
"#;

/// metaworld-stages.sh copied into `dir` beside the stub recipe, run there for runs/x with `vars`.
fn stages(dir: &Path, vars: &[(&str, &str)]) -> (Output, Vec<String>) {
    stages_of(dir, &[], vars)
}

/// The same, given `args` (a mode such as `engine`, or stages).
fn stages_of(dir: &Path, args: &[&str], vars: &[(&str, &str)]) -> (Output, Vec<String>) {
    fs::create_dir_all(dir.join("scripts/gpu")).unwrap();
    fs::create_dir_all(dir.join("bench/metaworld")).unwrap();
    fs::copy(Path::new(ROOT).join("scripts/gpu/metaworld-stages.sh"), dir.join("scripts/gpu/metaworld-stages.sh")).unwrap();
    fs::write(dir.join("bench/metaworld/recipe.sh"), STUB_STAGES).unwrap();
    fs::write(dir.join("bench/metaworld/other-seeds.sh"), STUB_OTHER_SEEDS).unwrap();
    fs::copy(Path::new(ROOT).join("bench/metaworld/data-settings.sh"), dir.join("bench/metaworld/data-settings.sh")).unwrap();
    let calls = dir.join("calls.txt");
    let _ = fs::remove_file(&calls);
    let out = Command::new("bash")
        .arg(dir.join("scripts/gpu/metaworld-stages.sh"))
        .args(args)
        .current_dir(dir)
        .env_remove("JUDGE_FRAMES")
        .env_remove("STUDY_DIR")
        .env_remove("COMPARE_JUDGE")
        .env_remove("TEACHER")
        .env_remove("OWN")
        .env_remove("COMPARE_EMA")
        .env_remove("EMA_DECAY")
        .env_remove("OTHER_SEEDS")
        .env_remove("COMPARE_HISTORY_SIGMA")
        .env_remove("HISTORY_SIGMA")
        .env_remove("COMPARE_GUIDANCE")
        .env_remove("GUIDANCE")
        .env_remove("COMPARE_SAMPLE_SEED")
        .env_remove("SAMPLE_SEED")
        .env_remove("STUDY_FROM")
        .env("RUN", "runs/x")
        .env("OUT", dir.join("out"))
        .env("CALLS", &calls)
        .env("SKIP_FIDELITY", "1")
        .env("SKIP_PROBE", "1")
        .envs(vars.iter().copied())
        .output()
        .unwrap();
    let calls = fs::read_to_string(&calls).unwrap_or_default().lines().map(String::from).collect();
    (out, calls)
}

/// The stages with `vars`, which must succeed: their calls, and a log of the run for messages.
fn stages_ran(dir: &Path, vars: &[(&str, &str)]) -> (Vec<String>, String) {
    let (out, calls) = stages(dir, vars);
    let log = format!("{}\n{}\n{calls:#?}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{log}");
    (calls, log)
}

/// The stages with `vars` refused (exit 2, saying `said`) before any stage ran.
fn refused_before_any_stage(dir: &Path, vars: &[(&str, &str)], said: &str) {
    let (out, calls) = stages(dir, vars);
    assert_eq!(out.status.code(), Some(2), "{calls:?}");
    assert!(String::from_utf8_lossy(&out.stderr).contains(said), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(calls.is_empty(), "{calls:?}");
}

#[test]
fn each_judge_has_its_own_study_folder() {
    let dir = common::temp_dir("gpu-stages");
    let d = dir.path();
    // The recipe's own judge named, and left to its default (the stub's, recipe.sh's).
    let recipe = fs::read_to_string(Path::new(ROOT).join("bench/metaworld/recipe.sh")).unwrap();
    assert!(recipe.contains(r#"JUDGE_FRAMES="${JUDGE_FRAMES:-reconstructed}""#), "recipe.sh's default judge is not the stub's");
    for (own, other, vars) in [
        ("real", "reconstructed", &[("JUDGE_FRAMES", "real"), ("COMPARE_JUDGE", "reconstructed")][..]),
        ("reconstructed", "real", &[("COMPARE_JUDGE", "real")][..]),
    ] {
        let (calls, log) = stages_ran(d, vars);
        let second = format!("runs/x/study-judge-{other}");
        for (judge, folder) in [(own, "runs/x/study"), (other, second.as_str())] {
            // The judge stage leaves the judge on the simulator's frames in the folder of the study it is for.
            for stage in ["judge", "study"] {
                let call = format!("{stage} judge={judge} study={folder} ema=");
                assert_eq!(calls.iter().filter(|c| **c == call).count(), 1, "{call}\n{log}");
            }
            let study = fs::read_to_string(d.join(folder).join("study.json")).unwrap();
            assert_eq!(study.trim(), format!("{{\"judge\": \"{judge}\"}}"), "{folder}\n{log}");
            assert!(calls.iter().any(|c| c.starts_with(&format!("ceiling judge={judge} "))), "{log}");
        }
        // The judge that learns from the VAE's round trips starts once the VAE is trained.
        let vae = calls.iter().position(|c| c.starts_with("vae ")).expect("a vae stage");
        let reconstructed = calls.iter().position(|c| c.starts_with("judge judge=reconstructed ")).unwrap();
        assert!(vae < reconstructed, "{log}");
        fs::remove_dir_all(d.join("runs")).unwrap();
    }
    refused_before_any_stage(d, &[("COMPARE_JUDGE", "reconstructed")], "is the study's own judge");
}

/// Runs the stages without and with `asked` set to 1 (beside `base`): the optional `stage` runs
/// only when asked, and after the stage `after`.
fn runs_after_when_asked(name: &str, base: &[(&str, &str)], asked: &str, stage: &str, after: &str) {
    let dir = common::temp_dir(name);
    let d = dir.path();
    let with: Vec<(&str, &str)> = base.iter().copied().chain([(asked, "1")]).collect();
    for (vars, wanted) in [(base, false), (&with[..], true)] {
        let (calls, log) = stages_ran(d, vars);
        let before = calls.iter().position(|c| c.starts_with(&format!("{after} "))).unwrap_or_else(|| panic!("no {after} stage: {log}"));
        match calls.iter().position(|c| c.starts_with(&format!("{stage} "))) {
            Some(at) => assert!(wanted && at > before, "{log}"),
            None => assert!(!wanted, "{log}"),
        }
        fs::remove_dir_all(d.join("runs")).unwrap();
    }
}

#[test]
fn the_engine_and_realtime_modes_train_the_model_first_then_run_their_stage_alone_the_light_decoder_beside() {
    let dir = common::temp_dir("gpu-modes");
    let d = dir.path();
    for mode in ["engine", "realtime"] {
        let (out, calls) = stages_of(d, &[mode], &[]);
        let log = format!("{}\n{}\n{calls:#?}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        assert!(out.status.success(), "{log}");
        let at = |stage: &str| calls.iter().position(|c| c.starts_with(&format!("{stage} "))).unwrap_or_else(|| panic!("no {stage}: {log}"));
        for before in ["data", "vae", "latents train", "truth", "judge"] {
            assert!(at(before) < at(mode), "{before} before {mode}: {log}");
        }
        assert!(!calls.iter().any(|c| c.starts_with("study ")), "no study in the {mode} mode: {log}");
        assert_eq!(calls.last().map(|c| c.starts_with(&format!("{mode} "))), Some(true), "{log}");
        // The realtime stage's light decoder trains beside the world model, once the VAE is there.
        if mode == "realtime" {
            assert!(at("vae") < at("light") && at("light") < at(mode), "{log}");
        } else {
            assert!(!calls.iter().any(|c| c.starts_with("light ")), "no light decoder in the {mode} mode: {log}");
        }
    }
}

#[test]
fn the_teacher_stage_follows_the_study_when_asked() {
    runs_after_when_asked("gpu-teacher", &[], "TEACHER", "teacher", "study");
}

#[test]
fn the_own_stage_follows_the_teacher_when_asked() {
    runs_after_when_asked("gpu-own", &[("TEACHER", "1")], "OWN", "own", "teacher");
}

#[test]
fn the_last_steps_weights_are_studied_beside_their_average_when_asked() {
    let dir = common::temp_dir("gpu-ema");
    let d = dir.path();
    let (calls, log) = stages_ran(d, &[("EMA_DECAY", "0.999"), ("COMPARE_EMA", "1")]);
    let studies: Vec<&String> = calls.iter().filter(|c| c.starts_with("study ")).collect();
    assert_eq!(studies, ["study judge=reconstructed study=runs/x/study ema=0.999", "study judge=reconstructed study=runs/x/study-last ema="], "{log}");
    assert!(d.join("runs/x/study-last/study.json").is_file(), "{log}");
    fs::remove_dir_all(d.join("runs")).unwrap();
    // Without an average there is nothing to compare: refused before any stage.
    refused_before_any_stage(d, &[("COMPARE_EMA", "1")], "set EMA_DECAY");
}

#[test]
fn the_study_in_lanes_follows_the_study_when_asked() {
    let dir = common::temp_dir("gpu-streams");
    let d = dir.path();
    let (calls, log) = stages_ran(d, &[("COMPARE_STREAMS", "2")]);
    let studies: Vec<&String> = calls.iter().filter(|c| c.starts_with("study ") || c.starts_with("streams ")).collect();
    assert_eq!(
        studies,
        ["study judge=reconstructed study=runs/x/study ema=", "study judge=reconstructed study=runs/x/study-streams2 ema=", "streams 2 study=runs/x/study-streams2"],
        "{log}"
    );
    assert!(d.join("runs/x/study-streams2/study.json").is_file(), "{log}");
}

#[test]
fn the_study_is_repeated_per_guidance_history_noise_level_and_sampler_seed_from_its_truth_when_asked() {
    let dir = common::temp_dir("gpu-history-sigma");
    let d = dir.path();
    let (calls, log) = stages_ran(d, &[("COMPARE_GUIDANCE", "2"), ("COMPARE_HISTORY_SIGMA", "0 0.1"), ("COMPARE_SAMPLE_SEED", "1")]);
    let studies: Vec<&String> = calls
        .iter()
        .filter(|c| c.starts_with("study ") || c.starts_with("history-sigma ") || c.starts_with("guidance ") || c.starts_with("sample-seed "))
        .collect();
    assert_eq!(
        studies,
        [
            "study judge=reconstructed study=runs/x/study ema=",
            "study judge=reconstructed study=runs/x/study-g2 ema=",
            "guidance 2 study=runs/x/study-g2",
            "study judge=reconstructed study=runs/x/study-h0 ema=",
            "history-sigma 0 study=runs/x/study-h0",
            "study judge=reconstructed study=runs/x/study-h0.1 ema=",
            "history-sigma 0.1 study=runs/x/study-h0.1",
            "study judge=reconstructed study=runs/x/study-seed1 ema=",
            "sample-seed 1 study=runs/x/study-seed1",
        ],
        "{log}"
    );
    // Each comparison starts from the study's own truth (copied, not measured again).
    for s in ["study-g2", "study-h0", "study-h0.1", "study-seed1"] {
        assert_eq!(fs::read_to_string(d.join("runs/x").join(s).join("truth.json")).unwrap().trim(), "runs/x/study", "{log}");
    }
}

#[test]
fn other_held_out_seeds_are_studied_after_the_study_when_asked() {
    let dir = common::temp_dir("gpu-other-seeds");
    let d = dir.path();
    let (calls, log) = stages_ran(d, &[("OTHER_SEEDS", "200000"), ("STUDY_DIR", "runs/x/mine")]);
    let study = calls.iter().position(|c| c.starts_with("study ")).unwrap_or_else(|| panic!("{log}"));
    let other = calls.iter().position(|c| c == "other-seeds runs/x data truth study VAL_SEED_START=200000 RUN=runs/x/seeds-200000 study=").unwrap_or_else(|| panic!("{log}"));
    assert!(study < other, "{log}");
    fs::remove_dir_all(d.join("runs")).unwrap();
    // Seeds among the training ones are refused before any stage.
    refused_before_any_stage(d, &[("OTHER_SEEDS", "5")], "VAL_SEED_START=5 must be a whole number of at least TRAIN_EPISODES");
}

/// Removes detached.sh's folder of a name when the test ends, also on failure.
struct Detached(String);

impl Drop for Detached {
    fn drop(&mut self) {
        let dir = Path::new("/tmp/detached").join(&self.0);
        if let Ok(pid) = fs::read_to_string(dir.join("pid")) {
            let _ = Command::new("kill").arg("--").arg(format!("-{}", pid.trim())).output();
        }
        let _ = fs::remove_dir_all(dir);
    }
}

/// A stub of scripts/gpu/metaworld.sh's `sweep`: its training stage holds the run folder's lock
/// for half a second (as `bwm train --resume auto` does with nothing left to train) and fails
/// where another chain holds it; the chain that finds no model trains it (the truth and the
/// verdicts appear after a second), then each setting says where it ran and whether the truth was
/// in its study folder when it began; fails at once with FAIL=1.
const STUB_SWEEP: &str = r#"
[ "${FAIL:-0}" = 1 ] && { echo "stub: failing"; exit 1; }
mkdir -p "$OUT" "$RUN"
mkdir "$RUN/lock" 2>/dev/null || { echo "stub: the run folder $RUN is in use"; exit 1; }
sleep 0.5
if [ ! -f "$RUN/study/judged.json" ]; then
  sleep 1; mkdir -p "$RUN/study"; echo t > "$RUN/study/truth.json"; echo j > "$RUN/study/judged.json"
  echo "trained by $SETTINGS" >> "$MADE"
fi
rmdir "$RUN/lock"
for s in $SETTINGS; do
  echo "sweep: $s" >> "$OUT/sweep.log"
  found=no; [ -f "$RUN/sweep/$s/study/truth.json" ] && [ -f "$RUN/sweep/$s/study/judged.json" ] && found=yes
  echo "$s on GPU $CUDA_VISIBLE_DEVICES, truth $found" >> "$MADE"
done
"#;

fn sweep_split(dir: &Path, vars: &[(&str, &str)]) -> Output {
    fs::create_dir_all(dir.join("scripts/gpu")).unwrap();
    fs::copy(Path::new(ROOT).join("scripts/gpu/sweep_split.sh"), dir.join("scripts/gpu/sweep_split.sh")).unwrap();
    fs::write(dir.join("scripts/gpu/metaworld.sh"), STUB_SWEEP).unwrap();
    Command::new("bash")
        .arg(dir.join("scripts/gpu/sweep_split.sh"))
        .current_dir(dir)
        .env("OUT", dir.join("out"))
        .env("MADE", dir.join("made.txt"))
        .env("RUN", "runs/s")
        .envs(vars.iter().copied())
        .output()
        .unwrap()
}

#[test]
fn the_sweeps_chains_start_on_their_gpus_once_the_first_has_trained_the_model() {
    let dir = common::temp_dir("gpu-sweep-split");
    let d = dir.path();
    let out = sweep_split(d, &[("CHAINS", "0:euler-50,euler-8 0:euler-4 1:euler-20,euler-12")]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("sweep_split: trained at") && stdout.contains("(status 0)"), "{stdout}");
    assert_eq!(
        lines(&d.join("made.txt")),
        [
            "euler-12 on GPU 1, truth yes",
            "euler-20 on GPU 1, truth yes",
            "euler-4 on GPU 0, truth yes",
            "euler-50 on GPU 0, truth no",
            "euler-8 on GPU 0, truth no",
            "trained by euler-50 euler-8",
        ]
    );
    for c in 0..3 {
        assert!(d.join(format!("out/c{c}/sweep.log")).is_file(), "chain {c} has its own log folder");
    }

    let failed = sweep_split(&d.join("f"), &[("FAIL", "1")]);
    assert_eq!(failed.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&failed.stdout).contains("chain 0 ended before its sweep began"));
}

/// A stub of bench/metaworld/recipe.sh's fidelity and study stages for bench/metaworld/sweep.sh:
/// records the sampler settings each stage got and writes the outputs sweep.py reads (the same
/// for every setting).
const STUB_SWEEP_RECIPE: &str = r#"
for stage in "$@"; do
  echo "$stage solver=$SOLVER steps=$SAMPLE_STEPS fp8=$FP8 streams=$FIDELITY_STREAMS/$STUDY_STREAMS" >> "$CALLS"
  if [ "$stage" = fidelity ]; then
    mkdir -p "$FIDELITY_DIR"
    echo '{"all": {"horizons": {"32": {"model": {"psnr": 27.0}}}}, "tasks": {"t": {"horizons": {"32": {"model": {"psnr": 27.0}}}}}}' > "$FIDELITY_DIR/fidelity.json"
  else
    mkdir -p "$STUDY_DIR"
    echo '{"rates": [{"task": "t", "variant": "x", "estimated": 0.5}], "all": {"pearson_r": 0.9, "best_ranked_first": true}}' > "$STUDY_DIR/study.json"
  fi
  printf '%s\t0.1\n' "$stage" >> "$TIMINGS"  # as the recipe's `timed` writes it
done
"#;

#[test]
fn the_sweep_times_each_settings_stages_and_passes_fp8_and_lanes_on() {
    let dir = common::temp_dir("gpu-sweep");
    let d = dir.path();
    fs::create_dir_all(d.join("bench/metaworld")).unwrap();
    for f in ["sweep.sh", "sweep.py", "files.py"] {
        fs::copy(Path::new(ROOT).join("bench/metaworld").join(f), d.join("bench/metaworld").join(f)).unwrap();
    }
    fs::write(d.join("bench/metaworld/recipe.sh"), STUB_SWEEP_RECIPE).unwrap();
    fs::create_dir_all(d.join("runs/w/data/val/meta")).unwrap();
    fs::write(d.join("runs/w/data/val/meta/info.json"), r#"{"total_tasks": 1}"#).unwrap();
    // The trained run's newest checkpoint, where the sweep records its pick.
    fs::create_dir_all(d.join("runs/w/checkpoints/step-00000010")).unwrap();
    fs::write(d.join("runs/w/checkpoints/step-00000010/model.safetensors"), "weights").unwrap();
    fs::write(d.join("runs/w/checkpoints/latest"), "step-00000010").unwrap();
    let sweep = || {
        Command::new("bash")
            .arg(d.join("bench/metaworld/sweep.sh"))
            .current_dir(d)
            .env("RUN", "runs/w")
            .env("BWM", common::bwm())
            .env("CALLS", d.join("calls.txt"))
            .env("STEPS", "8 50")
            .env("SOLVERS", "euler")
            .env("EXTRA_SETTINGS", "euler-8-fp8row-streams2")
            .env("PYTHON", common::python())
            .output()
            .unwrap()
    };
    let out = sweep();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(
        fs::read_to_string(d.join("calls.txt")).unwrap().lines().collect::<Vec<_>>(),
        [
            "fidelity solver=euler steps=50 fp8= streams=1/1",
            "study solver=euler steps=50 fp8= streams=1/1",
            "fidelity solver=euler steps=8 fp8= streams=1/1",
            "study solver=euler steps=8 fp8= streams=1/1",
            "fidelity solver=euler steps=8 fp8=row streams=2/2",
            "study solver=euler steps=8 fp8=row streams=2/2",
        ]
    );
    assert!(stdout.contains("sweep: euler, 8 steps, FP8 (row scaling), 2 streams"), "{stdout}");
    let timings = fs::read_to_string(d.join("runs/w/sweep/euler-8-fp8row-streams2/timings.tsv")).unwrap();
    let stages: Vec<(&str, f64)> = timings.lines().map(|l| l.split_once('\t').unwrap()).map(|(s, v)| (s, v.parse().unwrap())).collect();
    assert_eq!(stages.iter().map(|s| s.0).collect::<Vec<_>>(), ["fidelity", "study"], "{timings}");
    assert!(stages.iter().all(|s| s.1 >= 0.0), "{timings}");
    let report: serde_json::Value = serde_json::from_str(&fs::read_to_string(d.join("runs/w/sweep/sweep.json")).unwrap()).unwrap();
    assert_eq!(report["default"], "euler-8", "{report}");
    let lanes = report["settings"].as_array().unwrap().iter().find(|r| r["setting"] == "euler-8-fp8row-streams2").unwrap();
    assert_eq!((lanes["fp8"].as_str(), lanes["streams"].as_u64()), (Some("row"), Some(2)), "{lanes}");
    assert!(lanes["seconds"]["study"].is_number(), "{lanes}");
    // The pick travels with the weights: `bwm sampler` recorded it in the newest checkpoint's
    // input contract.
    let contract: serde_json::Value = serde_json::from_str(&fs::read_to_string(d.join("runs/w/checkpoints/step-00000010/contract.json")).unwrap()).unwrap();
    let record = &contract["sampler"];
    assert_eq!((record["steps"].as_u64(), record["solver"].as_str()), (Some(8), Some("euler")), "{record}");
    assert!(record["measured"].as_str().unwrap().contains("sweep.json"), "{record}");

    // Again on the same weights: every setting is taken as measured. On weights trained again into
    // the run (the same step, other bytes), each is measured again.
    let calls = || fs::read_to_string(d.join("calls.txt")).unwrap().lines().count();
    let again = sweep();
    assert!(again.status.success() && String::from_utf8_lossy(&again.stdout).matches("measured").count() >= 3, "{again:?}");
    assert_eq!(calls(), 6);
    fs::write(d.join("runs/w/checkpoints/step-00000010/model.safetensors"), "trained again").unwrap();
    let retrained = sweep();
    assert!(retrained.status.success(), "{retrained:?}");
    assert_eq!(calls(), 12);
}

#[test]
fn detached_work_is_followed_across_waits_and_packed() {
    let name = Detached(format!("test-{}", std::process::id()));
    let out_dir = common::temp_dir("gpu-detached");
    let script = Path::new(ROOT).join("scripts/gpu/detached.sh");
    let run = |args: &[&str]| -> Output {
        Command::new("bash").arg(&script).args(args).env("OUT", out_dir.path()).output().unwrap()
    };
    // The command writes a variant-like log (progress with carriage returns), then waits for a file.
    let gate = out_dir.path().join("go");
    let work = format!(
        "mkdir -p $OUT/v; printf 'step 1/9\\nstep 2/9\\n' > $OUT/v/log; printf 'a\\r1/5 episodes' > $OUT/r.log; until [ -f {} ]; do sleep 0.2; done",
        gate.display()
    );
    let started = run(&["start", &name.0, "bash", "-c", &work]);
    assert!(started.status.success(), "{}", String::from_utf8_lossy(&started.stderr));
    let mut waited = run(&["wait", &name.0, "1"]);
    for _ in 0..20 {
        if String::from_utf8_lossy(&waited.stdout).contains("v/log: step 2/9") {
            break;
        }
        waited = run(&["wait", &name.0, "1"]);
    }
    let stdout = String::from_utf8_lossy(&waited.stdout);
    assert_eq!(waited.status.code(), Some(3), "{stdout}");
    assert!(stdout.contains("detached: v/log: step 2/9") && stdout.contains("detached: r.log: 1/5 episodes"), "{stdout}");
    assert!(out_dir.path().join(format!("{}.tar.gz", name.0)).exists());
    fs::write(&gate, "").unwrap();
    let done = run(&["wait", &name.0, "30"]);
    let stdout = String::from_utf8_lossy(&done.stdout);
    assert_eq!(done.status.code(), Some(0), "{stdout}");
    assert!(stdout.contains("ended with status 0") && !stdout.contains("v/log:"), "{stdout}");
    let listing = Command::new("tar").arg("-tzf").arg(out_dir.path().join(format!("{}.tar.gz", name.0))).output().unwrap();
    assert!(String::from_utf8_lossy(&listing.stdout).contains("out/v/log"), "{}", String::from_utf8_lossy(&listing.stdout));

    // Episode videos: the first of each videos/ folder, or those VIDEOS picks.
    let study = out_dir.path().join("study");
    let files = ["eval-0/videos/expert/t/episode_000.png", "eval-0/videos/expert/t/episode_001.png", "eval-1/videos/wrong/t/episode_003.png"];
    for f in files {
        let p = study.join(f);
        fs::create_dir_all(p.parent().unwrap()).unwrap();
        fs::write(&p, f).unwrap();
    }
    let packed = |pattern: Option<&str>| -> Vec<bool> {
        let mut wait = Command::new("bash");
        wait.arg(&script).args(["wait", &name.0, "1"]).arg(&study).env("OUT", out_dir.path());
        match pattern {
            Some(p) => wait.env("VIDEOS", p),
            None => wait.env_remove("VIDEOS"),
        };
        let o = wait.output().unwrap();
        assert_eq!(o.status.code(), Some(0), "{}", String::from_utf8_lossy(&o.stdout));
        let listing = Command::new("tar").arg("-tzf").arg(out_dir.path().join(format!("{}-videos.tar.gz", name.0))).output().unwrap();
        let listing = String::from_utf8_lossy(&listing.stdout).into_owned();
        files.iter().map(|f| listing.contains(f)).collect()
    };
    assert_eq!(packed(None), [true, false, false]);
    assert_eq!(packed(Some("*/videos/wrong/*")), [false, false, true]);
}

#[test]
fn a_binary_is_unpacked_over_the_copy_another_script_runs() {
    let dir = common::temp_dir("gpu-unpack");
    // The running copy is a real executable (`sleep`): writing over it fails with "Text file busy".
    let script = format!(
        r#"source {ROOT}/scripts/gpu/common.sh 2>/dev/null
xz -c "$(command -v sleep)" > sleep.xz || exit 9
unpack sleep.xz dist/bwm || exit 1
dist/bwm 60 & pid=$!
until [ "$(readlink /proc/$pid/exe)" = "$PWD/dist/bwm" ]; do sleep 0.05; done
unpack sleep.xz dist/bwm; rc=$?
kill -0 $pid || rc=3
kill $pid
[ "$(ls dist)" = bwm ] || rc=4
dist/bwm 0 || rc=5
exit $rc"#
    );
    let out = Command::new("bash").arg("-c").arg(&script).current_dir(dir.path()).env("OUT", dir.path().join("out")).output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn a_measured_command_that_fails_is_named_and_fails_the_script() {
    let dir = common::temp_dir("gpu-mem");
    let d = dir.path();
    fs::create_dir_all(d.join("stub")).unwrap();
    write_executable(&d.join("stub/nvidia-smi"), "#!/bin/sh\necho 100\n");
    // Two measured commands, the first failing: the second still runs, each has its memory line,
    // the failing one named, and the script exits 1 although its last command succeeded.
    let script = format!(
        r#"source {ROOT}/scripts/gpu/common.sh 2>/dev/null
mem first sh -c 'echo crashed; exit 3'; echo "first returned $?"
mem second sh -c 'echo fine'; echo "second returned $?""#
    );
    let path = format!("{}:{}", d.join("stub").display(), std::env::var("PATH").unwrap_or_default());
    let out = Command::new("bash").arg("-c").arg(&script).current_dir(d).env("OUT", d.join("out")).env("PATH", &path).output().unwrap();
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert_eq!(out.status.code(), Some(1), "{stdout}\n{stderr}");
    // (The memory figures themselves depend on whether the sampler read once before the command
    // ended: not checked.)
    assert!(stdout.contains("first: FAILED (exit status 3); peak GPU memory used") && stdout.contains("first returned 3"), "{stdout}");
    assert!(stdout.contains("second: peak GPU memory used") && stdout.contains("second returned 0"), "{stdout}");
    assert!(stderr.contains("failed: first"), "{stderr}");
    assert!(fs::read_to_string(d.join("out/first.log")).unwrap().contains("crashed"));
    // Nothing failing: the script's own status stands.
    let script = format!("source {ROOT}/scripts/gpu/common.sh 2>/dev/null\nmem ok true\nexit 0");
    let out = Command::new("bash").arg("-c").arg(&script).current_dir(d).env("OUT", d.join("out")).env("PATH", &path).output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", String::from_utf8_lossy(&out.stderr));
}

/// A GPU host in `d` for `script` (copied with common.sh): a stub bwm packed as pack.sh packs it
/// (`bwm` its shell text), a stub nvidia-smi in d/stub, and a stub reference (`reference` the text
/// of tests/reference/run_gpu.sh).
fn stub_gpu_host(d: &Path, script: &str, bwm: &str, reference: &str) {
    fs::create_dir_all(d.join("scripts/gpu")).unwrap();
    for f in ["common.sh", script] {
        fs::copy(Path::new(ROOT).join("scripts/gpu").join(f), d.join("scripts/gpu").join(f)).unwrap();
    }
    fs::create_dir_all(d.join("stub")).unwrap();
    let stub = d.join("stub/bwm");
    write_executable(&stub, bwm);
    fs::create_dir_all(d.join(".pack")).unwrap();
    let packed = Command::new("sh").arg("-c").arg(format!("xz -c {} > {}", stub.display(), d.join(".pack/bwm.xz").display())).status().unwrap();
    assert!(packed.success());
    write_executable(&d.join("stub/nvidia-smi"), "#!/bin/sh\necho 100\n");
    fs::create_dir_all(d.join("tests/reference")).unwrap();
    fs::write(d.join("tests/reference/run_gpu.sh"), reference).unwrap();
}

#[test]
fn the_fp8_timing_sets_each_step_against_the_reference_of_the_same_call() {
    let dir = common::temp_dir("gpu-fp8-train");
    let d = dir.path();
    // A stub bwm whose FP8 step is the faster, and a stub reference.
    stub_gpu_host(
        d,
        "fp8_train.sh",
        "#!/bin/sh\ncase \"$*\" in *train.fp8=true*) s=0.410 ;; *) s=0.448 ;; esac\necho \"breakdown of a $s s step (1 micro-batches of 1)\"\n",
        "echo \"$TRAIN_ARGS\" > \"$OUT/reference-args\"\necho 'reference train: 0.634 s/step (min 0.613), 1.576 samples/s' > \"$OUT/reference-train.log\"\n",
    );
    let run = |reference: &str| -> String {
        let path = format!("{}:{}", d.join("stub").display(), std::env::var("PATH").unwrap_or_default());
        let out = Command::new("bash")
            .arg("scripts/gpu/fp8_train.sh")
            .current_dir(d)
            .env("OUT", d.join("out"))
            .env("PATH", path)
            .env("REFERENCE", reference)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    let stdout = run("1");
    assert!(stdout.contains("fp8_train: bf16 0.448 s per step, the reference 0.634 s: 1.415x"), "{stdout}");
    assert!(stdout.contains("fp8_train: fp8 0.410 s per step, the reference 0.634 s: 1.546x"), "{stdout}");
    assert_eq!(fs::read_to_string(d.join("out/reference-args")).unwrap().trim(), "--no-checkpointing");
    fs::remove_dir_all(d.join("out")).unwrap();
    let stdout = run("0");
    assert!(stdout.contains("breakdown of a 0.410 s step") && !stdout.contains("fp8_train:"), "{stdout}");
    assert!(!d.join("out/reference-args").exists());
}

#[test]
fn the_5b_chunk_of_each_setting_is_set_against_the_reference_of_the_same_run() {
    let dir = common::temp_dir("gpu-realtime-5b");
    let d = dir.path();
    fs::create_dir_all(d.join("scripts/gpu")).unwrap();
    fs::copy(Path::new(ROOT).join("scripts/gpu/rollout.sh"), d.join("scripts/gpu/rollout.sh")).unwrap();
    // A stub bwm whose chunk takes 0.1 s per step, plus 1.3 s to decode with the VAE's decoder or
    // 0.1 s with the light one, and whose distillation step (bench-train) takes 9 s at first,
    // then 1 s + 0.1 s per teacher step per student step; a stub reference.
    stub_gpu_host(
        d,
        "realtime_5b.sh",
        r#"#!/bin/sh
case "$*" in *bench-train*)
  sub=$(echo "$*" | sed 's/.*--teacher-substeps \([0-9]*\).*/\1/')
  for i in 1 2 3 4 5; do awk -v s="$sub" -v i=$i 'BEGIN { printf "step %6d/5  loss 0.50000  lr 1.00e-4  grad_norm 1.000  %.2f s/step  1.0 samples/s\n", i, (i == 1 ? 9 : 1 + s * 0.1) }'; done
  exit 0 ;;
esac
steps=$(echo "$*" | sed 's/.*--sample-steps \([0-9]*\).*/\1/')
case "$*" in *--random-light-decoder*) dec=0.1 ;; *) dec=1.3 ;; esac
for i in 0 1 2; do awk -v s="$steps" -v c="$dec" -v i=$i 'BEGIN { t = 0.1 + s * 0.1 + c; printf "chunk %d: %.2f s = encode 0.10 s + DiT %.2f s (0.100 s/step) + decode %.2f s; 72 frames; %.1f generated frames/s; device memory 1 MiB used\n", i, t, s * 0.1, c, 72 / t }'; done
"#,
        "echo 'reference rollout: 10.30 s per chunk = encode 0.06 s + DiT 8.74 s (0.175 s/step) + decode 1.50 s' > \"$OUT/reference-rollout.log\"\n",
    );
    let run_distilling = |settings: &str, reference: &str, distill: Option<&str>| -> Output {
        let path = format!("{}:{}", d.join("stub").display(), std::env::var("PATH").unwrap_or_default());
        let _ = fs::remove_dir_all(d.join("out"));
        let mut cmd = Command::new("bash");
        cmd.arg("scripts/gpu/realtime_5b.sh").current_dir(d).env("OUT", d.join("out")).env("PATH", path).env("SETTINGS", settings).env("REFERENCE", reference);
        match distill {
            Some(v) => cmd.env("DISTILL", v),
            None => cmd.env_remove("DISTILL"),
        };
        cmd.output().unwrap()
    };
    let run = |settings: &str, reference: &str| run_distilling(settings, reference, Some(""));
    // The default: the chunks, then the distillation's step for students of 1 and 2 steps from
    // the teacher's 4, with LoRA (full weights not on this 100 MiB GPU).
    let out = run_distilling("light:1 full:50", "1", None);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", String::from_utf8_lossy(&out.stderr));
    for line in [
        "realtime_5b: distillation, LoRA rank 64, a student of 1 step(s) from the teacher's 4: 1.40 s per step (median of the last 3 of 5), peak GPU memory 100 MiB",
        "realtime_5b: distillation, LoRA rank 64, a student of 2 step(s) from the teacher's 4: 1.20 s per step (median of the last 3 of 5)",
        "realtime_5b: distillation, full weights, a student of 2 step(s): not run, the GPU holds 100 MiB",
    ] {
        assert!(stdout.contains(line), "no '{line}' in {stdout}");
    }
    assert_eq!(fs::read_to_string(d.join("out/realtime_5b.txt")).unwrap().lines().count(), 6);
    assert!(d.join("out/distill-lora-s1.log").is_file() && !d.join("out/distill-full-s1.log").exists());
    // A student whose steps do not divide the teacher's is refused before anything runs.
    let out = run_distilling("light:1", "1", Some("3"));
    assert!(out.status.code() == Some(2) && String::from_utf8_lossy(&out.stderr).contains("DISTILL '3'"), "{out:?}");
    assert!(!d.join("out/roll-light-s1.log").exists());
    // WEIGHTS picks the distillation's weights; an empty SETTINGS runs no chunk; other weights
    // are refused before anything runs.
    let run_weights = |weights: &str| -> Output {
        let path = format!("{}:{}", d.join("stub").display(), std::env::var("PATH").unwrap_or_default());
        let _ = fs::remove_dir_all(d.join("out"));
        Command::new("bash")
            .arg("scripts/gpu/realtime_5b.sh")
            .current_dir(d)
            .env("OUT", d.join("out"))
            .env("PATH", path)
            .envs([("SETTINGS", ""), ("REFERENCE", "0"), ("DISTILL", "1"), ("WEIGHTS", weights)])
            .output()
            .unwrap()
    };
    let out = run_weights("lora");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success() && stdout.contains("LoRA rank 64, a student of 1 step(s)") && !stdout.contains("full weights"), "{stdout}");
    assert_eq!(fs::read_to_string(d.join("out/realtime_5b.txt")).unwrap().lines().count(), 1, "{stdout}");
    assert!(!d.join("out/roll-light-s1.log").exists() && !d.join("out/distill-full-s1.log").exists());
    let out = run_weights("lora fp8");
    assert!(out.status.code() == Some(2) && String::from_utf8_lossy(&out.stderr).contains("WEIGHTS 'fp8': lora or full"), "{out:?}");
    assert!(!d.join("out/distill-lora-s1.log").exists());
    let out = run("light:1 full:50", "1");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", String::from_utf8_lossy(&out.stderr));
    assert!(
        stdout.contains("realtime_5b: light decoder, 1 steps: 0.30 s per chunk (encode 0.10 s + DiT 0.10 s + decode 0.10 s; 240.0 generated frames/s), the reference's 50-step chunk 10.30 s: 34.33x"),
        "{stdout}"
    );
    assert!(stdout.contains("realtime_5b: full decoder, 50 steps: 6.40 s per chunk") && stdout.contains("1.61x"), "{stdout}");
    assert_eq!(fs::read_to_string(d.join("out/realtime_5b.txt")).unwrap().lines().count(), 2);
    // Without the reference: the chunks alone.
    let out = run("light:4", "0");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success() && stdout.contains("light decoder, 4 steps: 0.60 s per chunk") && !stdout.contains("reference"), "{stdout}");
    // A reference that timed nothing fails the run, saying so.
    fs::write(d.join("tests/reference/run_gpu.sh"), "echo 'Traceback: out of memory' > \"$OUT/reference-rollout.log\"\n").unwrap();
    let out = run("light:1", "1");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success() && stdout.contains("no reference chunk timed") && stdout.contains("light decoder, 1 steps: 0.30 s"), "{stdout}");
    // A setting it cannot run is refused before anything runs.
    let out = run("light:1 medium:4", "1");
    assert!(out.status.code() == Some(2) && String::from_utf8_lossy(&out.stderr).contains("'medium:4': the decoder is light or full"), "{out:?}");
    assert!(!d.join("out/roll-light-s1.log").exists());
}

/// The stand-in of scripts/gpu/unit.sh's test binaries in `unit_sh_fails_where_cuda_is_missing`:
/// a test that needs CUDA and asks `bwm_testdir::need`, ignored by a plain `cargo test`, as
/// theirs are. Run with `--ignored` on a GPU machine it checks a sum on the device.
#[test]
#[ignore = "needs a CUDA device (the stand-in of scripts/gpu/unit.sh's test binaries)"]
fn needs_cuda_as_the_gpu_unit_tests_do() {
    if !bwm_testdir::need(bwm_testdir::Dep::Cuda, (!tch::Cuda::is_available()).then(|| "libtorch sees no CUDA device".to_string())) {
        return;
    }
    let x = tch::Tensor::ones([3], (tch::Kind::Float, tch::Device::Cuda(0)));
    assert_eq!(x.sum(tch::Kind::Float).double_value(&[]), 3.0);
}

/// scripts/gpu/unit.sh where libtorch sees no CUDA device (none is visible to it here, also on a
/// GPU machine): the `vae` group's CUDA-graph binary (this test binary's CUDA test standing in)
/// fails for want of CUDA, which the script itself requires (BWM_REQUIRE, whatever the caller's
/// environment says), and its trainer binary, which runs no test (a stub of a binary whose filter
/// matches nothing), fails too. Nothing of it passes.
#[test]
fn unit_sh_fails_where_cuda_is_missing() {
    let dir = common::temp_dir("gpu-unit");
    let d = dir.path();
    fs::create_dir_all(d.join("scripts/gpu")).unwrap();
    for f in ["common.sh", "unit.sh"] {
        fs::copy(Path::new(ROOT).join("scripts/gpu").join(f), d.join("scripts/gpu").join(f)).unwrap();
    }
    fs::create_dir_all(d.join("stub")).unwrap();
    let stand_in = d.join("stub/test-cuda-graph");
    let exe = std::env::current_exe().unwrap();
    write_executable(&stand_in, &format!("#!/bin/sh\nexec '{}' needs_cuda_as_the_gpu_unit_tests_do --exact \"$@\"\n", exe.display()));
    let no_test = d.join("stub/test-trainer");
    write_executable(&no_test, "#!/bin/sh\necho 'running 0 tests'\necho 'test result: ok. 0 passed; 0 failed; 0 ignored; 0 measured; 7 filtered out; finished in 0.00s'\n");
    fs::create_dir_all(d.join(".pack-tests")).unwrap();
    for stub in [&stand_in, &no_test] {
        let name = stub.file_name().unwrap().to_str().unwrap();
        let packed = Command::new("sh").arg("-c").arg(format!("xz -c '{}' > '.pack-tests/{name}.xz'", stub.display())).current_dir(d).status().unwrap();
        assert!(packed.success());
    }
    let out = Command::new("bash")
        .args(["scripts/gpu/unit.sh", "vae"])
        .current_dir(d)
        .env("OUT", d.join("out"))
        .env("CUDA_VISIBLE_DEVICES", "")
        .env("BWM_REQUIRE", "")
        .env_remove("BWM_SKIP_LOG")
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert_eq!(out.status.code(), Some(1), "{text}");
    assert!(text.contains("cuda is required (BWM_REQUIRE) but missing: libtorch sees no CUDA device"), "{text}");
    assert!(text.contains("unit: FAILED: dist/test-cuda-graph --ignored"), "{text}");
    assert!(text.contains("unit: FAILED: dist/test-trainer --ignored the_cuda_graph --test-threads 1 ran no test"), "{text}");
    assert!(!text.contains("bwm-test: SKIPPED"), "{text}");
    assert!(fs::read_to_string(d.join("out/unit.log")).unwrap().contains("ran no test"), "the log keeps the output");
}
