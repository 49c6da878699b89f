//! `bwm submit`: a Slurm batch script that runs one `bwm launch` per node of the allocation
//! (`srun`, one task per node), written to the output folder and submitted with `sbatch`. Before
//! the time limit Slurm signals the script, which has the ranks checkpoint and stop, then requeues
//! the job; every start of the job resumes the run (`--resume auto`).

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, ensure, Context, Result};
use clap::Args;

#[derive(Args, Debug)]
pub struct SubmitArgs {
    /// Nodes to allocate; each runs one `bwm launch`.
    #[arg(long, default_value_t = 1)]
    nodes: usize,
    /// GPUs per node (`--gres=gpu:N`); 0 runs CPU ranks (see --nproc-per-node).
    #[arg(long)]
    gpus_per_node: usize,
    /// Ranks per node (default: --gpus-per-node, or 1 without GPUs).
    #[arg(long)]
    nproc_per_node: Option<usize>,
    /// CPUs for each node's task (the launcher and its ranks); without it the cluster's default
    /// for a task, often one CPU (said when submitting).
    #[arg(long)]
    cpus_per_task: Option<usize>,
    #[arg(long)]
    partition: Option<String>,
    /// Time limit, in any of sbatch's formats (minutes, HH:MM:SS, D-HH:MM:SS).
    #[arg(long)]
    time: Option<String>,
    #[arg(long)]
    account: Option<String>,
    #[arg(long, default_value = "bwm")]
    job_name: String,
    /// Folder for the batch script and the logs (`<job-name>-<job id>/node-N.out`, `rank-R.log`).
    #[arg(long, default_value = "runs/slurm")]
    output_dir: PathBuf,
    /// Restarts of the whole group within one job run (`bwm launch --max-restarts`).
    #[arg(long, default_value_t = 0)]
    max_restarts: u32,
    /// Rank 0's port on the first node (default: 29500 + 2 x (job id mod 5000), so that jobs
    /// sharing a node differ); the launchers' agent store uses the next one.
    #[arg(long)]
    master_port: Option<u16>,
    /// Seconds before the time limit at which Slurm warns the job (default 180, or a third of
    /// --time when that is less). Slurm looks every 30 s, so the warning comes up to 30 s earlier.
    /// The ranks get all but 60 of them (half of them below 120) to checkpoint and stop; the rest
    /// is for the requeue.
    #[arg(long)]
    signal_before: Option<u32>,
    /// Print the script; write and submit nothing.
    #[arg(long)]
    dry_run: bool,
    /// The `bwm` subcommand every rank runs, e.g. `-- train --config configs/wan5b.toml`.
    #[arg(last = true, required = true)]
    command: Vec<String>,
}

pub fn run(a: SubmitArgs) -> Result<()> {
    let exe = std::env::current_exe().context("locating the bwm binary")?;
    let cwd = std::env::current_dir().context("reading the current directory")?;
    let out = if a.output_dir.is_absolute() {
        a.output_dir.clone()
    } else {
        cwd.join(&a.output_dir)
    };
    let text = script(&a, &exe, &cwd, &out)?;
    if a.cpus_per_task.is_none() {
        eprintln!(
            "bwm submit: no --cpus-per-task: each node's task (the launcher, its ranks and their data loading) gets the CPUs the cluster gives a task by default, often one; set it to the node's cores"
        );
    }
    if a.dry_run {
        print!("{text}");
        return Ok(());
    }
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let path = out.join(format!("{}.sbatch", a.job_name));
    std::fs::write(&path, &text).with_context(|| format!("writing {}", path.display()))?;
    let id = sbatch("sbatch", &path)?;
    println!("submitted batch job {id}");
    println!(
        "script {}; logs in {}",
        path.display(),
        out.join(format!("{}-{id}", a.job_name)).display()
    );
    Ok(())
}

