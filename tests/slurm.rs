//! `bwm submit` through a real Slurm: a one-host cluster (scripts/slurm/start-local.sh: munged,
//! slurmctld, slurmd under a temporary folder) runs a 2-rank CPU training job submitted with
//! sbatch to completion, and a second one through the time-limit warning: checkpoint, requeue,
//! resume, completion. Skipped, with the reason printed, only where `sbatch` is not installed
//! and BWM_REQUIRE_SLURM is unset (CI sets it).

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use common::*;

fn scripts() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/slurm")
}

/// The running daemons; dropped (also when the test fails), it cancels the job if it is still
/// running and stops them.
struct Cluster {
    dir: PathBuf,
    conf: PathBuf,
    job: Option<u64>,
}

impl Cluster {
    fn start(dir: &Path) -> Cluster {
        let ctld = free_port_pair();
        let slurmd = ctld + 1;
        let cluster = Cluster {
            dir: dir.to_path_buf(),
            conf: dir.join("slurm.conf"),
            job: None,
        };
        let out = Command::new("bash")
            .arg(scripts().join("start-local.sh"))
            .arg(dir)
            .env("BWM_SLURMCTLD_PORT", ctld.to_string())
            .env("BWM_SLURMD_PORT", slurmd.to_string())
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "start-local.sh failed:\n{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        cluster
    }

    fn slurm(&self, program: &str) -> Command {
        let mut c = Command::new(program);
        c.env("SLURM_CONF", &self.conf);
        c
    }

    /// `scontrol show job`'s fields of the job.
    fn job_fields(&self, id: u64) -> String {
        let out = self
            .slurm("scontrol")
            .args(["show", "job", &id.to_string()])
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).to_string()
    }
}

fn field<'a>(fields: &'a str, name: &str) -> Option<&'a str> {
    fields
        .split_whitespace()
        .find_map(|kv| kv.strip_prefix(name)?.strip_prefix('='))
}

impl Drop for Cluster {
    fn drop(&mut self) {
        if let Some(id) = self.job {
            let state = field(&self.job_fields(id), "JobState")
                .unwrap_or("")
                .to_string();
            if matches!(
                state.as_str(),
                "PENDING" | "RUNNING" | "CONFIGURING" | "COMPLETING" | "REQUEUED"
            ) {
                let _ = self.slurm("scancel").arg(id.to_string()).status();
                let until = Instant::now() + Duration::from_secs(40);
                while Instant::now() < until
                    && !matches!(
                        field(&self.job_fields(id), "JobState"),
                        Some("CANCELLED" | "COMPLETED" | "FAILED")
                    )
                {
                    std::thread::sleep(Duration::from_millis(500));
                }
            }
        }
        let _ = Command::new("bash")
            .arg(scripts().join("stop-local.sh"))
            .arg(&self.dir)
            .status();
    }
}

/// `sbatch` on PATH (running it needs a configuration, which only the test cluster has).
fn sbatch_installed() -> bool {
    use std::os::unix::fs::PermissionsExt;
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path).any(|d| {
        std::fs::metadata(d.join("sbatch"))
            .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
    })
}

fn dump_logs(dir: &Path) -> String {
    let mut text = String::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "out" || x == "log") {
                text += &format!(
                    "==> {} <==\n{}\n",
                    p.display(),
                    std::fs::read_to_string(&p).unwrap_or_default()
                );
            }
        }
    }
    text
}

/// `bwm submit` of a 2-rank CPU training job; returns the job id.
fn submit(
    cluster: &Cluster,
    dir: &Path,
    job_name: &str,
    config: &Path,
    env: &[(&str, &str)],
) -> u64 {
    let out = cluster
        .slurm(bwm().to_str().unwrap())
        .args([
            "submit",
            "--nodes",
            "1",
            "--gpus-per-node",
            "0",
            "--nproc-per-node",
            "2",
            "--time",
            "10",
            "--job-name",
            job_name,
            "--output-dir",
        ])
        .arg(dir.join("slurm"))
        .args(["--", "train", "--config"])
        .arg(config)
        .envs(env.iter().copied())
        .current_dir(dir)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
        .lines()
        .find_map(|l| l.strip_prefix("submitted batch job "))
        .unwrap_or_else(|| panic!("no job id in {stdout:?}"))
        .trim()
        .parse()
        .unwrap()
}

