//! `bwm evaluate` end to end on CPU (tiny random model, small random VAE) against scripted
//! openpi policy servers (tests/python/openpi_server.py, PyPI `websockets`) and a scripted HTTP
//! judge: three policies (absolute poses cut to whole latent groups, deltas re-requested to fill
//! a chunk, absolute full chunks), a dataset task and an image+state-file task. One episode's
//! policy raises (traceback text frame, close 1011), another's connection is dropped; both are
//! reported per episode and the evaluation goes on, then exits 1 with a summary of the errors by
//! kind. The report files are checked against a hand computation of the success rates, Pearson r
//! and MAE. A policy server that never sends its metadata fails each episode by the timeout, named
//! as such, and the evaluation exits 1.

mod common;

use common::{bwm, python, temp_dir, write_random_vae};

use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use bwm_testdir::{python_with, Dep};
use serde_json::{json, Value};
use tch::{Device, Kind, Tensor};



fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn demo() -> PathBuf {
    common::demo_data()
}

/// Kills the process it holds when dropped (also when an assertion fails).
struct Guard(Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}



/// Runs a command with stdout/stderr in files, killed after `limit`; returns (success, stdout, stderr).
fn run_limited(mut cmd: Command, dir: &Path, name: &str, limit: Duration) -> (bool, String, String) {
    let (out, err) = (dir.join(format!("{name}.stdout")), dir.join(format!("{name}.stderr")));
    cmd.stdout(File::create(&out).unwrap()).stderr(File::create(&err).unwrap());
    let mut child = Guard(cmd.spawn().unwrap());
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.0.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed() < limit, "{name} did not finish within {limit:?}:\n{}", std::fs::read_to_string(&out).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(100));
    };
    (status.success(), std::fs::read_to_string(out).unwrap(), std::fs::read_to_string(err).unwrap())
}

fn world_model_flags(cmd: &mut Command, vae: &Path) {
    cmd.args(["--random-weights", "tiny", "--vae"]).arg(vae);
    cmd.args(["--stats"]).arg(demo().join("stat.json"));
    cmd.args(["--device", "cpu", "--history", "4", "--future", "8", "--sample-steps", "2", "--seed", "3"]);
}

fn read_jsonl(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-9
}

fn pearson(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len() as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let cov: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let vx: f64 = x.iter().map(|a| (a - mx).powi(2)).sum();
    let vy: f64 = y.iter().map(|b| (b - my).powi(2)).sum();
    cov / (vx * vy).sqrt()
}

#[test]
fn policies_are_evaluated_in_closed_loop_and_failed_episodes_are_reported() {
    closed_loop_scenario(1, 1);
}

/// The same evaluation with four episodes in flight: batches that mix policies, tasks and
/// episodes that fail mid-way give every episode what it gets alone, recorded in the config's order.
#[test]
fn episodes_in_flight_together_give_what_each_gets_alone() {
    closed_loop_scenario(4, 1);
}

/// Five episodes in flight in two lanes (three and two) that take turns, each lane's chunk
/// queued before the other's is read back: the same records as one episode at a time.
#[test]
fn episodes_in_flight_in_two_streams_give_what_each_gets_alone() {
    closed_loop_scenario(5, 2);
}

