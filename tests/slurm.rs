//! `bwm submit` through a real Slurm of two nodes on this machine (scripts/slurm/start-local.sh):
//! each node a network namespace with its own address on a bridge, node 1 also running munged and
//! slurmctld, the run folder shared as a cluster's filesystem is. A 2-node x 2-rank CPU job
//! rendezvouses across the namespaces (the ranks of node 2 connect to node 1's address), gets the
//! warning of its 1-minute time limit from Slurm itself, checkpoints, requeues, resumes and
//! finishes with the weights of an uninterrupted 4-rank run, bit for bit; `scancel` of a running
//! 2-node job stops both nodes cleanly. Each test brings up its own cluster and removes it, also
//! when it fails. Without Slurm or network namespaces the tests are skipped (`bwm_testdir::need`;
//! BWM_REQUIRE=slurm makes that a failure).

mod common;

use std::collections::BTreeMap;
use std::net::Ipv4Addr;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use bwm_testdir::{need, Dep};
use common::*;

const MINUTE: Duration = Duration::from_secs(60);

fn scripts() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/slurm")
}

fn on_path(program: &str) -> bool {
    use std::os::unix::fs::PermissionsExt;
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path).any(|d| std::fs::metadata(d.join(program)).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0))
}

/// Why the two-node test cluster cannot run here, if it cannot (found out once per process: the
/// tests ask in parallel).
fn cluster_missing() -> Option<String> {
    static ANSWER: std::sync::OnceLock<Option<String>> = std::sync::OnceLock::new();
    ANSWER.get_or_init(find_cluster_missing).clone()
}

fn find_cluster_missing() -> Option<String> {
    let slurm: Vec<&str> = ["sbatch", "scontrol", "scancel", "sinfo", "slurmctld", "slurmd", "munged", "mungekey"].into_iter().filter(|p| !on_path(p)).collect();
    if !slurm.is_empty() {
        return Some(format!("{} not on PATH (scripts/setup.sh --tests installs slurm-wlm and munge)", slurm.join(", ")));
    }
    let tools: Vec<&str> = ["ip", "nsenter", "unshare", "flock"].into_iter().filter(|p| !on_path(p)).collect();
    if !tools.is_empty() {
        return Some(format!("{} not on PATH (iproute2, util-linux)", tools.join(", ")));
    }
    // The nodes are network namespaces: try to make one.
    let probe = format!("bwm-netns-probe-{}", std::process::id());
    let out = Command::new("ip").args(["netns", "add", &probe]).output();
    match out {
        Ok(o) if o.status.success() => {
            let _ = Command::new("ip").args(["netns", "del", &probe]).status();
            None
        }
        Ok(o) => Some(format!("network namespaces cannot be made here (`ip netns add`: {}); the test cluster needs root", String::from_utf8_lossy(&o.stderr).trim())),
        Err(e) => Some(format!("running ip: {e}")),
    }
}

struct Node {
    name: String,
    namespace: String,
    addr: Ipv4Addr,
}

/// A running cluster; dropped (also when the test fails), it is stopped and removed with whatever
/// its jobs left (scripts/slurm/stop-local.sh).
struct Cluster {
    dir: PathBuf,
    conf: PathBuf,
    nodes: Vec<Node>,
}

