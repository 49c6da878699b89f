//! `bwm launch` end to end on CPU: SIGTERM to the launcher makes every rank stop at one agreed
//! step with a checkpoint (exit 0), and `--resume auto` then ends with the weights of an
//! uninterrupted run; two launchers as two nodes of one host train the weights of one launcher
//! with two ranks, restart together when a rank on one node dies, and treat a node whose launcher
//! stops sending heartbeats as failed; inconsistent nodes and bad addresses are refused before
//! any rank starts.

mod common;

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use common::*;

const MINUTE: Duration = Duration::from_secs(60);

fn launch(name: &str, args: &[&str], config: &Path, extra: &[&str]) -> Proc {
    launch_env(name, args, config, extra, &[])
}

fn launch_env(
    name: &str,
    args: &[&str],
    config: &Path,
    extra: &[&str],
    env: &[(&str, &str)],
) -> Proc {
    let mut c = Command::new(bwm());
    c.arg("launch")
        .args(args)
        .args(["--", "train", "--config"])
        .arg(config)
        .args(extra)
        .env("BWM_DIST_TIMEOUT", "60");
    c.envs(env.iter().copied());
    Proc::spawn(name, &mut c)
}

/// Node `rank` of `nnodes` on this host, one rank per node.
fn node(rank: usize, nnodes: usize, port: u16, config: &Path, extra: &[&str]) -> Proc {
    node_env(rank, nnodes, port, config, extra, &[])
}

fn node_env(
    rank: usize,
    nnodes: usize,
    port: u16,
    config: &Path,
    extra: &[&str],
    env: &[(&str, &str)],
) -> Proc {
    let (rank, nnodes, port) = (rank.to_string(), nnodes.to_string(), port.to_string());
    let mut args = vec![
        "--nnodes",
        &nnodes,
        "--node-rank",
        &rank,
        "--master-addr",
        "127.0.0.1",
        "--master-port",
        &port,
        "--nproc-per-node",
        "1",
    ];
    args.extend(extra);
    launch_env(&format!("node {rank}"), &args, config, &[], env)
}

fn checkpoint_line(step: u64) -> impl Fn(&str) -> bool {
    let name = format!("step-{step:08}");
    move |l: &str| l.starts_with("checkpoint ") && l.ends_with(&name)
}

#[test]
fn sigterm_stops_all_ranks_at_one_step_with_a_checkpoint_and_resume_matches_an_uninterrupted_run() {
    let dir = temp_dir("launch-sigterm");
    write_cache(&dir.join("cache"));
    let steps = 6;
    // One process, accumulation 2 == two ranks, accumulation 1: the same global batch of 2.
    let reference = write_config(&dir, "one.toml", &dir.join("one"), steps, 2);
    let mut one = Proc::spawn(
        "one",
        Command::new(bwm())
            .args(["train", "--config"])
            .arg(&reference),
    );
    assert!(one.finish(5 * MINUTE).success(), "{}", one.text());

    let two = write_config(&dir, "two.toml", &dir.join("two"), steps, 1);
    let port = free_port().to_string();
    let mut c = Command::new(bwm());
    c.args([
        "launch",
        "--nproc-per-node",
        "2",
        "--master-port",
        &port,
        "--",
        "train",
        "--config",
    ])
    .arg(&two)
    .env("BWM_FAULT_SLOW_CHECKPOINT_MS", "500");
    let mut launcher = Proc::spawn("launch", &mut c);
    launcher.wait_for(
        "with the checkpoint of step 2",
        3 * MINUTE,
        checkpoint_line(2),
    );
    launcher.signal("TERM");
    let status = launcher.finish(3 * MINUTE);
    let text = launcher.text();
    assert!(
        status.success(),
        "the launcher should exit 0 after a clean stop: {status}\n{text}"
    );
    let stops: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("stopped by signal at step "))
        .collect();
    assert_eq!(stops.len(), 2, "one line per rank:\n{text}");
    assert_eq!(
        stops[0], stops[1],
        "the ranks stopped at different steps:\n{text}"
    );
    let (step, ckpt) = stops[0]
        .strip_prefix("stopped by signal at step ")
        .unwrap()
        .split_once("; checkpoint ")
        .unwrap();
    let step: u64 = step.parse().unwrap();
    assert!(
        (2..steps).contains(&step),
        "stopped at step {step}:\n{text}"
    );
    assert_eq!(latest_step(&dir.join("two")), step);
    assert!(Path::new(ckpt).join("state.json").is_file(), "{ckpt}");
    assert!(
        Path::new(ckpt).ends_with(format!("step-{step:08}")),
        "{ckpt}"
    );

    let port = free_port().to_string();
    let mut resumed = launch(
        "resume",
        &["--nproc-per-node", "2", "--master-port", &port],
        &two,
        &["--resume", "auto"],
    );
    assert!(resumed.finish(3 * MINUTE).success(), "{}", resumed.text());
    assert!(
        resumed.text().contains(&format!("at step {step}")),
        "{}",
        resumed.text()
    );
    assert_eq!(latest_step(&dir.join("two")), steps);
    assert_close(
        &final_weights(&dir.join("one")),
        &final_weights(&dir.join("two")),
        "stopped by SIGTERM and resumed vs uninterrupted",
    );
}

