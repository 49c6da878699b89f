//! `bwm launch`: one process per GPU (or N CPU processes) with torchrun's environment variables;
//! forwards SIGINT/SIGTERM as SIGTERM, on which the ranks checkpoint and stop (exit 0 when they all
//! did); when a rank fails, stops the others and restarts the group (training resumes from its
//! last complete checkpoint with `--resume auto`). With several nodes, one launcher per node, and
//! node 0's launcher hosts an agent store (`agent`) through which all of them start, restart and
//! stop together.

mod agent;

use std::fs::OpenOptions;
use std::net::{SocketAddr, TcpListener, ToSocketAddrs};
use std::os::unix::process::ExitStatusExt;
use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context, Result};
use clap::Args;

/// How long the surviving ranks of a failed group get after SIGTERM: they cannot checkpoint (the
/// collective needs every rank), so waiting longer only delays the restart.
const FAILURE_GRACE: Duration = Duration::from_secs(10);

#[derive(Args)]
pub struct LaunchArgs {
    /// Processes on this node (default: one per visible GPU, else 1).
    #[arg(long)]
    nproc_per_node: Option<usize>,
    /// Nodes of the job, each running one `bwm launch` (inside Slurm: SLURM_NNODES when left at 1).
    #[arg(long, default_value_t = 1)]
    nnodes: usize,
    /// This node's index, 0..nnodes (inside Slurm: SLURM_NODEID when --nnodes is left at 1).
    #[arg(long, default_value_t = 0)]
    node_rank: usize,
    /// Address of node 0, where rank 0 hosts the collective and, with several nodes, the
    /// launchers' agent store listens.
    #[arg(long, default_value = "127.0.0.1")]
    master_addr: String,
    #[arg(long, default_value_t = 29500)]
    master_port: u16,
    /// Port of the launchers' agent store on node 0 (several nodes only; default: --master-port + 1).
    #[arg(long)]
    agent_port: Option<u16>,
    /// Restarts of the whole group (all nodes) after a rank or a node fails.
    #[arg(long, default_value_t = 0)]
    max_restarts: u32,
    /// Seconds the ranks get to checkpoint and exit after SIGTERM before they are killed.
    #[arg(long, default_value_t = 120.0)]
    grace_period: f64,
    /// Seconds without a heartbeat after which a node (or node 0's agent store) counts as failed.
    #[arg(long, default_value_t = 30.0)]
    heartbeat_timeout: f64,
    /// Seconds to wait for every node's launcher to join, at the start and at each restart.
    #[arg(long, default_value_t = 300.0)]
    rdzv_timeout: f64,
    /// Append each rank's stdout and stderr to `DIR/rank-<RANK>.log` instead of the launcher's.
    #[arg(long, value_name = "DIR")]
    log_dir: Option<PathBuf>,
    /// The `bwm` subcommand each rank runs, e.g. `-- train --config configs/tiny.toml`.
    #[arg(last = true, required = true)]
    command: Vec<String>,
}

/// Slurm's view of the job, when the launcher runs inside one (`srun bwm launch ...`).
fn slurm_defaults(a: &mut LaunchArgs) -> Result<()> {
    let var = |n: &str| std::env::var(n).ok();
    if let (Some(nodes), Some(node)) = (var("SLURM_NNODES"), var("SLURM_NODEID")) {
        if a.nnodes == 1 {
            a.nnodes = nodes
                .trim()
                .parse()
                .with_context(|| format!("SLURM_NNODES={nodes:?} is not a number"))?;
            a.node_rank = node
                .trim()
                .parse()
                .with_context(|| format!("SLURM_NODEID={node:?} is not a number"))?;
        }
    }
    Ok(())
}

fn seconds(flag: &str, value: f64) -> Result<Duration> {
    ensure!(
        value.is_finite() && value > 0.0 && value < 1e9,
        "{flag} {value} is not a positive number of seconds"
    );
    Ok(Duration::from_secs_f64(value))
}

/// What this launcher starts: its node's ranks of the job.
struct Plan {
    exe: PathBuf,
    command: Vec<String>,
    nproc: usize,
    node_rank: usize,
    world: usize,
    master_addr: String,
    master_port: u16,
    library_path: String,
    /// The folder of the `libnccl.so` link that `library_path` names, removed with the plan.
    _nccl_link: Option<tempfile::TempDir>,
    log_dir: Option<PathBuf>,
    grace: Duration,
}

