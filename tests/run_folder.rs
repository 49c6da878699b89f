//! One run folder, one writer, and logs that survive a kill (CPU, the tiny model): a second
//! `bwm train --resume auto` on a live run fails at once naming the holder (pid and host), and
//! after the holder is killed with SIGKILL its lock is stale and the next `--resume auto` takes the
//! run over; kills inside appends to `losses.tsv` and `metrics.jsonl` (a fault hook cuts a line in
//! half and holds the write open) are followed by `--resume auto` runs that finish with exit 0 and
//! a loss plot, every log line whole.

mod common;

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use common::{bwm, temp_dir, write_cache, write_config, Proc};

/// Generous: only guards against a hang.
const TIMEOUT: Duration = Duration::from_secs(600);

fn host() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap().trim().to_string()
}

fn train(config: &Path, resume: &str) -> Command {
    let mut c = Command::new(bwm());
    c.args(["train", "--resume", resume, "--config"]).arg(config);
    c
}

/// `bwm train --resume auto` to the end: exit 0, a loss plot; its stdout and stderr.
fn resume_to_the_end(config: &Path, run: &Path) -> String {
    let out = train(config, "auto").output().unwrap();
    let text = format!("{}\n{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{text}");
    assert!(run.join("loss.svg").is_file(), "no loss plot: {text}");
    text
}

#[test]
fn a_second_train_on_a_live_run_fails_naming_the_holder_and_a_killed_holders_lock_is_taken_over() {
    let dir = temp_dir("run-lock");
    write_cache(&dir.join("cache"));
    let run = dir.join("run");
    let config = write_config(&dir, "run.toml", &run, 3, 1);

    // The first run holds its first checkpoint write open (the fault hook) until it is killed.
    let mut first = Proc::spawn("first", train(&config, "auto").env("BWM_FAULT_SLOW_CHECKPOINT_MS", "600000"));
    first.wait_for("starting its first checkpoint write", TIMEOUT, |l| l.starts_with("checkpoint: writing"));
    let losses_before = std::fs::read_to_string(run.join("losses.tsv")).unwrap();

    let second = train(&config, "auto").output().unwrap();
    let stderr = String::from_utf8_lossy(&second.stderr);
    assert!(!second.status.success(), "a second writer of a live run must fail\n{}\n{stderr}", String::from_utf8_lossy(&second.stdout));
    let holder = format!("pid {} on host {}", first.child.id(), host());
    assert!(stderr.contains(&holder), "the error names the holder ({holder}): {stderr}");
    assert_eq!(std::fs::read_to_string(run.join("losses.tsv")).unwrap(), losses_before, "the second run wrote to the first one's log");

    // SIGKILL: the kernel releases the lock; the file still names the dead holder.
    first.signal("KILL");
    first.finish(TIMEOUT);
    let text = resume_to_the_end(&config, &run);
    assert!(text.contains(&format!("taking over from {holder}")), "the stale lock is recognized: {text}");
    let steps: Vec<u64> = bwm_trainer::run_log::read_run_losses(&run).unwrap().iter().map(|(s, _)| *s).collect();
    assert_eq!(steps, [1, 2, 3]);
}

#[test]
fn kills_inside_log_appends_then_resume_auto_finish_with_whole_lines_and_a_loss_plot() {
    let dir = temp_dir("run-append");
    write_cache(&dir.join("cache"));
    let run = dir.join("run");
    let config = write_config(&dir, "run.toml", &run, 6, 1);

    // Killed with half of step 3's line in losses.tsv, then with half of step 5's in metrics.jsonl
    // (each run checkpoints every step, so the next resumes from the step before the cut).
    for (file, step) in [("losses.tsv", 3), ("metrics.jsonl", 5)] {
        let mut killed = Proc::spawn(file, train(&config, "auto").env("BWM_FAULT_CUT_APPEND", format!("{file}:{step}")));
        let marker = format!("append: cut {file} at step {step}");
        killed.wait_for(&marker, TIMEOUT, |l| l.starts_with(&marker));
        killed.signal("KILL");
        killed.finish(TIMEOUT);
        let text = std::fs::read_to_string(run.join(file)).unwrap();
        assert!(!text.is_empty() && !text.ends_with('\n'), "{file} should end in a cut line: {text:?}");
    }
    resume_to_the_end(&config, &run);

    let losses = std::fs::read_to_string(run.join("losses.tsv")).unwrap();
    assert!(losses.ends_with('\n'), "{losses:?}");
    for line in losses.lines() {
        let parsed = line.split_once('\t').and_then(|(s, l)| Some((s.parse::<u64>().ok()?, l.parse::<f64>().ok()?)));
        assert!(parsed.is_some_and(|(_, l)| l.is_finite()), "losses.tsv line {line:?}");
    }
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    for line in metrics.lines() {
        let m: serde_json::Value = serde_json::from_str(line).unwrap_or_else(|e| panic!("metrics.jsonl line {line:?}: {e}"));
        assert!(m["step"].as_u64().is_some() && m["loss"].as_f64().is_some(), "{line}");
    }
    let read: Vec<u64> = bwm_trainer::run_log::read_run_losses(&run).unwrap().iter().map(|(s, _)| *s).collect();
    assert_eq!(read, [1, 2, 3, 4, 5, 6]);
}