#[test]
fn two_launchers_as_two_nodes_equal_one_launcher_and_restart_together() {
    let dir = temp_dir("launch-nodes");
    write_cache(&dir.join("cache"));
    let steps = 5;
    let reference = write_config(&dir, "ref.toml", &dir.join("ref"), steps, 1);
    let port = free_port().to_string();
    let mut one = launch(
        "one launcher",
        &["--nproc-per-node", "2", "--master-port", &port],
        &reference,
        &[],
    );
    assert!(one.finish(5 * MINUTE).success(), "{}", one.text());

    let nodes = write_config(&dir, "nodes.toml", &dir.join("nodes"), steps, 1);
    let port = free_port_pair();
    let mut n1 = node(1, 2, port, &nodes, &[]);
    let mut n0 = node(0, 2, port, &nodes, &[]);
    for n in [&mut n0, &mut n1] {
        assert!(n.finish(5 * MINUTE).success(), "{}", n.text());
    }
    assert!(
        n0.text().contains("launch: node 0, 1 ranks here, world 2"),
        "{}",
        n0.text()
    );
    assert_close(
        &final_weights(&dir.join("ref")),
        &final_weights(&dir.join("nodes")),
        "2 nodes x 1 rank vs 1 node x 2 ranks",
    );

    // Node 1's rank is killed after step 2: both nodes stop and start again, resuming.
    let restart = write_config(&dir, "restart.toml", &dir.join("restart"), steps, 1);
    let port = free_port_pair();
    let extra = ["--max-restarts", "1", "--grace-period", "20"];
    let slow = [("BWM_FAULT_SLOW_CHECKPOINT_MS", "500")];
    let mut c1 = node_env(1, 2, port, &restart, &extra, &slow);
    let mut c0 = node_env(0, 2, port, &restart, &extra, &slow);
    c0.wait_for(
        "with the checkpoint of step 2",
        3 * MINUTE,
        checkpoint_line(2),
    );
    let ranks = c1.children();
    assert_eq!(ranks.len(), 1, "node 1 should run one rank: {ranks:?}");
    signal(ranks[0], "KILL");
    for n in [&mut c0, &mut c1] {
        assert!(n.finish(5 * MINUTE).success(), "{}", n.text());
    }
    assert!(
        c0.text().contains("restarting every node (1/1)"),
        "{}",
        c0.text()
    );
    assert!(
        c1.text()
            .contains("stopping this node's ranks for restart 1"),
        "{}",
        c1.text()
    );
    assert!(
        c0.text().contains("(attempt 2)") && c1.text().contains("(attempt 2)"),
        "{}\n{}",
        c0.text(),
        c1.text()
    );
    assert_eq!(latest_step(&dir.join("restart")), steps);
    assert_close(
        &final_weights(&dir.join("ref")),
        &final_weights(&dir.join("restart")),
        "2 nodes with a restart vs 1 node",
    );
}

/// One node of two ranks, rank 1 killed after the checkpoint of step 1: with `--max-restarts 0`
/// the launcher stops the other rank and exits non-zero naming the dead rank; with 1 it restarts
/// the group, which resumes and finishes.
#[test]
fn a_killed_rank_fails_the_launch_without_restarts_and_is_restarted_with_one() {
    let dir = temp_dir("launch-killed-rank");
    write_cache(&dir.join("cache"));
    let steps = 4;
    let slow = [("BWM_FAULT_SLOW_CHECKPOINT_MS", "300")];
    let run = |name: &str, restarts: &str| -> Proc {
        let config = write_config(&dir, &format!("{name}.toml"), &dir.join(name), steps, 1);
        let port = free_port().to_string();
        let args = ["--nproc-per-node", "2", "--master-port", &port, "--max-restarts", restarts, "--grace-period", "10"];
        let mut p = launch_env(name, &args, &config, &[], &slow);
        p.wait_for("with the checkpoint of step 1", 3 * MINUTE, checkpoint_line(1));
        let ranks = p.children();
        assert_eq!(ranks.len(), 2, "two ranks: {ranks:?}");
        signal(ranks[1], "KILL");
        p
    };

    let mut none = run("none", "0");
    assert!(!none.finish(2 * MINUTE).success(), "{}", none.text());
    let last = none.text().trim().lines().last().unwrap_or_default().to_string();
    assert!(last.starts_with("error: launch: rank 1") && last.contains("(after 0 restarts)"), "{last}\n{}", none.text());
    assert!(latest_step(&dir.join("none")) < steps, "{}", none.text());

    let mut one = run("one", "1");
    assert!(one.finish(5 * MINUTE).success(), "{}", one.text());
    assert!(one.text().contains("restarting the group (1/1)"), "{}", one.text());
    assert_eq!(latest_step(&dir.join("one")), steps);
}