/// `command` (a `train` command line) with `--resume auto` in place of any `--resume VALUE` or
/// `--resume=VALUE`.
fn resuming(command: &[String]) -> Vec<String> {
    let mut out = Vec::with_capacity(command.len() + 2);
    let mut words = command.iter();
    while let Some(w) = words.next() {
        if w == "--resume" {
            words.next();
        } else if !w.starts_with("--resume=") {
            out.push(w.clone());
        }
    }
    out.extend(["--resume".to_string(), "auto".to_string()]);
    out
}

impl Plan {
    /// Starts this node's ranks; attempts after the first resume the run from its latest
    /// checkpoint (`--resume auto`, in place of any `--resume` the command gave: a fixed
    /// checkpoint would redo the work since it, and may have been pruned).
    fn spawn(&self, attempt: u32) -> Result<Ranks> {
        let command = if attempt > 0 && self.command.first().map(String::as_str) == Some("train") {
            resuming(&self.command)
        } else {
            self.command.clone()
        };
        eprintln!(
            "launch: node {}, {} ranks here, world {}, master {}:{} (attempt {})",
            self.node_rank,
            self.nproc,
            self.world,
            self.master_addr,
            self.master_port,
            attempt + 1
        );
        if let Some(dir) = &self.log_dir {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("creating --log-dir {}", dir.display()))?;
        }
        let mut ranks = Ranks {
            procs: Vec::with_capacity(self.nproc),
            failed: Vec::new(),
        };
        for local in 0..self.nproc {
            let rank = self.node_rank * self.nproc + local;
            let mut c = Command::new(&self.exe);
            c.args(&command)
                .env("RANK", rank.to_string())
                .env("LOCAL_RANK", local.to_string())
                .env("WORLD_SIZE", self.world.to_string())
                .env("LOCAL_WORLD_SIZE", self.nproc.to_string())
                .env("GROUP_RANK", self.node_rank.to_string())
                .env("MASTER_ADDR", &self.master_addr)
                .env("MASTER_PORT", self.master_port.to_string())
                .env("NCCL_NVLS_ENABLE", "0")
                .env("LD_LIBRARY_PATH", &self.library_path);
            if let Some(dir) = &self.log_dir {
                let path = dir.join(format!("rank-{rank}.log"));
                let log = OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(&path)
                    .with_context(|| format!("opening {}", path.display()))?;
                c.stdout(Stdio::from(log.try_clone()?))
                    .stderr(Stdio::from(log));
            }
            // On an error the ranks already started are killed when `ranks` drops.
            let child = c
                .spawn()
                .with_context(|| format!("starting rank {rank} ({})", self.exe.display()))?;
            ranks.procs.push(Proc {
                rank,
                child,
                status: None,
            });
        }
        Ok(ranks)
    }
}

/// This node's running ranks.
struct Ranks {
    procs: Vec<Proc>,
    /// Positions in `procs` of the ranks that exited otherwise than 0, in the order seen.
    failed: Vec<usize>,
}

struct Proc {
    rank: usize,
    child: Child,
    status: Option<ExitStatus>,
}

enum Outcome {
    /// Every rank exited 0.
    Finished,
    /// Why the group failed: the first rank seen to exit otherwise.
    Failed(String),
}

impl Ranks {
    fn refresh(&mut self) -> Result<()> {
        let mut newly_failed = Vec::new();
        for (i, p) in self.procs.iter_mut().enumerate().filter(|(_, p)| p.status.is_none()) {
            p.status = p
                .child
                .try_wait()
                .with_context(|| format!("waiting for rank {}", p.rank))?;
            if p.status.is_some_and(|s| !s.success()) {
                newly_failed.push(i);
            }
        }
        // Seen in the same look, a rank killed by a signal is more likely the cause than one that
        // exited with an error (its peers fail when it disappears).
        newly_failed.sort_by_key(|&i| self.procs[i].status.and_then(|s| s.signal()).is_none());
        self.failed.extend(newly_failed);
        Ok(())
    }

    fn first_failure(&self) -> Option<String> {
        self.failed.first().map(|&i| {
            let p = &self.procs[i];
            format!("rank {} exited with {}", p.rank, p.status.expect("a failed rank has a status"))
        })
    }

    /// `None` while ranks run and none has failed.
    fn poll(&mut self) -> Result<Option<Outcome>> {
        self.refresh()?;
        if let Some(why) = self.first_failure() {
            return Ok(Some(Outcome::Failed(why)));
        }
        Ok(self
            .procs
            .iter()
            .all(|p| p.status.is_some())
            .then_some(Outcome::Finished))
    }