/// Polls `scontrol show job` until `done` holds for the job's fields.
fn wait_job(
    cluster: &Cluster,
    id: u64,
    what: &str,
    logs: &Path,
    done: impl Fn(&str) -> bool,
) -> String {
    let deadline = Instant::now() + Duration::from_secs(240);
    loop {
        let fields = cluster.job_fields(id);
        if done(&fields) {
            return fields;
        }
        assert!(
            Instant::now() < deadline,
            "job {id} not {what} after 240 s:\n{fields}\n{}",
            dump_logs(logs)
        );
        std::thread::sleep(Duration::from_millis(500));
    }
}

fn finished(fields: &str) -> bool {
    !matches!(
        field(fields, "JobState").unwrap_or(""),
        "" | "PENDING" | "CONFIGURING" | "RUNNING" | "COMPLETING" | "REQUEUED"
    )
}

#[test]
fn submit_runs_a_two_rank_cpu_job_to_completion_on_a_local_slurm_cluster() {
    if !sbatch_installed() {
        assert!(
            std::env::var_os("BWM_REQUIRE_SLURM").is_none(),
            "BWM_REQUIRE_SLURM is set but sbatch is not installed (scripts/setup.sh installs slurm-wlm and munge)"
        );
        eprintln!("skipped: sbatch is not installed (scripts/setup.sh installs slurm-wlm and munge; BWM_REQUIRE_SLURM=1 makes this a failure)");
        return;
    }
    let started = Instant::now();
    let dir = temp_dir("slurm");
    let mut cluster = Cluster::start(&dir.join("cluster"));
    eprintln!("cluster up in {:.1} s", started.elapsed().as_secs_f64());
    write_cache(&dir.join("cache"));
    let steps = 4;
    let config = write_config(&dir, "run.toml", &dir.join("run"), steps, 1);
    let logs = dir.join("slurm");
    let id = submit(&cluster, &dir, "bwm-test", &config, &[]);
    cluster.job = Some(id);
    let script = std::fs::read_to_string(logs.join("bwm-test.sbatch")).unwrap();
    assert!(
        script.contains("#SBATCH --requeue") && !script.contains("--gres"),
        "{script}"
    );
    let fields = wait_job(&cluster, id, "finished", &logs, finished);
    let logs_text = dump_logs(&logs);
    assert_eq!(
        field(&fields, "JobState"),
        Some("COMPLETED"),
        "{fields}\n{logs_text}"
    );
    assert_eq!(
        field(&fields, "ExitCode"),
        Some("0:0"),
        "{fields}\n{logs_text}"
    );
    assert_eq!(latest_step(&dir.join("run")), steps, "{logs_text}");
    assert!(
        dir.join(format!("run/checkpoints/step-{steps:08}/state.json"))
            .is_file(),
        "{logs_text}"
    );
    let job_logs = logs.join(format!("bwm-test-{id}"));
    let node0 = std::fs::read_to_string(job_logs.join("node-0.out")).unwrap_or_default();
    assert!(
        node0.contains("launch: node 0, 2 ranks here, world 2"),
        "{logs_text}"
    );
    for rank in 0..2 {
        let log =
            std::fs::read_to_string(job_logs.join(format!("rank-{rank}.log"))).unwrap_or_default();
        assert!(
            log.contains(&format!("done: step {steps}")),
            "rank {rank}:\n{logs_text}"
        );
    }
    eprintln!(
        "first job done after {:.1} s",
        started.elapsed().as_secs_f64()
    );

    // Slurm's warning before the time limit (`--signal=B:USR1@...`, sent here by hand): the ranks
    // checkpoint and stop, the job requeues itself, and its next start resumes and completes.
    let steps = 12;
    let config = write_config(&dir, "requeue.toml", &dir.join("requeue"), steps, 1);
    let id = submit(
        &cluster,
        &dir,
        "bwm-requeue",
        &config,
        &[("BWM_FAULT_SLOW_CHECKPOINT_MS", "300")],
    );
    cluster.job = Some(id);
    let job_logs = logs.join(format!("bwm-requeue-{id}"));
    let rank0 = || std::fs::read_to_string(job_logs.join("rank-0.log")).unwrap_or_default();
    let deadline = Instant::now() + Duration::from_secs(240);
    while !rank0().contains("checkpoints/step-00000002") {
        assert!(
            Instant::now() < deadline,
            "no checkpoint of step 2 after 240 s:\n{}",
            dump_logs(&logs)
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    let signalled = cluster
        .slurm("scancel")
        .args(["--batch", "--signal=USR1", &id.to_string()])
        .status()
        .unwrap();
    assert!(signalled.success());
    eprintln!("USR1 sent after {:.1} s", started.elapsed().as_secs_f64());
    // The requeued job starts again after the credential lifetime (10 s on the test cluster).
    wait_job(&cluster, id, "requeued", &logs, |f| field(f, "Restarts") == Some("1"));
    eprintln!("requeued after {:.1} s", started.elapsed().as_secs_f64());
    let fields = wait_job(&cluster, id, "finished", &logs, finished);
    let logs_text = dump_logs(&logs);
    assert_eq!(
        field(&fields, "JobState"),
        Some("COMPLETED"),
        "{fields}\n{logs_text}"
    );
    let log = rank0();
    let stop = log
        .lines()
        .find_map(|l| l.strip_prefix("stopped by signal at step "))
        .unwrap_or_else(|| panic!("{logs_text}"));
    let stop_step: u64 = stop.split(';').next().unwrap().parse().unwrap();
    assert!((2..steps).contains(&stop_step), "{logs_text}");
    assert!(
        log.contains(&format!("at step {stop_step}: "))
            && log.contains(&format!("done: step {steps}")),
        "{logs_text}"
    );
    let batch =
        std::fs::read_to_string(logs.join(format!("bwm-requeue-{id}.out"))).unwrap_or_default();
    assert!(
        batch.contains(&format!("requeueing job {id}")),
        "{logs_text}"
    );
    assert_eq!(latest_step(&dir.join("requeue")), steps, "{logs_text}");
    drop(cluster);
    eprintln!("slurm test took {:.1} s", started.elapsed().as_secs_f64());
}

#[test]
fn submit_without_sbatch_says_so() {
    let dir = temp_dir("submit-no-sbatch");
    let out = Command::new(bwm())
        .args(["submit", "--gpus-per-node", "1", "--output-dir"])
        .arg(&dir)
        .args(["--", "train", "--config", "x.toml"])
        .env("PATH", &dir)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("`sbatch` was not found on PATH") && stderr.contains("--dry-run"),
        "{stderr}"
    );
    // The script is written before the submission, so it can be submitted by hand.
    assert!(dir.join("bwm.sbatch").is_file());
    let dry = Command::new(bwm())
        .args([
            "submit",
            "--gpus-per-node",
            "1",
            "--dry-run",
            "--",
            "train",
            "--config",
            "x.toml",
        ])
        .env("PATH", &dir)
        .output()
        .unwrap();
    assert!(
        dry.status.success(),
        "{}",
        String::from_utf8_lossy(&dry.stderr)
    );
    assert!(String::from_utf8_lossy(&dry.stdout).starts_with("#!/bin/bash\n#"));
}