impl Cluster {
    fn start(dir: &Path) -> Cluster {
        let out = Command::new("bash")
            .arg(scripts().join("start-local.sh"))
            .arg(dir)
            .env("BWM_SLURM_NODES", "2")
            // A run killed before this guard drops leaves a cluster that the next start removes.
            .env("BWM_SLURM_OWNER_PID", std::process::id().to_string())
            .output()
            .unwrap();
        // Parsed before the check, so that a half-made cluster is removed too.
        let env = std::fs::read_to_string(dir.join("cluster.env")).unwrap_or_default();
        let fields: BTreeMap<&str, &str> = env.split_whitespace().filter_map(|kv| kv.split_once('=')).collect();
        let nodes = (1..=2)
            .filter_map(|i| {
                Some(Node {
                    name: fields.get(format!("NODE{i}").as_str())?.to_string(),
                    namespace: fields.get(format!("NS{i}").as_str())?.to_string(),
                    addr: fields.get(format!("ADDR{i}").as_str())?.parse().ok()?,
                })
            })
            .collect();
        let cluster = Cluster { dir: dir.to_path_buf(), conf: dir.join("slurm.conf"), nodes };
        assert!(out.status.success(), "start-local.sh failed:\n{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        assert_eq!(cluster.nodes.len(), 2, "cluster.env:\n{env}");
        cluster
    }

    fn slurm(&self, program: &str) -> Command {
        let mut c = Command::new(program);
        c.env("SLURM_CONF", &self.conf);
        c
    }

    /// `scontrol show job`'s fields of the job.
    fn job_fields(&self, id: u64) -> String {
        let out = self.slurm("scontrol").args(["show", "job", &id.to_string()]).output().unwrap();
        String::from_utf8_lossy(&out.stdout).to_string()
    }

    /// The processes in node `i`'s network namespace that are not the cluster's daemons: a job's.
    fn job_processes(&self, i: usize) -> Vec<String> {
        let out = Command::new("ip").args(["netns", "pids", &self.nodes[i].namespace]).output().unwrap();
        String::from_utf8_lossy(&out.stdout)
            .split_whitespace()
            .filter_map(|pid| {
                let comm = std::fs::read_to_string(format!("/proc/{pid}/comm")).ok()?;
                let comm = comm.trim();
                let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
                let cmdline = String::from_utf8_lossy(&cmdline).replace('\0', " ");
                (!matches!(comm, "slurmd" | "slurmctld" | "slurmscriptd" | "munged")).then(|| format!("{pid} {comm}: {}", cmdline.trim()))
            })
            .collect()
    }

    /// Waits until no job process is left on either node; returns those left after `timeout`.
    fn wait_no_job_processes(&self, timeout: Duration) -> Vec<String> {
        let deadline = Instant::now() + timeout;
        loop {
            let left: Vec<String> = (0..self.nodes.len()).flat_map(|i| self.job_processes(i).into_iter().map(move |p| format!("node {}: {p}", i + 1))).collect();
            if left.is_empty() || Instant::now() > deadline {
                return left;
            }
            std::thread::sleep(Duration::from_millis(500));
        }
    }

    /// The established TCP connections in node `i`'s namespace, as (local, remote) addresses.
    fn connections(&self, i: usize) -> Vec<((Ipv4Addr, u16), (Ipv4Addr, u16))> {
        let out = Command::new("ip").args(["netns", "pids", &self.nodes[i].namespace]).output().unwrap();
        let Some(pid) = String::from_utf8_lossy(&out.stdout).split_whitespace().next().map(str::to_string) else { return vec![] };
        // /proc/PID/net/tcp lists the sockets of PID's network namespace.
        let table = std::fs::read_to_string(format!("/proc/{pid}/net/tcp")).unwrap_or_default();
        let endpoint = |s: &str| -> Option<(Ipv4Addr, u16)> {
            let (ip, port) = s.split_once(':')?;
            Some((Ipv4Addr::from(u32::from_str_radix(ip, 16).ok()?.to_le_bytes()), u16::from_str_radix(port, 16).ok()?))
        };
        table
            .lines()
            .skip(1)
            .filter_map(|l| {
                let f: Vec<&str> = l.split_whitespace().collect();
                (f.get(3) == Some(&"01")).then_some(())?;
                Some((endpoint(f.get(1)?)?, endpoint(f.get(2)?)?))
            })
            .collect()
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = Command::new("bash").arg(scripts().join("stop-local.sh")).arg(&self.dir).status();
    }
}

fn field<'a>(fields: &'a str, name: &str) -> Option<&'a str> {
    fields.split_whitespace().find_map(|kv| kv.strip_prefix(name)?.strip_prefix('='))
}

/// The tail of every log under `dir` (the job's, the ranks', the daemons'), for failure messages.
fn dump_logs(dir: &Path) -> String {
    let mut text = String::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "out" || x == "log") {
                let all = std::fs::read_to_string(&p).unwrap_or_default();
                let lines: Vec<&str> = all.lines().collect();
                text += &format!("==> {} <==\n{}\n", p.display(), lines[lines.len().saturating_sub(40)..].join("\n"));
            }
        }
    }
    text
}