/// Runs `sbatch <script>` and returns the job id it reports.
fn sbatch(program: &str, script: &Path) -> Result<u64> {
    let output = match Command::new(program).arg(script).output() {
        Ok(o) => o,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => bail!(
            "`{program}` was not found on PATH: `bwm submit` needs Slurm's client commands (--dry-run prints the script without them); the script is {}",
            script.display()
        ),
        Err(e) => return Err(e).with_context(|| format!("running {program} {}", script.display())),
    };
    let stdout = String::from_utf8_lossy(&output.stdout);
    ensure!(
        output.status.success(),
        "{program} {} failed ({}): {}{}",
        script.display(),
        output.status,
        String::from_utf8_lossy(&output.stderr).trim(),
        stdout.trim()
    );
    job_id(&stdout).with_context(|| {
        format!(
            "{program} did not report a job id (\"Submitted batch job <id>\"); it printed: {}",
            stdout.trim()
        )
    })
}

fn job_id(sbatch_stdout: &str) -> Option<u64> {
    sbatch_stdout.lines().find_map(|l| {
        l.trim()
            .strip_prefix("Submitted batch job ")?
            .split_whitespace()
            .next()?
            .parse()
            .ok()
    })
}

/// `s` as one shell word.
fn quote(s: &str) -> String {
    let plain = !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "_-./:=@%+,".contains(c));
    if plain {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

/// A name or limit on an `#SBATCH` line (and, for the job name, in the script's paths).
fn directive_value(flag: &str, v: &str) -> Result<String> {
    ensure!(
        !v.is_empty()
            && v.chars()
                .all(|c| c.is_ascii_alphanumeric() || "_-.:,+=@/".contains(c)),
        "{flag} {v:?}: use letters, digits and _-.:,+=@/ only"
    );
    Ok(v.to_string())
}

/// A path on an `#SBATCH` line, which sbatch does not unquote.
fn path_value(flag: &str, p: &Path) -> Result<String> {
    let s = p
        .to_str()
        .with_context(|| format!("{flag} {}: not UTF-8", p.display()))?;
    ensure!(
        !s.contains('%'),
        "{flag} {s}: `%` would be read as a Slurm filename pattern"
    );
    ensure!(
        !s.chars()
            .any(|c| c.is_whitespace() || c.is_control() || "'\"\\$`#".contains(c)),
        "{flag} {s:?}: Slurm paths cannot hold spaces, quotes, `$`, `#` or backslashes"
    );
    Ok(s.to_string())
}

/// Seconds of an sbatch `--time` (minutes, MM:SS, HH:MM:SS, D-HH, D-HH:MM or D-HH:MM:SS), rounded
/// up to whole minutes as Slurm does; `None` for no limit (0, -1, INFINITE, UNLIMITED).
fn time_limit_seconds(t: &str) -> Result<Option<u64>> {
    if matches!(t.to_ascii_uppercase().as_str(), "-1" | "INFINITE" | "UNLIMITED") {
        return Ok(None);
    }
    let bad = || anyhow::anyhow!("--time {t}: not one of sbatch's formats (minutes, MM:SS, HH:MM:SS, D-HH, D-HH:MM, D-HH:MM:SS)");
    // At most 9 digits a field: no sum below overflows.
    let number = |s: &str| -> Result<u64> {
        ensure!(!s.is_empty() && s.len() <= 9 && s.bytes().all(|b| b.is_ascii_digit()), bad());
        Ok(s.parse()?)
    };
    let (days, clock) = match t.split_once('-') {
        Some((d, rest)) => (Some(number(d)?), rest),
        None => (None, t),
    };
    let fields = clock.split(':').map(number).collect::<Result<Vec<u64>>>()?;
    let seconds = match (days, fields.as_slice()) {
        (None, [m]) => m * 60,
        (None, [m, s]) => m * 60 + s,
        (None, [h, m, s]) => h * 3600 + m * 60 + s,
        (Some(d), [h]) => d * 86400 + h * 3600,
        (Some(d), [h, m]) => d * 86400 + h * 3600 + m * 60,
        (Some(d), [h, m, s]) => d * 86400 + h * 3600 + m * 60 + s,
        _ => return Err(bad()),
    };
    let minutes = seconds.div_ceil(60);
    Ok((minutes > 0).then_some(minutes * 60))
}

/// Seconds before the time limit at which Slurm warns the job, and the ranks' part of them (the
/// launchers' --grace-period).
fn warning(a: &SubmitArgs) -> Result<(u32, u32)> {
    let limit = match &a.time {
        Some(t) => time_limit_seconds(t)?,
        None => None,
    };
    let before = a
        .signal_before
        .unwrap_or_else(|| limit.map_or(180, |l| (l / 3).min(180) as u32));
    ensure!(
        before >= 10,
        "--signal-before {before} leaves the ranks no time to checkpoint before the job requeues itself: give at least 10 s"
    );
    if let (Some(limit), Some(t)) = (limit, &a.time) {
        // Slurm looks at the limits every 30 s and warns at the first look within `before` + 30 s
        // of the limit: a warning that can come as the job starts comes at every requeued start.
        ensure!(
            u64::from(before) + 30 < limit,
            "--signal-before {before} with --time {t} ({limit} s): Slurm looks at the limits every 30 s, so it may warn the job {} s before its limit, as it starts (and at every requeued start); give a --signal-before below {} s",
            u64::from(before) + 30,
            limit.saturating_sub(30)
        );
    }
    let requeue = (before / 2).min(60);
    Ok((before, before - requeue))
}

/// The batch script for `a`, running `exe` from `cwd` with logs under `out`.
fn script(a: &SubmitArgs, exe: &Path, cwd: &Path, out: &Path) -> Result<String> {
    ensure!(a.nodes > 0, "--nodes must be at least 1");
    let nproc = a.nproc_per_node.unwrap_or(a.gpus_per_node.max(1));
    ensure!(nproc > 0, "--nproc-per-node must be at least 1");
    ensure!(
        a.gpus_per_node == 0 || nproc <= a.gpus_per_node,
        "--nproc-per-node {nproc} exceeds --gpus-per-node {}: each rank takes one GPU",
        a.gpus_per_node
    );
    ensure!(
        a.cpus_per_task != Some(0),
        "--cpus-per-task must be at least 1"
    );
    let (signal_before, grace) = warning(a)?;
    ensure!(
        a.master_port.is_none_or(|p| p > 0 && p < u16::MAX),
        "--master-port must be 1-65534 (the agent store takes the next port)"
    );
    let job_name = directive_value("--job-name", &a.job_name)?;
    let mut command = a.command.clone();
    // Only a training run continues where it stopped: it alone is stopped before the time limit
    // and requeued. Another command runs once, to its end or the limit.
    let requeues = command.first().map(String::as_str) == Some("train");
    if requeues {
        // Every start of the job, the first and each requeue, continues the run.
        match command
            .iter()
            .position(|c| c == "--resume" || c.starts_with("--resume="))
        {
            None => command.extend(["--resume".to_string(), "auto".to_string()]),
            Some(i) => {
                let value = command[i]
                    .strip_prefix("--resume=")
                    .or(command.get(i + 1).map(String::as_str))
                    .unwrap_or("");
                ensure!(value == "auto", "`--resume {value}`: a requeued job must continue its run; leave --resume out (bwm submit adds `--resume auto`)");
            }
        }
    }

    let mut s = String::from("#!/bin/bash\n");
    s.push_str("# Written by `bwm submit`. Runs one `bwm launch` per node; the job inherits the environment of the\n");
    s.push_str("# shell that submitted it (LD_LIBRARY_PATH for libtorch included).\n");
    let mut directive = |d: String| s.push_str(&format!("#SBATCH {d}\n"));
    directive(format!("--job-name={job_name}"));
    directive(format!("--nodes={}", a.nodes));
    directive("--ntasks-per-node=1".into());
    if a.gpus_per_node > 0 {
        directive(format!("--gres=gpu:{}", a.gpus_per_node));
    }
    if let Some(c) = a.cpus_per_task {
        directive(format!("--cpus-per-task={c}"));
    }
    if let Some(p) = &a.partition {
        directive(format!(
            "--partition={}",
            directive_value("--partition", p)?
        ));
    }
    if let Some(acc) = &a.account {
        directive(format!("--account={}", directive_value("--account", acc)?));
    }
    if let Some(t) = &a.time {
        directive(format!("--time={}", directive_value("--time", t)?));
    }
    if requeues {
        directive("--requeue".into());
        directive(format!("--signal=B:USR1@{signal_before}"));
    }
    directive("--open-mode=append".into());
    directive(format!(
        "--output={}/%x-%j.out",
        path_value("--output-dir", out)?
    ));
    directive(format!(
        "--chdir={}",
        path_value("the current directory", cwd)?
    ));

    let logs = format!(
        "{}/{job_name}-\"$SLURM_JOB_ID\"",
        quote(&path_value("--output-dir", out)?)
    );
    s.push_str(&format!("\nLOGS={logs}\nmkdir -p \"$LOGS\"\n"));
    s.push_str("MASTER_ADDR=\"$(scontrol show hostnames \"$SLURM_JOB_NODELIST\" | head -n1)\"\n");
    match a.master_port {
        Some(p) => s.push_str(&format!("MASTER_PORT={p}\n")),
        // Two ports a job (the master's and, one above, the launchers' agent store): consecutive
        // job ids on one host do not collide.
        None => s.push_str("MASTER_PORT=$((29500 + 2 * (SLURM_JOB_ID % 5000)))\n"),
    }
    s.push_str(if requeues {
        "\n# Slurm's warning before the time limit (USR1, to this shell only): SIGTERM to every process of\n\
         # the job's steps (`scancel --signal` leaves the batch shell out), on which the ranks checkpoint\n\
         # and stop and the launchers exit 0; then the job requeues itself. (srun itself is not signalled:\n\
         # it answers SIGTERM by killing its step.) On scancel or preemption Slurm sends SIGTERM to all\n\
         # processes itself; this shell then keeps waiting for the checkpoint.\n\
         requeue=0\n\
         trap 'requeue=1; scancel --signal=TERM \"$SLURM_JOB_ID\"' USR1\n\
         trap 'true' TERM\n"
    } else {
        "\n# Not a training run: it runs once, to its end or the time limit (it cannot continue where it\n\
         # stopped, so it is not requeued). On scancel or preemption this shell waits for it to stop.\n\
         trap 'true' TERM\n"
    });
    let mut srun = vec![
        "srun".to_string(),
        format!("--nodes={}", a.nodes),
        "--ntasks-per-node=1".into(),
    ];
    if let Some(c) = a.cpus_per_task {
        srun.push(format!("--cpus-per-task={c}"));
    }
    srun.extend([
        "--kill-on-bad-exit=1".to_string(),
        "--output=\"$LOGS/node-%n.out\"".to_string(),
    ]);
    let exe = exe
        .to_str()
        .with_context(|| format!("the bwm binary's path {} is not UTF-8", exe.display()))?;
    let launch = [
        // SLURM_NNODES and SLURM_NODEID are expanded in each node's task, not in this script.
        quote(r#"exec "$0" launch --nnodes "$SLURM_NNODES" --node-rank "$SLURM_NODEID" "$@""#),
        quote(exe),
        format!("--nproc-per-node {nproc}"),
        "--master-addr \"$MASTER_ADDR\" --master-port \"$MASTER_PORT\"".into(),
        format!("--max-restarts {} --grace-period {grace}", a.max_restarts),
        "--log-dir \"$LOGS\"".into(),
        format!(
            "-- {}",
            command
                .iter()
                .map(|c| quote(c))
                .collect::<Vec<_>>()
                .join(" ")
        ),
    ];
    s.push_str(&format!(
        "{} bash -c \\\n  {} \\\n  &\n",
        srun.join(" "),
        launch.join(" \\\n  ")
    ));
    s.push_str(
        "step=$!\n\
         # `wait` returns early when a trapped signal arrives; wait again until the step has exited.\n\
         while kill -0 \"$step\" 2>/dev/null; do wait \"$step\"; done\n\
         wait \"$step\"\n\
         status=$?\n",
    );
    if requeues {
        s.push_str(
            "if [ \"$requeue\" = 1 ]; then\n  \
               echo \"bwm submit: requeueing job $SLURM_JOB_ID before its time limit; it resumes from the last checkpoint\"\n  \
               scontrol requeue \"$SLURM_JOB_ID\"\n\
             fi\n",
        );
    }
    s.push_str("exit \"$status\"\n");
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: SubmitArgs,
    }

    fn args(argv: &[&str]) -> SubmitArgs {
        Cli::try_parse_from(std::iter::once("submit").chain(argv.iter().copied()))
            .unwrap()
            .args
    }

    fn render(argv: &[&str]) -> Result<String> {
        script(
            &args(argv),
            Path::new("/opt/bwm/bwm"),
            Path::new("/home/u/bwm"),
            Path::new("/home/u/bwm/runs/slurm"),
        )
    }

    #[test]
    fn gpu_job_on_two_nodes() {
        let s = render(&[
            "--nodes",
            "2",
            "--gpus-per-node",
            "8",
            "--cpus-per-task",
            "64",
            "--partition",
            "h200",
            "--time",
            "2-00:00:00",
            "--account",
            "robots",
            "--job-name",
            "wan5b",
            "--max-restarts",
            "2",
            "--",
            "train",
            "--config",
            "configs/wan 5b.toml",
        ])
        .unwrap();
        for line in [
            "#SBATCH --job-name=wan5b\n",
            "#SBATCH --nodes=2\n",
            "#SBATCH --ntasks-per-node=1\n",
            "#SBATCH --gres=gpu:8\n",
            "#SBATCH --cpus-per-task=64\n",
            "#SBATCH --partition=h200\n",
            "#SBATCH --account=robots\n",
            "#SBATCH --time=2-00:00:00\n",
            "#SBATCH --requeue\n",
            "#SBATCH --signal=B:USR1@180\n",
            "#SBATCH --output=/home/u/bwm/runs/slurm/%x-%j.out\n",
            "#SBATCH --chdir=/home/u/bwm\n",
            "LOGS=/home/u/bwm/runs/slurm/wan5b-\"$SLURM_JOB_ID\"\n",
            "MASTER_ADDR=\"$(scontrol show hostnames \"$SLURM_JOB_NODELIST\" | head -n1)\"\n",
            "MASTER_PORT=$((29500 + 2 * (SLURM_JOB_ID % 5000)))\n",
            "srun --nodes=2 --ntasks-per-node=1 --cpus-per-task=64 --kill-on-bad-exit=1 --output=\"$LOGS/node-%n.out\" bash -c \\\n",
            "  'exec \"$0\" launch --nnodes \"$SLURM_NNODES\" --node-rank \"$SLURM_NODEID\" \"$@\"' \\\n  /opt/bwm/bwm \\\n  --nproc-per-node 8 \\\n",
            "  --max-restarts 2 --grace-period 120 \\\n",
            "  -- train --config 'configs/wan 5b.toml' --resume auto \\\n  &\n",
            "scontrol requeue \"$SLURM_JOB_ID\"\n",
            "trap 'requeue=1; scancel --signal=TERM \"$SLURM_JOB_ID\"' USR1\n",
        ] {
            assert!(s.contains(line), "missing {line:?} in\n{s}");
        }
        assert!(s.starts_with("#!/bin/bash\n"));
        // sbatch reads #SBATCH lines only before the first command.
        let first_command = s
            .lines()
            .position(|l| !l.starts_with('#') && !l.is_empty())
            .unwrap();
        assert!(
            s.lines()
                .skip(first_command)
                .all(|l| !l.starts_with("#SBATCH")),
            "{s}"
        );
    }

    #[test]
    fn cpu_job_has_no_gres_and_keeps_an_explicit_resume_auto() {
        let s = render(&[
            "--gpus-per-node",
            "0",
            "--nproc-per-node",
            "2",
            "--master-port",
            "31000",
            "--",
            "train",
            "--resume",
            "auto",
            "--config",
            "c.toml",
        ])
        .unwrap();
        assert!(!s.contains("--gres"), "{s}");
        assert!(
            !s.contains("--partition") && !s.contains("--time") && !s.contains("--cpus-per-task"),
            "{s}"
        );
        assert!(
            s.contains("#SBATCH --nodes=1\n") && s.contains("--nproc-per-node 2 "),
            "{s}"
        );
        assert!(s.contains("MASTER_PORT=31000\n"), "{s}");
        assert!(
            s.contains("-- train --resume auto --config c.toml \\\n"),
            "{s}"
        );
        assert_eq!(s.matches("--resume").count(), 1, "{s}");
    }

    #[test]
    fn a_command_that_cannot_resume_is_not_requeued() {
        let s = render(&["--gpus-per-node", "1", "--time", "04:00:00", "--", "train-vae", "--data", "d", "--out", "v.safetensors"]).unwrap();
        assert!(!s.contains("--requeue") && !s.contains("USR1") && !s.contains("scontrol requeue"), "{s}");
        assert!(s.contains("-- train-vae --data d --out v.safetensors \\\n") && !s.contains("--resume"), "{s}");
        assert!(s.contains("trap 'true' TERM\n"), "{s}");
        let dir = bwm_testdir::TestDir::new("submit-once");
        std::fs::write(dir.join("job.sh"), &s).unwrap();
        assert!(Command::new("bash").arg("-n").arg(dir.join("job.sh")).status().unwrap().success(), "{s}");
    }

    #[test]
    fn the_script_runs_in_bash() {
        // Syntax check of the whole script (bash -n parses without running).
        let s = render(&[
            "--gpus-per-node",
            "1",
            "--",
            "train",
            "--config",
            "it's.toml",
        ])
        .unwrap();
        let dir = bwm_testdir::TestDir::new("submit");
        let path = dir.join("job.sh");
        std::fs::write(&path, &s).unwrap();
        let out = Command::new("bash").arg("-n").arg(&path).output().unwrap();
        assert!(
            out.status.success(),
            "{}\n{s}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(s.contains(r"'it'\''s.toml'"), "{s}");
    }

    #[test]
    fn bad_inputs_are_refused() {
        let e = |argv: &[&str]| format!("{:#}", render(argv).unwrap_err());
        assert!(
            e(&["--gpus-per-node", "1", "--", "train", "--resume", "no"]).contains("--resume no")
        );
        assert!(e(&[
            "--gpus-per-node",
            "2",
            "--nproc-per-node",
            "4",
            "--",
            "train"
        ])
        .contains("exceeds --gpus-per-node"));
        assert!(e(&[
            "--gpus-per-node",
            "1",
            "--job-name",
            "my job",
            "--",
            "train"
        ])
        .contains("--job-name"));
        assert!(
            e(&["--gpus-per-node", "1", "--partition", "a$b", "--", "train"])
                .contains("--partition")
        );
        assert!(e(&["--gpus-per-node", "1", "--nodes", "0", "--", "train"]).contains("--nodes"));
        assert!(e(&[
            "--gpus-per-node",
            "1",
            "--signal-before",
            "5",
            "--",
            "train"
        ])
        .contains("--signal-before"));
        let out = script(
            &args(&["--gpus-per-node", "1", "--", "train"]),
            Path::new("/b"),
            Path::new("/c"),
            Path::new("/logs/%j"),
        );
        assert!(format!("{:#}", out.unwrap_err()).contains("filename pattern"));
    }

    #[test]
    fn a_one_minute_limit_is_warned_inside_it() {
        // Slurm warns between S and S + 30 s before the limit (it looks every 30 s): the default
        // warning of a 1-minute job is a third of it, so the job runs some seconds first.
        let s = render(&["--gpus-per-node", "0", "--time", "1", "--", "train"]).unwrap();
        assert!(s.contains("#SBATCH --time=1\n") && s.contains("#SBATCH --signal=B:USR1@20\n"), "{s}");
        assert!(s.contains("--grace-period 10 "), "{s}");
        let s = render(&["--gpus-per-node", "0", "--time", "0:50", "--signal-before", "12", "--", "train"]).unwrap();
        assert!(s.contains("#SBATCH --signal=B:USR1@12\n") && s.contains("--grace-period 6 "), "{s}");
        // Long limits keep 180 s, 60 of them for the requeue.
        let s = render(&["--gpus-per-node", "0", "--time", "10:00:00", "--", "train"]).unwrap();
        assert!(s.contains("#SBATCH --signal=B:USR1@180\n") && s.contains("--grace-period 120 "), "{s}");
        let e = |argv: &[&str]| format!("{:#}", render(argv).unwrap_err());
        // A warning that may come as the job starts would come again at every requeued start.
        let early = e(&["--gpus-per-node", "0", "--time", "1", "--signal-before", "30", "--", "train"]);
        assert!(early.contains("--signal-before 30") && early.contains("--time 1 (60 s)"), "{early}");
        assert!(e(&["--gpus-per-node", "0", "--time", "3", "--signal-before", "180", "--", "train"]).contains("--time 3 (180 s)"));
        assert!(render(&["--gpus-per-node", "0", "--time", "4", "--signal-before", "180", "--", "train"]).is_ok());
        assert!(e(&["--gpus-per-node", "0", "--time", "1:x", "--", "train"]).contains("sbatch's formats"));
    }

    #[test]
    fn time_limits_in_sbatch_formats() {
        for (t, secs) in [
            ("1", Some(60)),
            ("90", Some(5400)),
            ("0:30", Some(60)),
            ("1:30", Some(120)),
            ("2:00:00", Some(7200)),
            ("1:00:01", Some(3660)),
            ("2-0", Some(172800)),
            ("1-2:03", Some(93780)),
            ("1-02:03:04", Some(93840)),
            ("0", None),
            ("UNLIMITED", None),
            ("infinite", None),
            ("-1", None),
        ] {
            assert_eq!(time_limit_seconds(t).unwrap(), secs, "{t}");
        }
        for t in ["", "x", "1:2:3:4", "1-", "-", "1-2-3", "1:", "99999999999"] {
            assert!(time_limit_seconds(t).is_err(), "{t}");
        }
    }

    #[test]
    fn job_id_from_sbatch_output() {
        assert_eq!(job_id("Submitted batch job 4242\n"), Some(4242));
        assert_eq!(
            job_id("sbatch: warning: x\nSubmitted batch job 17 on cluster c\n"),
            Some(17)
        );
        assert_eq!(job_id("sbatch: error: Batch job submission failed\n"), None);
    }

    #[test]
    fn missing_sbatch_is_a_clear_error() {
        let e = format!(
            "{:#}",
            sbatch("/nonexistent/bwm-test/sbatch", Path::new("/tmp/x.sbatch")).unwrap_err()
        );
        assert!(
            e.contains("was not found") && e.contains("--dry-run"),
            "{e}"
        );
    }
}