    /// SIGTERM to the ranks still running, `grace` for them to exit, then SIGKILL. Returns why
    /// the stop was not clean (a rank exited non-zero or had to be killed), `None` when it was.
    fn stop(&mut self, grace: Duration) -> Option<String> {
        let _ = self.refresh();
        let alive: Vec<String> = self.procs.iter().filter(|p| p.status.is_none()).map(|p| p.child.id().to_string()).collect();
        if !alive.is_empty() {
            // The shell's builtin `kill`: std sends no signal but SIGKILL, and a `kill` binary is
            // not on every image.
            let _ = Command::new("sh").arg("-c").arg(r#"kill -TERM "$@""#).arg("sh").args(&alive).status();
        }
        let deadline = Instant::now() + grace;
        while self.procs.iter().any(|p| p.status.is_none()) && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(100));
            let _ = self.refresh();
        }
        let mut killed = Vec::new();
        for p in self.procs.iter_mut().filter(|p| p.status.is_none()) {
            let _ = p.child.kill();
            p.status = p.child.wait().ok();
            killed.push(p.rank);
        }
        if !killed.is_empty() {
            return Some(format!(
                "rank(s) {killed:?} did not exit within {:.0} s of SIGTERM and were killed",
                grace.as_secs_f64()
            ));
        }
        self.first_failure()
    }
}

impl Drop for Ranks {
    fn drop(&mut self) {
        for p in self.procs.iter_mut().filter(|p| p.status.is_none()) {
            if let Ok(None) = p.child.try_wait() {
                let _ = p.child.kill();
                let _ = p.child.wait();
            }
        }
    }
}

pub fn run(mut a: LaunchArgs) -> Result<()> {
    slurm_defaults(&mut a)?;
    let nproc = a
        .nproc_per_node
        .unwrap_or_else(|| (tch::Cuda::device_count() as usize).max(1));
    ensure!(
        nproc > 0 && a.nnodes > 0,
        "--nproc-per-node and --nnodes must be at least 1"
    );
    ensure!(
        a.node_rank < a.nnodes,
        "--node-rank {} is not below --nnodes {}",
        a.node_rank,
        a.nnodes
    );
    ensure!(a.master_port != 0, "--master-port 0 is not a port");
    let grace = seconds("--grace-period", a.grace_period)?;
    let heartbeat_timeout = seconds("--heartbeat-timeout", a.heartbeat_timeout)?;
    let rdzv_timeout = seconds("--rdzv-timeout", a.rdzv_timeout)?;
    let master: Vec<SocketAddr> = (a.master_addr.as_str(), a.master_port)
        .to_socket_addrs()
        .with_context(|| format!("--master-addr {} does not resolve", a.master_addr))?
        .collect();
    ensure!(
        !master.is_empty(),
        "--master-addr {} resolves to no address",
        a.master_addr
    );
    let exe = std::env::current_exe().context("locating the bwm binary")?;
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone())
            .context("installing the SIGINT/SIGTERM handler")?;
    }
    if a.node_rank == 0 {
        // Rank 0 listens on this port on every interface; a clash is clearer here than from it.
        TcpListener::bind(SocketAddr::new(unspecified(&master[0]), a.master_port)).with_context(
            || {
                format!(
                    "--master-port {} is in use on this host (node 0 hosts rank 0 there)",
                    a.master_port
                )
            },
        )?;
    }
    let (library_path, nccl_link) = nccl_library_path();
    let plan = Plan {
        exe,
        command: a.command.clone(),
        nproc,
        node_rank: a.node_rank,
        world: nproc * a.nnodes,
        master_addr: a.master_addr.clone(),
        master_port: a.master_port,
        library_path,
        _nccl_link: nccl_link,
        log_dir: a.log_dir.clone(),
        grace,
    };
    if a.nnodes == 1 {
        return run_single(&plan, a.max_restarts, &stop);
    }
    let agent_port = match a.agent_port {
        Some(p) => p,
        None => a
            .master_port
            .checked_add(1)
            .context("--master-port 65535 leaves no port for the agent store; pass --agent-port")?,
    };
    ensure!(
        agent_port != 0 && agent_port != a.master_port,
        "--agent-port must differ from --master-port and not be 0"
    );
    let settings = agent::Settings {
        nnodes: a.nnodes,
        node_rank: a.node_rank,
        nproc,
        command: a.command.clone(),
        max_restarts: a.max_restarts,
        heartbeat_timeout,
        rdzv_timeout,
        grace,
    };
    let store_addr: Vec<SocketAddr> = master
        .iter()
        .map(|m| SocketAddr::new(m.ip(), agent_port))
        .collect();
    if a.node_rank == 0 {
        let store = agent::host(
            SocketAddr::new(unspecified(&master[0]), agent_port),
            &settings,
        )?;
        let loopback = SocketAddr::new(
            if master[0].is_ipv4() {
                [127, 0, 0, 1].into()
            } else {
                std::net::Ipv6Addr::LOCALHOST.into()
            },
            agent_port,
        );
        let mine = agent::member(&[loopback], &settings, &plan, &stop);
        let hosted = store
            .join()
            .unwrap_or_else(|_| Err(anyhow::anyhow!("the agent store thread panicked")));
        return match (mine, hosted) {
            (Ok(()), hosted) => hosted,
            (Err(mine), Ok(())) => Err(mine),
            (Err(mine), Err(hosted)) => {
                if mine.to_string() != hosted.to_string() {
                    eprintln!("error: {hosted:#}");
                }
                Err(mine)
            }
        };
    }
    agent::member(&store_addr, &settings, &plan, &stop)
}