/// `bwm submit` of a 2-node x 2-rank CPU training job; returns the job id.
fn submit(cluster: &Cluster, dir: &Path, job_name: &str, time: &str, config: &Path, env: &[(&str, &str)]) -> u64 {
    let out = cluster
        .slurm(bwm().to_str().unwrap())
        .args(["submit", "--nodes", "2", "--gpus-per-node", "0", "--nproc-per-node", "2", "--time", time, "--job-name", job_name, "--output-dir"])
        .arg(dir.join("slurm"))
        .args(["--", "train", "--config"])
        .arg(config)
        .envs(env.iter().copied())
        .current_dir(dir)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(out.status.success(), "{stdout}{}", String::from_utf8_lossy(&out.stderr));
    stdout
        .lines()
        .find_map(|l| l.strip_prefix("submitted batch job "))
        .unwrap_or_else(|| panic!("no job id in {stdout:?}"))
        .trim()
        .parse()
        .unwrap()
}

/// The job has ended for good (a requeued job passes through other states, SIGNALING among them).
fn finished(fields: &str) -> bool {
    matches!(
        field(fields, "JobState").unwrap_or(""),
        "COMPLETED" | "CANCELLED" | "FAILED" | "TIMEOUT" | "NODE_FAIL" | "PREEMPTED" | "BOOT_FAIL" | "DEADLINE" | "OUT_OF_MEMORY"
    )
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}

/// The master host and port of a node's launcher line ("launch: node N, 2 ranks here, world 4,
/// master HOST:PORT (attempt 1)").
fn master_of(node_log: &str) -> Option<(String, u16)> {
    let line = node_log.lines().find(|l| l.starts_with("launch: node "))?;
    let master = line.split(", master ").nth(1)?.split_whitespace().next()?;
    let (host, port) = master.rsplit_once(':')?;
    Some((host.to_string(), port.parse().ok()?))
}

/// What is left in a run's checkpoint folder of writes that did not finish (`.step-*.tmp-*`,
/// staging folders, `.latest.tmp-*`).
fn unfinished_writes(run: &Path) -> Vec<String> {
    std::fs::read_dir(run.join("checkpoints"))
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with('.'))
        .collect()
}