fn closed_loop_scenario(in_flight: usize, streams: usize) {
    let dir = temp_dir(&format!("evaluate-{in_flight}-{streams}"));
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 4);
    let x0 = bwm_model::vb::with_seed(1, || Tensor::rand([3, 1, 32, 32], (Kind::Float, Device::Cpu))) * 2.0 - 1.0;
    let x0 = bwm_data::frames::tensor_to_frames(&x0).unwrap();
    x0[0].save(dir.join("x0.png")).unwrap();
    let stats: Value = serde_json::from_str(&std::fs::read_to_string(demo().join("stat.json")).unwrap()).unwrap();
    let pose: Vec<f32> = stats["state_pose"]["mean"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
    std::fs::write(dir.join("pose.json"), serde_json::to_string(&pose).unwrap()).unwrap();

    // Judge plan: "policy/task/episode" -> p, or [p, frames needed before p is given].
    let plan = json!({
        "alpha/bottle/0": [0.9, 8], "alpha/bottle/1": 0.2, "alpha/cube/0": 0.7,
        "beta/bottle/0": 0.1, "beta/bottle/1": [0.6, 16], "beta/cube/0": 0.4,
        "gamma/bottle/0": 0.8, "gamma/bottle/1": 0.9, "gamma/cube/0": 0.9,
    });
    std::fs::write(dir.join("plan.json"), plan.to_string()).unwrap();
    std::fs::write(
        dir.join("reference.csv"),
        "policy,task,success_rate\nalpha,bottle,0.6\nalpha,cube,0.4\nbeta,bottle,0.3\nbeta,cube,0.1\ngamma,bottle,0.9\ngamma,cube,0.5\nother,bottle,0.5\n",
    )
    .unwrap();

    let ports_file = dir.join("ports.json");
    let log = dir.join("server.jsonl");
    let server = Guard(
        Command::new(python())
            .arg(root().join("tests/python/openpi_server.py"))
            .args(["--out"])
            .arg(&ports_file)
            .args(["--log"])
            .arg(&log)
            .args(["--plan"])
            .arg(dir.join("plan.json"))
            .args(["--lifetime", "300", "--ping", "1"])
            .args(["--policy", "alpha:abs:6:observation/image:24x24x3"])
            .args(["--policy", "beta:delta:3:images.cam_high:3x16x16"])
            .args(["--policy", "gamma:abs:8:observation/image:24x24x3"])
            .stdout(Stdio::null())
            .stderr(File::create(dir.join("server.stderr")).unwrap())
            .spawn()
            .expect("starting tests/python/openpi_server.py"),
    );
    let start = Instant::now();
    while !ports_file.exists() {
        assert!(start.elapsed() < Duration::from_secs(60), "the policy server did not start: {}", std::fs::read_to_string(dir.join("server.stderr")).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(100));
    }
    let ports: Value = serde_json::from_str(&std::fs::read_to_string(&ports_file).unwrap()).unwrap();
    let port = |name: &str| ports[name].as_u64().unwrap();

    let config = format!(
        r#"
horizon = 16
resolution = "32x32"
fps = 10
timeout_s = 60
reference = "reference.csv"

[observation]
image_keys = ["observation/image"]
image_size = "24x24"

[[policies]]
name = "alpha"
url = "ws://127.0.0.1:{alpha}"
chunk = "cut"
adapter = {{ kind = "eef_abs", indices = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13] }}

[[policies]]
name = "beta"
url = "ws://127.0.0.1:{beta}"
chunk = "rerequest"
adapter = {{ kind = "eef_delta", absolute = [6, 13] }}
observation = {{ image_keys = [["images", "cam_high"]], image_size = "16x16", image_layout = "chw" }}

[[policies]]
name = "gamma"
url = "ws://127.0.0.1:{gamma}"

[judge]
kind = "http"
url = "http://127.0.0.1:{judge}/judge"
threshold = 0.5

[[tasks]]
name = "bottle"
dataset = "{demo}"
episodes = [0, 2]

[[tasks]]
name = "cube"
[[tasks.starts]]
images = ["x0.png"]
pose = "pose.json"
prompt = "stack the cube"
[[tasks.starts]]
images = ["x0.png"]
pose = "pose.json"
prompt = "stack the cube (raise)"
[[tasks.starts]]
images = ["x0.png"]
pose = "pose.json"
prompt = "stack the cube (drop)"
"#,
        alpha = port("alpha"),
        beta = port("beta"),
        gamma = port("gamma"),
        judge = port("judge"),
        demo = demo().display(),
    );
    std::fs::write(dir.join("eval.toml"), config).unwrap();

    let out = dir.join("out");
    let mut cmd = Command::new(bwm());
    cmd.arg("evaluate").arg("--config").arg(dir.join("eval.toml")).arg("--out").arg(&out);
    cmd.arg("--episodes-in-flight").arg(in_flight.to_string()).arg("--streams").arg(streams.to_string());
    world_model_flags(&mut cmd, &vae);
    let t0 = Instant::now();
    let (ok, stdout, stderr) = run_limited(cmd, &dir, "evaluate", Duration::from_secs(240));
    eprintln!("bwm evaluate took {:.1} s\n{stdout}", t0.elapsed().as_secs_f64());
    assert!(!ok, "6 episodes ended on policy or connection errors: bwm evaluate must fail:\n{stdout}\n{stderr}");
    assert!(stderr.contains("6 of 15 episodes ended on an error"), "{stderr}");
    drop(server);
    // The errors summed up by kind, each with its first episode's error.
    assert!(stdout.contains("evaluate: 6 of 15 episodes ended on an error"), "{stdout}");
    let kind = |k: &str| stdout.lines().find(|l| l.trim_start().starts_with(&format!("{k}: "))).unwrap_or_else(|| panic!("no '{k}:' line:\n{stdout}")).to_string();
    let policy = kind("policy");
    assert!(policy.contains("3 episodes; first: alpha / cube #1") && policy.contains("scripted failure in the policy"), "{policy}");
    let connection = kind("connection");
    assert!(connection.contains("3 episodes; first: alpha / cube #2") && connection.contains("connection"), "{connection}");

    // A progress line per episode; the failed ones say why.
    for k in 1..=15 {
        assert!(stdout.contains(&format!("[{k}/15] ")), "no progress line {k}:\n{stdout}");
    }
    assert_eq!(stdout.matches("FAILED").count(), 6, "{stdout}");
    assert!(stdout.contains("server metadata"), "{stdout}");
    assert!(stdout.contains(&format!("{in_flight} episode(s) in flight in {streams} stream(s)")), "{stdout}");

    let records = read_jsonl(&out.join("episodes.jsonl"));
    assert_eq!(records.len(), 15);
    let order: Vec<(&str, &str, u64)> =
        records.iter().map(|r| (r["policy"].as_str().unwrap(), r["task"].as_str().unwrap(), r["episode"].as_u64().unwrap())).collect();
    let config_order: Vec<(&str, &str, u64)> = ["alpha", "beta", "gamma"]
        .iter()
        .flat_map(|&p| [("bottle", 0), ("bottle", 1), ("cube", 0), ("cube", 1), ("cube", 2)].map(|(t, e)| (p, t, e)))
        .collect();
    assert_eq!(order, config_order, "records in the config's order");
    let rec = |p: &str, t: &str, e: u64| -> &Value {
        records.iter().find(|r| r["policy"] == p && r["task"] == t && r["episode"] == e).unwrap_or_else(|| panic!("no record {p}/{t}/{e}"))
    };
    // (policy, task, episode) -> (success, frames generated, policy requests)
    let expected = [
        ("alpha", "bottle", 0, true, 8, 2),
        ("alpha", "bottle", 1, false, 16, 4),
        ("alpha", "cube", 0, true, 4, 1),
        ("beta", "bottle", 0, false, 16, 6),
        ("beta", "bottle", 1, true, 16, 6),
        ("beta", "cube", 0, false, 16, 6),
        ("gamma", "bottle", 0, true, 8, 1),
        ("gamma", "bottle", 1, true, 8, 1),
        ("gamma", "cube", 0, true, 8, 1),
    ];
    for (p, t, e, success, frames, requests) in expected {
        let r = rec(p, t, e);
        assert_eq!(r["error"], Value::Null, "{r}");
        assert_eq!((r["success"].as_bool().unwrap(), r["frames"].as_u64().unwrap(), r["policy_requests"].as_u64().unwrap()), (success, frames, requests), "{r}");
        let video = out.join(r["video"].as_str().unwrap());
        assert!(std::fs::metadata(&video).map(|m| m.len() > 0).unwrap_or(false), "{} missing", video.display());
    }
    // The raising episode: the traceback text and the 1011 close are reported; frames generated
    // before the failure are kept (alpha and gamma had one chunk, beta none: its second request
    // was still filling the first chunk).
    for (p, frames) in [("alpha", 4), ("beta", 0), ("gamma", 8)] {
        let r = rec(p, "cube", 1);
        let err = r["error"].as_str().unwrap();
        assert!(err.contains("policy server error") && err.contains("1011") && err.contains("scripted failure in the policy"), "{err}");
        assert_eq!((r["success"].as_bool(), r["frames"].as_u64(), r["policy_requests"].as_u64()), (Some(false), Some(frames), Some(2)), "{r}");
        assert_eq!(r["video"].is_null(), frames == 0, "{r}");
        let r = rec(p, "cube", 2);
        let err = r["error"].as_str().unwrap();
        assert!(err.contains("connection"), "{err}");
        assert_eq!((r["success"].as_bool(), r["frames"].as_u64(), r["video"].is_null()), (Some(false), Some(0), true), "{r}");
        assert_eq!(r["policy_requests"].as_u64(), Some(1), "{r}");
    }

    // What the policies were shown: the state is the last commanded pose.
    let entries = read_jsonl(&log);
    let replies = |policy: &str, conn: u64| -> Vec<&Value> {
        entries.iter().filter(|e| e["policy"] == policy && e["conn"] == conn && e["event"] == "reply").collect()
    };
    let floats = |a: &Value| -> Vec<f64> { a.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect() };
    let state = |e: &Value| floats(&e["state"]);
    let cube = replies("alpha", 3);
    assert_eq!(cube[0]["prompt"], "stack the cube");
    assert!(state(cube[0]).iter().zip(&pose).all(|(a, b)| (a - *b as f64).abs() < 1e-6), "the file's pose is the first state");
    assert_eq!(cube[0]["image"], json!([[24, 24, 3], "|u1"]));
    // alpha, bottle episode 1 (connection 2): 6 actions per reply, 4 executed (cut to whole groups of 4).
    let bottle = replies("alpha", 2);
    assert_eq!(bottle.len(), 4);
    // The record keeps the poses that drove the model: the executed four of each reply, the
    // adapter's 14 indices of each row.
    let sent: Vec<Vec<f64>> = bottle.iter().flat_map(|r| r["actions"].as_array().unwrap()[..4].iter().map(floats)).collect();
    let recorded: Vec<Vec<f64>> = rec("alpha", "bottle", 1)["actions"].as_array().unwrap().iter().map(floats).collect();
    assert_eq!(recorded.len(), 16);
    for (r, s) in recorded.iter().zip(&sent) {
        assert!(r.len() == 14 && r.iter().zip(s).all(|(a, b)| (a - b).abs() < 1e-5), "recorded {r:?}, sent {s:?}");
    }
    for r in &records {
        assert_eq!(r["actions"].as_array().map(Vec::len), r["frames"].as_u64().map(|f| f as usize), "one action per generated frame: {r}");
    }
    for w in bottle.windows(2) {
        let executed = &w[0]["actions"][3];
        for (i, s) in state(w[1]).iter().enumerate() {
            assert!((s - executed[i].as_f64().unwrap()).abs() < 1e-6, "state {i} after the cut chunk");
        }
    }
    // beta, bottle episode 1 (connection 2): deltas of 0.002 integrated, grippers absolute; 3 per
    // reply, re-requested until 8, the surplus of the third reply dropped.
    let bottle = replies("beta", 2);
    assert_eq!(bottle.len(), 6);
    assert_eq!(bottle[0]["image"], json!([[3, 16, 16], "|u1"]));
    let s0 = state(bottle[0]);
    for (k, executed) in [(1, 3.0), (2, 6.0), (3, 8.0), (4, 11.0), (5, 14.0)] {
        let s = state(bottle[k]);
        for i in 0..14 {
            let want = match i {
                6 => 1.0,
                13 => 0.0,
                _ => s0[i] + 0.002 * executed,
            };
            assert!((s[i] - want).abs() < 1e-5, "beta request {k} state {i}: {} vs {want}", s[i]);
        }
    }

    // The judge saw all frames so far, as uint8 [T, 32, 32, 3], after every chunk.
    let judged: Vec<&Value> = entries.iter().filter(|e| e["event"] == "judge").collect();
    assert!(judged.iter().all(|e| e["dtype"] == "|u1" && e["shape"][1] == 32 && e["shape"][2] == 32 && e["shape"][3] == 3));
    let alpha_b1: Vec<u64> = judged.iter().filter(|e| e["key"] == "alpha/bottle/1").map(|e| e["shape"][0].as_u64().unwrap()).collect();
    assert_eq!(alpha_b1, vec![4, 8, 12, 16]);

    // Success rates by hand: errors count as failures.
    let rates = [
        ("alpha", "bottle", 0.5, 0.6),
        ("alpha", "cube", 1.0 / 3.0, 0.4),
        ("beta", "bottle", 0.5, 0.3),
        ("beta", "cube", 0.0, 0.1),
        ("gamma", "bottle", 1.0, 0.9),
        ("gamma", "cube", 1.0 / 3.0, 0.5),
    ];
    let summary: Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let got = summary["rates"].as_array().unwrap();
    assert_eq!(got.len(), 6);
    for ((p, t, rate, reference), g) in rates.iter().zip(got) {
        assert_eq!((g["policy"].as_str().unwrap(), g["task"].as_str().unwrap()), (*p, *t));
        assert!(close(g["success_rate"].as_f64().unwrap(), *rate) && close(g["reference"].as_f64().unwrap(), *reference), "{g}");
        assert_eq!(g["errors"].as_u64().unwrap(), if *t == "cube" { 2 } else { 0 });
    }
    let (x, y): (Vec<f64>, Vec<f64>) = rates.iter().map(|r| (r.2, r.3)).unzip();
    let agreement = &summary["reference"];
    assert_eq!(agreement["pairs"], 6);
    assert!((agreement["pearson_r"].as_f64().unwrap() - 0.9057322922484738).abs() < 1e-9, "{agreement}");
    assert!((pearson(&x, &y) - 0.9057322922484738).abs() < 1e-9);
    assert!((agreement["mae"].as_f64().unwrap() - 0.12222222222222223).abs() < 1e-9, "{agreement}");
    // Across policies, each averaged over its tasks: alpha 5/12, beta 1/4, gamma 2/3 against 0.5, 0.2, 0.7.
    assert_eq!(agreement["policies"], 3);
    assert!((agreement["policy_pearson_r"].as_f64().unwrap() - 0.973684210526316).abs() < 1e-9, "{agreement}");
    assert!((agreement["policy_mae"].as_f64().unwrap() - 0.055555555555555546).abs() < 1e-9, "{agreement}");
    let ranking: Vec<(&str, f64)> =
        summary["policies"].as_array().unwrap().iter().map(|p| (p["policy"].as_str().unwrap(), p["success_rate"].as_f64().unwrap())).collect();
    assert_eq!(ranking.iter().map(|r| r.0).collect::<Vec<_>>(), vec!["gamma", "alpha", "beta"]);
    assert!(close(ranking[0].1, 2.0 / 3.0) && close(ranking[1].1, 5.0 / 12.0) && close(ranking[2].1, 0.25));

    let csv = std::fs::read_to_string(out.join("success_rates.csv")).unwrap();
    assert!(csv.starts_with("policy,task,episodes,successes,errors,success_rate,reference_success_rate\n"), "{csv}");
    assert!(csv.contains("alpha,cube,3,1,2,0.333333,0.400000\n") && csv.contains("beta,cube,3,0,2,0.000000,0.100000\n"), "{csv}");
    let policies_csv = std::fs::read_to_string(out.join("policies.csv")).unwrap();
    assert!(policies_csv.contains("1,gamma,0.666667,2,5,2,0.700000\n"), "{policies_csv}");
}