fn unspecified(addr: &SocketAddr) -> std::net::IpAddr {
    match addr {
        SocketAddr::V4(_) => std::net::Ipv4Addr::UNSPECIFIED.into(),
        SocketAddr::V6(_) => std::net::Ipv6Addr::UNSPECIFIED.into(),
    }
}

fn run_single(plan: &Plan, max_restarts: u32, stop: &AtomicBool) -> Result<()> {
    let mut attempt = 0;
    loop {
        let mut ranks = plan.spawn(attempt)?;
        let outcome = loop {
            if stop.load(Ordering::SeqCst) {
                return stop_on_signal(&mut ranks, plan.grace);
            }
            if let Some(o) = ranks.poll()? {
                break o;
            }
            std::thread::sleep(Duration::from_millis(100));
        };
        let why = match outcome {
            Outcome::Finished => return Ok(()),
            Outcome::Failed(why) => why,
        };
        ranks.stop(FAILURE_GRACE.min(plan.grace));
        if stop.load(Ordering::SeqCst) {
            bail!("launch: {why}; not restarting: stopped by a signal");
        }
        if attempt >= max_restarts {
            bail!("launch: {why} (after {attempt} restarts)");
        }
        attempt += 1;
        eprintln!("launch: {why}; restarting the group ({attempt}/{max_restarts})");
        std::thread::sleep(Duration::from_secs(1));
    }
}

/// After SIGINT/SIGTERM: the ranks checkpoint and exit; a clean stop is a success (a requeued
/// job resumes from that checkpoint).
fn stop_on_signal(ranks: &mut Ranks, grace: Duration) -> Result<()> {
    eprintln!(
        "launch: signal received; the ranks checkpoint and stop (grace period {:.0} s)",
        grace.as_secs_f64()
    );
    match ranks.stop(grace) {
        None => {
            eprintln!("launch: all ranks stopped cleanly");
            Ok(())
        }
        Some(why) => bail!("launch: stopped by a signal, but {why}"),
    }
}

/// LD_LIBRARY_PATH for the ranks: libtorch loads the `libnccl.so.2` of the torch wheel
/// (`nvidia/nccl/lib`), while cudarc opens `libnccl.so`, which on the GPU machines resolves to an
/// older system copy; two NCCLs in one process corrupt communicators (docs/architecture.md). A
/// directory holding a `libnccl.so` link to the wheel's library goes first; it lasts as long as
/// the returned guard.
fn nccl_library_path() -> (String, Option<tempfile::TempDir>) {
    let current = std::env::var("LD_LIBRARY_PATH").unwrap_or_default();
    let wheel_nccl = current
        .split(':')
        .filter(|d| d.ends_with("torch/lib"))
        .map(|d| std::path::Path::new(d).join("../../nvidia/nccl/lib"))
        .find(|d| d.join("libnccl.so.2").exists());
    let Some(nccl_dir) = wheel_nccl else {
        return (current, None);
    };
    let made = tempfile::Builder::new().prefix("bwm-nccl-link-").tempdir().and_then(|link_dir| {
        std::os::unix::fs::symlink(nccl_dir.join("libnccl.so.2"), link_dir.path().join("libnccl.so"))?;
        Ok(link_dir)
    });
    match made {
        Ok(link_dir) => {
            let path = format!("{}:{}:{current}", link_dir.path().display(), nccl_dir.display());
            (path, Some(link_dir))
        }
        Err(e) => {
            eprintln!(
                "launch: warning: could not link libnccl.so in {}: {e}",
                std::env::temp_dir().display()
            );
            (current, None)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_restart_resumes_from_the_latest_checkpoint_whatever_resume_was_given() {
        let words = |s: &str| s.split(' ').map(String::from).collect::<Vec<_>>();
        for given in ["train --config c.toml", "train --resume runs/x/checkpoints/step-00000100 --config c.toml", "train --resume=auto --config c.toml"] {
            assert_eq!(resuming(&words(given)), words("train --config c.toml --resume auto"), "{given}");
        }
    }
}