#[test]
fn a_two_node_job_warned_by_its_time_limit_requeues_and_ends_with_the_weights_of_an_uninterrupted_run() {
    if !need(Dep::Slurm, cluster_missing()) {
        return;
    }
    let started = Instant::now();
    let dir = temp_dir("slurm-requeue");
    let cluster = Cluster::start(&dir.join("cluster"));
    eprintln!("cluster up in {:.1} s", started.elapsed().as_secs_f64());
    write_cache(&dir.join("cache"));
    // Every step writes a checkpoint that takes at least 2 s (the fault hook), so that the run
    // outlasts the warning of a 1-minute limit on any machine: Slurm sends it 10 to 40 s after the
    // start (`bwm submit`'s default for --time 1 is --signal-before 20; Slurm looks every 30 s).
    // One libtorch thread a rank: 8 ranks (the job's and the reference's) share the cores.
    let steps = 25;
    let config = write_config(&dir, "run.toml", &dir.join("run"), steps, 1);
    let logs = dir.join("slurm");
    let id = submit(&cluster, &dir, "bwm-requeue", "1", &config, &[("BWM_FAULT_SLOW_CHECKPOINT_MS", "2000"), ("OMP_NUM_THREADS", "1")]);
    let script = read(&logs.join("bwm-requeue.sbatch"));
    assert!(script.contains("#SBATCH --time=1\n") && script.contains("#SBATCH --signal=B:USR1@20\n") && script.contains("#SBATCH --nodes=2\n"), "{script}");

    // The uninterrupted reference meanwhile: the same world of 4 ranks and global batch, on one host.
    let reference_config = write_config(&dir, "reference.toml", &dir.join("reference"), steps, 1);
    let port = free_port_pair().to_string();
    let mut reference = Proc::spawn(
        "reference",
        Command::new(bwm()).args(["launch", "--nproc-per-node", "4", "--master-port", &port, "--", "train", "--config"]).arg(&reference_config).env("OMP_NUM_THREADS", "1"),
    );

    let job_logs = logs.join(format!("bwm-requeue-{id}"));
    let (node1, node2) = (&cluster.nodes[0], &cluster.nodes[1]);
    let mut crossed = None;
    let mut lifted = false;
    let deadline = Instant::now() + 10 * MINUTE;
    let fields = loop {
        let fields = cluster.job_fields(id);
        if finished(&fields) {
            break fields;
        }
        // Requeued once by its limit, the job gets 10 minutes, so that the resumed run finishes in
        // one go (with 1 minute it would be warned and requeued every minute, which works, slowly).
        if !lifted && field(&fields, "Restarts").is_some_and(|r| r != "0") {
            let update = cluster.slurm("scontrol").args(["update", &format!("JobId={id}"), "TimeLimit=10"]).output().unwrap();
            assert!(update.status.success(), "scontrol update: {}", String::from_utf8_lossy(&update.stderr));
            lifted = true;
        }
        // The ranks of node 2 reach rank 0 at node 1's namespace address, over the veths.
        if crossed.is_none() {
            if let Some((host, port)) = master_of(&read(&job_logs.join("node-1.out"))) {
                assert_eq!(host, node1.name, "MASTER_ADDR is node 1's name");
                crossed = cluster.connections(1).into_iter().find(|(local, remote)| local.0 == node2.addr && *remote == (node1.addr, port));
            }
        }
        assert!(Instant::now() < deadline, "job {id} not finished after 10 minutes:\n{fields}\n{}", dump_logs(&dir));
        std::thread::sleep(Duration::from_millis(500));
    };
    eprintln!("job finished after {:.1} s", started.elapsed().as_secs_f64());
    let logs_text = dump_logs(&dir);
    assert_eq!(field(&fields, "JobState"), Some("COMPLETED"), "{fields}\n{logs_text}");
    assert_eq!(field(&fields, "ExitCode"), Some("0:0"), "{fields}\n{logs_text}");
    let ((local, _), (remote, port)) = crossed.unwrap_or_else(|| panic!("no connection from node 2 ({}) to rank 0 on node 1 ({}) seen\n{logs_text}", node2.addr, node1.addr));
    eprintln!("node 2 {local} -> node 1 {remote}:{port}");
    let node0 = read(&job_logs.join("node-0.out"));
    assert!(node0.contains("launch: node 0, 2 ranks here, world 4"), "{logs_text}");

    // Slurm's warning (nobody else signals the job) requeued it once; the ranks stopped on it
    // with a checkpoint, which the next start resumed.
    assert_eq!(field(&fields, "Restarts"), Some("1"), "{fields}\n{logs_text}");
    let batch = read(&logs.join(format!("bwm-requeue-{id}.out")));
    assert_eq!(batch.matches(&format!("requeueing job {id} before its time limit")).count(), 1, "{logs_text}");
    let rank0 = read(&job_logs.join("rank-0.log"));
    let stops: Vec<u64> = rank0
        .lines()
        .filter_map(|l| l.strip_prefix("stopped by signal at step ")?.split(';').next()?.parse().ok())
        .collect();
    let [stop] = stops[..] else { panic!("stops at {stops:?}:\n{logs_text}") };
    assert!((1..steps).contains(&stop), "stopped at step {stop}:\n{logs_text}");
    assert!(rank0.contains(&format!("step-{stop:08} at step {stop}: ")), "no resume from step {stop}:\n{logs_text}");
    assert!(rank0.contains(&format!("done: step {steps}")), "{logs_text}");
    for rank in 0..4 {
        assert!(read(&job_logs.join(format!("rank-{rank}.log"))).contains(&format!("done: step {steps}")), "rank {rank}:\n{logs_text}");
    }
    assert_eq!(latest_step(&dir.join("run")), steps, "{logs_text}");
    assert_eq!(cluster.wait_no_job_processes(MINUTE), Vec::<String>::new(), "left on the nodes after the job");

    let status = reference.finish(10 * MINUTE);
    assert!(status.success(), "{}", reference.text());
    let (a, b) = (final_weights(&dir.join("reference")), final_weights(&dir.join("run")));
    assert_eq!(a.len(), b.len());
    for ((na, ta), (nb, tb)) in a.iter().zip(&b) {
        assert_eq!(na, nb);
        assert!(ta.equal(tb), "{na} differs from the uninterrupted run's (stopped at step {stop})");
    }
    assert_eq!(unfinished_writes(&dir.join("run")), Vec::<String>::new());
    drop(cluster);
    eprintln!("requeue test took {:.1} s (stopped at step {stop})", started.elapsed().as_secs_f64());
}