#[test]
fn a_joint_policy_without_forward_kinematics_is_refused_at_start_up() {
    let dir = temp_dir("evaluate-joint");
    std::fs::write(
        dir.join("eval.toml"),
        format!(
            r#"
horizon = 8
resolution = "32x32"
[[policies]]
name = "arm"
url = "ws://127.0.0.1:9"
adapter = {{ kind = "joint" }}
[judge]
kind = "http"
url = "http://127.0.0.1:9/judge"
[[tasks]]
name = "bottle"
dataset = "{}"
"#,
            demo().display()
        ),
    )
    .unwrap();
    let mut cmd = Command::new(bwm());
    cmd.arg("evaluate").arg("--config").arg(dir.join("eval.toml")).arg("--out").arg(dir.join("out"));
    world_model_flags(&mut cmd, &dir.join("no-vae.safetensors"));
    let (ok, stdout, stderr) = run_limited(cmd, &dir, "evaluate", Duration::from_secs(60));
    assert!(!ok, "{stdout}");
    assert!(stderr.contains("joint adapter") && stderr.contains("forward-kinematics provider") && stderr.contains("[fk]"), "{stderr}");
    assert!(!dir.join("out").exists(), "nothing ran");
}

/// A policy server that accepts the websocket but never sends its metadata: each episode fails
/// on the client's timeout, named as such (not the socket's "os error 11"), and the evaluation,
/// every episode of which failed on it, exits 1.
#[test]
fn a_policy_server_that_never_sends_its_metadata_fails_the_evaluation() {
    let Some(py) = python_with(Dep::Python, &["websockets"]) else { return };
    let dir = temp_dir("evaluate-silent");
    let silent = r#"
import asyncio, websockets.asyncio.server as ws
async def silent(conn):
    await asyncio.Future()
async def main():
    async with ws.serve(silent, "127.0.0.1", 0) as server:
        print(server.sockets[0].getsockname()[1], flush=True)
        await asyncio.sleep(300)
asyncio.run(main())
"#;
    let mut server = Guard(Command::new(py).args(["-c", silent]).stdout(Stdio::piped()).stderr(Stdio::inherit()).spawn().unwrap());
    let mut port = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(server.0.stdout.take().unwrap()), &mut port).unwrap();
    let port: u16 = port.trim().parse().unwrap_or_else(|_| panic!("the silent server printed no port: {port:?}"));
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 4);
    let x0 = bwm_model::vb::with_seed(1, || Tensor::rand([3, 1, 32, 32], (Kind::Float, Device::Cpu))) * 2.0 - 1.0;
    bwm_data::frames::tensor_to_frames(&x0).unwrap()[0].save(dir.join("x0.png")).unwrap();
    let stats: Value = serde_json::from_str(&std::fs::read_to_string(demo().join("stat.json")).unwrap()).unwrap();
    std::fs::write(dir.join("pose.json"), stats["state_pose"]["mean"].to_string()).unwrap();
    std::fs::write(
        dir.join("eval.toml"),
        format!(
            r#"
horizon = 8
resolution = "32x32"
timeout_s = 1
[[policies]]
name = "silent"
url = "ws://127.0.0.1:{port}"
adapter = {{ kind = "eef_abs" }}
[judge]
kind = "http"
url = "http://127.0.0.1:9/judge"
[[tasks]]
name = "cube"
[[tasks.starts]]
images = ["x0.png"]
pose = "pose.json"
prompt = "stack the cube"
[[tasks.starts]]
images = ["x0.png"]
pose = "pose.json"
prompt = "stack the cube again"
"#
        ),
    )
    .unwrap();
    let mut cmd = Command::new(bwm());
    cmd.arg("evaluate").arg("--config").arg(dir.join("eval.toml")).arg("--out").arg(dir.join("out"));
    world_model_flags(&mut cmd, &vae);
    let (ok, stdout, stderr) = run_limited(cmd, &dir, "evaluate", Duration::from_secs(120));
    assert!(!ok, "every episode failed on its policy: bwm evaluate must fail:\n{stdout}\n{stderr}");
    assert_eq!(stdout.matches("FAILED").count(), 2, "{stdout}");
    assert!(stdout.contains("policy server sent no metadata within 1 s"), "{stdout}");
    assert!(!stdout.contains("os error"), "{stdout}");
    assert!(stdout.contains("evaluate: 2 of 2 episodes ended on an error"), "{stdout}");
    assert!(stderr.contains("2 of 2 episodes ended on an error"), "{stderr}");
    let records = read_jsonl(&dir.join("out/episodes.jsonl"));
    assert_eq!(records.len(), 2, "the records are written all the same");
}