#[test]
fn a_node_whose_launcher_stops_sending_heartbeats_counts_as_failed() {
    let dir = temp_dir("launch-heartbeat");
    write_cache(&dir.join("cache"));
    let config = write_config(&dir, "run.toml", &dir.join("run"), 10_000, 1);
    let port = free_port_pair();
    let extra = [
        "--heartbeat-timeout",
        "3",
        "--rdzv-timeout",
        "5",
        "--grace-period",
        "5",
        "--max-restarts",
        "1",
    ];
    let mut n1 = node(1, 2, port, &config, &extra);
    let mut n0 = node(0, 2, port, &config, &extra);
    n0.wait_for(
        "with the checkpoint of step 1",
        3 * MINUTE,
        checkpoint_line(1),
    );
    n1.signal("STOP");
    let status = n0.finish(2 * MINUTE);
    n1.signal("CONT");
    let text = n0.text();
    assert!(!status.success(), "{text}");
    assert!(
        text.contains("node 1's launcher sent no heartbeat for 3 s"),
        "{text}"
    );
    assert!(
        text.contains("node(s) [1] did not come back for the restart"),
        "{text}"
    );
    // Node 1, continued, finds node 0's agent store gone (or its verdict) and stops too.
    assert!(!n1.finish(MINUTE).success(), "{}", n1.text());
}

#[test]
fn inconsistent_nodes_and_bad_addresses_are_refused_before_any_rank_starts() {
    let dir = temp_dir("launch-refused");
    let config = dir.join("never-read.toml");
    let started = |p: &Proc| p.text().contains("ranks here");

    let mut p = launch(
        "unresolvable",
        &[
            "--nnodes",
            "2",
            "--node-rank",
            "1",
            "--master-addr",
            "no-such-host.invalid",
        ],
        &config,
        &[],
    );
    assert!(!p.finish(MINUTE).success());
    assert!(
        p.text()
            .contains("--master-addr no-such-host.invalid does not resolve"),
        "{}",
        p.text()
    );

    let mut p = launch("rank", &["--nnodes", "2", "--node-rank", "2"], &config, &[]);
    assert!(!p.finish(MINUTE).success());
    assert!(
        p.text().contains("--node-rank 2 is not below --nnodes 2"),
        "{}",
        p.text()
    );

    let port = free_port_pair();
    let mut n0 = node(0, 2, port, &config, &[]);
    let mut n1 = launch(
        "node 1 of 3",
        &[
            "--nnodes",
            "3",
            "--node-rank",
            "1",
            "--master-addr",
            "127.0.0.1",
            "--master-port",
            &port.to_string(),
            "--nproc-per-node",
            "1",
        ],
        &config,
        &[],
    );
    for n in [&mut n0, &mut n1] {
        assert!(!n.finish(MINUTE).success(), "{}", n.text());
        assert!(
            n.text().contains(
                "inconsistent nodes: node 1 was started with --nnodes 3, node 0 with --nnodes 2"
            ),
            "{}",
            n.text()
        );
        assert!(!started(n), "{}", n.text());
    }

    let port = free_port_pair();
    let held = std::net::TcpListener::bind(("0.0.0.0", port)).unwrap();
    let mut p = launch(
        "port in use",
        &["--nproc-per-node", "1", "--master-port", &port.to_string()],
        &config,
        &[],
    );
    assert!(!p.finish(MINUTE).success());
    assert!(
        p.text()
            .contains(&format!("--master-port {port} is in use")),
        "{}",
        p.text()
    );
    drop(held);
    let held = std::net::TcpListener::bind(("0.0.0.0", port + 1)).unwrap();
    let mut p = node(0, 2, port, &config, &[]);
    assert!(!p.finish(MINUTE).success());
    assert!(
        p.text().contains(&format!(
            "cannot host the launchers' agent store on port {}",
            port + 1
        )),
        "{}",
        p.text()
    );
    assert!(!started(&p), "{}", p.text());
    drop(held);
}