#[test]
fn scancel_of_a_running_two_node_job_stops_both_nodes_cleanly() {
    if !need(Dep::Slurm, cluster_missing()) {
        return;
    }
    let started = Instant::now();
    let dir = temp_dir("slurm-scancel");
    let cluster = Cluster::start(&dir.join("cluster"));
    write_cache(&dir.join("cache"));
    let steps = 1000;
    let config = write_config(&dir, "run.toml", &dir.join("run"), steps, 1);
    // Checkpoint writes that take a while: a stop that is not clean would cut one.
    let id = submit(&cluster, &dir, "bwm-scancel", "10", &config, &[("BWM_FAULT_SLOW_CHECKPOINT_MS", "300"), ("OMP_NUM_THREADS", "1")]);
    let job_logs = dir.join(format!("slurm/bwm-scancel-{id}"));
    let deadline = Instant::now() + 5 * MINUTE;
    // Training on both nodes: rank 0 (node 1) has checkpointed twice and rank 2 (node 2) runs.
    while !(read(&job_logs.join("rank-0.log")).contains("checkpoints/step-00000002") && read(&job_logs.join("rank-2.log")).contains("run ")) {
        assert!(Instant::now() < deadline, "job {id} did not train on both nodes within 5 minutes:\n{}\n{}", cluster.job_fields(id), dump_logs(&dir));
        std::thread::sleep(Duration::from_millis(200));
    }
    assert!(!cluster.job_processes(0).is_empty() && !cluster.job_processes(1).is_empty(), "the job runs on both nodes");
    let cancelled = cluster.slurm("scancel").arg(id.to_string()).status().unwrap();
    assert!(cancelled.success());
    eprintln!("scancel after {:.1} s", started.elapsed().as_secs_f64());
    let deadline = Instant::now() + 3 * MINUTE;
    let fields = loop {
        let fields = cluster.job_fields(id);
        if finished(&fields) {
            break fields;
        }
        assert!(Instant::now() < deadline, "job {id} not ended 3 minutes after scancel:\n{fields}\n{}", dump_logs(&dir));
        std::thread::sleep(Duration::from_millis(500));
    };
    let left = cluster.wait_no_job_processes(2 * MINUTE);
    let logs_text = dump_logs(&dir);
    assert_eq!(field(&fields, "JobState"), Some("CANCELLED"), "{fields}\n{logs_text}");
    assert_eq!(left, Vec::<String>::new(), "left on the nodes after scancel:\n{logs_text}");
    let run = dir.join("run");
    assert_eq!(unfinished_writes(&run), Vec::<String>::new(), "a checkpoint write was cut:\n{logs_text}");
    let latest = latest_step(&run);
    assert!(run.join(format!("checkpoints/step-{latest:08}/state.json")).is_file(), "{logs_text}");
    // Both nodes' ranks stopped on the SIGTERM at one step, which rank 0 checkpointed.
    for rank in 0..4 {
        let log = read(&job_logs.join(format!("rank-{rank}.log")));
        assert!(log.contains(&format!("stopped by signal at step {latest}; checkpoint ")), "rank {rank}:\n{logs_text}");
    }
    drop(cluster);
    eprintln!("scancel test took {:.1} s", started.elapsed().as_secs_f64());
}

#[test]
fn submit_without_sbatch_says_so() {
    let dir = temp_dir("submit-no-sbatch");
    let out = Command::new(bwm()).args(["submit", "--gpus-per-node", "1", "--output-dir"]).arg(&dir).args(["--", "train", "--config", "x.toml"]).env("PATH", &dir).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(stderr.contains("`sbatch` was not found on PATH") && stderr.contains("--dry-run"), "{stderr}");
    // The script is written before the submission, so it can be submitted by hand.
    assert!(dir.join("bwm.sbatch").is_file());
    let dry = Command::new(bwm()).args(["submit", "--gpus-per-node", "1", "--dry-run", "--", "train", "--config", "x.toml"]).env("PATH", &dir).output().unwrap();
    assert!(dry.status.success(), "{}", String::from_utf8_lossy(&dry.stderr));
    assert!(String::from_utf8_lossy(&dry.stdout).starts_with("#!/bin/bash\n#"));
}
