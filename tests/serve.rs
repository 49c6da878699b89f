//! `bwm serve` end to end on CPU (tiny random model, small random VAE) on a free loopback port:
//! a good request round-trips through the Python client of docs/serve.md with the right shapes;
//! with the model worker held busy (the hidden `--hold-while-exists` hook) a burst gets exactly
//! one request generating and `--queue` waiting, every further one 503 at once; malformed,
//! oversized and wrong-shape/dtype/size requests get 4xx with a message naming the problem, and
//! frames over the pixel budget 413 before the worker sees them (the log counts the bytes read);
//! 200 clients that send half a header do not keep /health or a real request from being
//! answered and are answered 408 after the read timeout; clients that leave mid-request do not
//! wedge the worker; declared bodies over the limit do not grow the server's memory; SIGTERM
//! finishes the request in flight, refuses new connections and exits 0. A request past
//! `--request-timeout-s` is answered 504 and abandoned by the worker at its next sampler step;
//! a trained checkpoint's frames are bounded by its training resolution by default.

mod common;

use common::{bwm, python, temp_dir, write_cache, write_config, write_random_vae};

use std::ffi::OsStr;
use std::fs::File;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use bwm_testdir::{python_with, Dep};

use serde_json::{json, Value};

/// Kills the process it holds when dropped (also when an assertion fails).
struct Guard(Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Sends `raw` as is and reads the reply until the server closes.
fn raw_exchange(addr: &str, raw: &[u8]) -> String {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    s.write_all(raw).unwrap();
    let mut reply = Vec::new();
    let _ = s.read_to_end(&mut reply);
    String::from_utf8_lossy(&reply).into_owned()
}

struct Reply {
    status: u16,
    content_type: String,
    body: Vec<u8>,
}

impl Reply {
    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// One HTTP/1.1 exchange; `declared` overrides the Content-Length sent. A write the server cut
/// short is not an error: its early reply is still read.
fn http(addr: &str, method: &str, path: &str, body: &[u8], declared: Option<usize>) -> Reply {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    s.set_write_timeout(Some(Duration::from_secs(30))).unwrap();
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/msgpack\r\nContent-Length: {}\r\n\r\n",
        declared.unwrap_or(body.len())
    );
    let _ = s.write_all(head.as_bytes()).and_then(|_| s.write_all(body));
    let mut raw = Vec::new();
    let read = s.read_to_end(&mut raw);
    if raw.is_empty() {
        panic!("no reply to {method} {path}: {read:?}");
    }
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").expect("reply head");
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let status = head.split(' ').nth(1).unwrap().parse().unwrap();
    let content_type = head
        .lines()
        .find_map(|l| l.to_ascii_lowercase().strip_prefix("content-type:").map(|v| v.trim().to_string()))
        .unwrap_or_default();
    Reply { status, content_type, body: raw[split + 4..].to_vec() }
}

/// Starts `bwm serve` on the CPU with a free port, `model` (weights flags) and `extra` flags,
/// stdout to `log`; returns the guard and the address it listens on. Random weights get H = K =
/// 4; a checkpoint, its contract's.
fn start_server(model: &[&std::ffi::OsStr], extra: &[&str], log: &Path) -> (Guard, String) {
    let chunk: &[&str] = if model.first() == Some(&OsStr::new("--random-weights")) { &["--history", "4", "--future", "4"] } else { &[] };
    let server = Guard(
        Command::new(bwm())
            .arg("serve")
            .args(model)
            .args(chunk)
            .args(["--device", "cpu", "--sample-steps", "2", "--port", "0"])
            .args(extra)
            .stdout(File::create(log).unwrap())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap(),
    );
    let start = Instant::now();
    loop {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        if let Some(a) = text.lines().find_map(|l| l.strip_prefix("serve: listening on http://")) {
            return (server, a.trim().to_string());
        }
        assert!(start.elapsed() < Duration::from_secs(60), "bwm serve did not start:\n{text}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Polls /health until `pred` holds (a guard against hangs, not a timing check).
fn wait_health(addr: &str, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
    let start = Instant::now();
    loop {
        let h = health(addr);
        if pred(&h) {
            return h;
        }
        assert!(start.elapsed() < Duration::from_secs(300), "never {what}: {h}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// A good request body of `t` given `h`x`w` frames and `t + k` actions of `d` values.
fn body_of(py: &Path, file: &Path, t: usize, h: usize, w: usize, k: usize, d: usize) -> Vec<u8> {
    let args = [t, h, w, k, d].map(|n| n.to_string());
    let out = Command::new(py).arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/serve_client.py")).arg("body").arg(file).args(args).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    std::fs::read(file).unwrap()
}

/// The request lines of the server's log.
fn request_lines(log: &Path) -> Vec<String> {
    std::fs::read_to_string(log).unwrap().lines().filter(|l| l.starts_with("serve: request ")).map(String::from).collect()
}

fn health(addr: &str) -> Value {
    let r = http(addr, "GET", "/health", b"", None);
    assert_eq!((r.status, r.content_type.as_str()), (200, "application/json"), "{}", r.text());
    serde_json::from_slice(&r.body).unwrap()
}

#[test]
fn serve_round_trips_rejects_bad_requests_and_sheds_load() {
    let dir = temp_dir("serve");
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 4);
    let log = dir.join("serve.stdout");
    let hold = dir.join("hold");
    let (server, addr) = start_server(
        &[OsStr::new("--random-weights"), OsStr::new("tiny"), OsStr::new("--vae"), vae.as_os_str()],
        &["--queue", "1", "--max-body-bytes", "1000000", "--read-timeout-s", "10", "--max-frame-pixels", "2048", "--hold-while-exists", hold.to_str().unwrap()],
        &log,
    );
    let url = format!("http://{addr}");

    let h = health(&addr);
    assert_eq!((h["status"].as_str(), h["device"].as_str(), h["action_dim"].as_u64()), (Some("ok"), Some("cpu"), Some(14)), "{h}");
    assert_eq!((h["queue_capacity"].as_u64(), h["queue_depth"].as_u64(), h["future"].as_u64()), (Some(1), Some(0), Some(4)), "{h}");
    assert_eq!(h["solver"], "euler", "{h}");
    assert!((h["history_sigma"].as_f64().unwrap() - 0.2083).abs() < 1e-3, "random weights record no history noise: the release's level: {h}");
    assert_eq!(h["shift"], 5.0, "random weights record no shift: Wan's: {h}");
    assert!(h["model"].as_str().unwrap().contains("tiny"), "{h}");
    assert_eq!(h["max_frame_pixels"], 2048, "--max-frame-pixels: {h}");

    // The documented Python client: 3 given frames (x0 + 2 history) and 3 + 4 actions.
    let out = Command::new(python()).arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/serve_client.py")).args(["roundtrip", &url, "3", "4", "14"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let reply: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(reply["frames"], json!([[4, 32, 32, 3], "|u1"]), "{reply}");
    assert_eq!(reply["actions"], json!([[4, 14], "<f4"]), "{reply}");
    assert_eq!(reply["actions_echoed"], true);
    assert_eq!(reply["same_seed_same_frames"], true);
    assert_eq!(reply["timings"], json!(["decode_s", "dit_s", "encode_s", "queue_s", "total_s"]));

    let bodies = dir.join("bodies");
    let out = Command::new(python())
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/serve_client.py"))
        .args(["bodies", bodies.to_str().unwrap(), "3", "4", "14"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let body = |name: &str| std::fs::read(bodies.join(name)).unwrap();
    let good = Arc::new(body("good.msgpack"));

    // A burst against 1 worker + a queue of 1, the worker held busy until released: one request
    // generating, one waiting, every further one refused at once.
    let before = health(&addr);
    std::fs::write(&hold, b"").unwrap();
    let send = |addr: &str, good: &Arc<Vec<u8>>| {
        let (addr, good) = (addr.to_string(), good.clone());
        std::thread::spawn(move || {
            let r = http(&addr, "POST", "/v1/chunk", &good, None);
            (r.status, r.text())
        })
    };
    let generating = send(&addr, &good);
    wait_health(&addr, "busy with the held request", |h| h["busy"] == true);
    let waiting = send(&addr, &good);
    wait_health(&addr, "a request waiting", |h| h["queue_depth"] == 1);
    let refused: Vec<(u16, String)> = (0..4)
        .map(|_| send(&addr, &good))
        .collect::<Vec<_>>()
        .into_iter()
        .map(|t| t.join().unwrap())
        .collect();
    for r in &refused {
        assert_eq!(r.0, 503, "every request beyond the queue is refused: {refused:?}");
        assert!(r.1.contains("queue is full"), "{}", r.1);
    }
    std::fs::remove_file(&hold).unwrap();
    for t in [generating, waiting] {
        let r = t.join().unwrap();
        assert_eq!(r.0, 200, "{}", r.1);
    }
    let after = wait_health(&addr, "idle after the burst", |h| h["busy"] == false && h["queue_depth"] == 0);
    let count = |h: &Value, k: &str| h[k].as_u64().unwrap();
    assert_eq!(count(&after, "served") - count(&before, "served"), 2, "{after}");
    assert_eq!(count(&after, "rejected_busy") - count(&before, "rejected_busy"), 4, "{after}");

    // Frames over the pixel budget (64x64 = 4096 > 2048) are refused with 413 before the model
    // worker sees them: nothing is served or failed, and the log counts the body's bytes.
    let py = python_with(Dep::Python, &["msgpack", "numpy"]).expect("the serve test needs the virtualenv's python with msgpack and numpy");
    let big = body_of(&py, &dir.join("big.msgpack"), 1, 64, 64, 4, 14);
    let before = health(&addr);
    let r = http(&addr, "POST", "/v1/chunk", &big, None);
    assert_eq!((r.status, r.content_type.as_str()), (413, "application/json"), "{}", r.text());
    let error: Value = serde_json::from_slice(&r.body).unwrap();
    let message = error["error"].as_str().unwrap();
    assert!(message.contains("64x64") && message.contains("4096 pixels") && message.contains("2048") && message.contains("--max-frame-pixels"), "{message}");
    let after = health(&addr);
    for k in ["served", "failed", "timed_out"] {
        assert_eq!(after[k], before[k], "{k}: the worker took up the refused request: {after}");
    }
    let line = request_lines(&log).into_iter().rev().find(|l| l.contains("path=/v1/chunk")).unwrap();
    assert!(line.contains("status=413") && line.contains(&format!("bytes_in={} ", big.len())), "the log counts the bytes read: {line}");
    // ... and the server goes on serving.
    let r = http(&addr, "POST", "/v1/chunk", &good, None);
    assert_eq!(r.status, 200, "{}", r.text());

    // Problems are named, with the right 4xx.
    let cases: [(&str, Reply, u16, &str); 12] = [
        ("NaN action", http(&addr, "POST", "/v1/chunk", &body("nan_actions.msgpack"), None), 422, "NaN or infinite"),
        ("infinite action", http(&addr, "POST", "/v1/chunk", &body("inf_actions.msgpack"), None), 422, "NaN or infinite"),
        ("negative dimension", http(&addr, "POST", "/v1/chunk", &body("negative_dim.msgpack"), None), 422, "non-negative"),
        ("dimensions overflowing", http(&addr, "POST", "/v1/chunk", &body("huge_dims.msgpack"), None), 422, "overflows"),
        ("more rows than data", http(&addr, "POST", "/v1/chunk", &body("huge_rows.msgpack"), None), 422, "data bytes"),
        ("malformed msgpack", http(&addr, "POST", "/v1/chunk", &body("malformed.bin"), None), 400, "not valid msgpack"),
        ("wrong shape", http(&addr, "POST", "/v1/chunk", &body("wrong_shape.msgpack"), None), 422, "'actions' has 8 rows"),
        ("wrong dtype", http(&addr, "POST", "/v1/chunk", &body("wrong_dtype.msgpack"), None), 422, "'frames' must be uint8, got float32"),
        ("frame size", http(&addr, "POST", "/v1/chunk", &body("bad_size.msgpack"), None), 422, "multiples of 32"),
        ("oversized", http(&addr, "POST", "/v1/chunk", &vec![0x90; 1_500_000], None), 413, "exceeds the limit of 1000000 bytes"),
        ("huge declared length", http(&addr, "POST", "/v1/chunk", b"", Some(1 << 40)), 413, "exceeds the limit"),
        ("unknown path", http(&addr, "GET", "/v2/nothing", b"", None), 404, "no endpoint"),
    ];
    for (what, reply, status, message) in cases {
        assert_eq!(reply.status, status, "{what}: {}", reply.text());
        assert_eq!(reply.content_type, "application/json", "{what}");
        let error: Value = serde_json::from_slice(&reply.body).unwrap_or_else(|_| panic!("{what}: {}", reply.text()));
        assert!(error["error"].as_str().unwrap().contains(message), "{what}: {error}");
    }
    let nan_len = body("nan_actions.msgpack").len();
    assert!(
        request_lines(&log).iter().any(|l| l.contains("status=422") && l.contains(&format!("bytes_in={nan_len} "))),
        "a refused request's line counts the bytes read: {:?}",
        request_lines(&log)
    );
    let wrong_method = http(&addr, "GET", "/v1/chunk", b"", None);
    assert_eq!(wrong_method.status, 405, "{}", wrong_method.text());
    let chunked = raw_exchange(&addr, b"POST /v1/chunk HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n0\r\n\r\n");
    assert!(chunked.starts_with("HTTP/1.1 411") && chunked.contains("Content-Length"), "{chunked}");
    let long_head = format!("GET /health HTTP/1.1\r\nHost: x\r\nX-Long: {}\r\n\r\n", "a".repeat(20 << 10));
    let many_headers = format!("GET /health HTTP/1.1\r\n{}\r\n", (0..70).map(|i| format!("X-{i}: y\r\n")).collect::<String>());
    for head in [long_head, many_headers] {
        let reply = raw_exchange(&addr, head.as_bytes());
        assert!(reply.starts_with("HTTP/1.1 431"), "{reply:?}");
    }

    // Clients that send half a header and wait hold their connections, not the server: while 200
    // of them hang, /health and a real request are answered, and each of them is later answered 408.
    let slow: Vec<TcpStream> = (0..200)
        .map(|_| {
            let mut c = TcpStream::connect(&addr).unwrap();
            c.write_all(b"POST /v1/chunk HTTP/1.1\r\nHost: x\r\nContent-Le").unwrap();
            c
        })
        .collect();
    let h = health(&addr);
    assert_eq!(h["status"], "ok", "{h}");
    let r = http(&addr, "POST", "/v1/chunk", &good, None);
    assert_eq!((r.status, r.content_type.as_str()), (200, "application/msgpack"), "{}", r.text());
    for mut c in slow.into_iter().step_by(50) {
        c.set_read_timeout(Some(Duration::from_secs(300))).unwrap();
        let mut answer = String::new();
        let _ = c.read_to_string(&mut answer);
        assert!(answer.starts_with("HTTP/1.1 408") && answer.contains("--read-timeout-s"), "{answer:?}");
    }

    // Clients that go away mid-request: one inside its body, one before reading its reply. The
    // worker is not left holding either: the next request is served and the queue drains.
    let mut cut = TcpStream::connect(&addr).unwrap();
    let head = format!("POST /v1/chunk HTTP/1.1\r\nHost: x\r\nContent-Length: {}\r\n\r\n", good.len());
    cut.write_all(head.as_bytes()).and_then(|_| cut.write_all(&good[..good.len() / 2])).unwrap();
    drop(cut);
    let mut gone = TcpStream::connect(&addr).unwrap();
    gone.write_all(head.as_bytes()).and_then(|_| gone.write_all(&good)).unwrap();
    drop(gone);
    let r = http(&addr, "POST", "/v1/chunk", &good, None);
    assert_eq!(r.status, 200, "{}", r.text());
    let drained = Instant::now();
    loop {
        let h = health(&addr);
        if h["queue_depth"] == 0 && h["busy"] == false {
            assert!(h["served"].as_u64().unwrap() >= 5 && h["rejected_busy"].as_u64().unwrap() >= 1, "{h}");
            break;
        }
        assert!(drained.elapsed() < Duration::from_secs(300), "the queue never drained: {h}");
        std::thread::sleep(Duration::from_millis(100));
    }

    // A burst of requests that declare 1 GiB bodies and send some of it: each is refused from its
    // Content-Length, and the server's memory does not grow with what was declared.
    let rss = || -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", server.0.id())).unwrap();
        status.lines().find_map(|l| l.strip_prefix("VmRSS:")).unwrap().trim().trim_end_matches(" kB").parse::<u64>().unwrap() * 1024
    };
    let before = rss();
    let chunk = vec![0x90u8; 64 << 10];
    for _ in 0..100 {
        let r = http(&addr, "POST", "/v1/chunk", &chunk, Some(1 << 30));
        assert_eq!(r.status, 413, "{}", r.text());
    }
    let grown = rss().saturating_sub(before);
    assert!(grown < 64 << 20, "100 declared 1 GiB bodies grew the server by {grown} bytes");

    // SIGTERM: the request in flight (its head read, its body still coming) is finished and
    // answered; new connections are refused; the server exits 0.
    let mut inflight = TcpStream::connect(&addr).unwrap();
    inflight.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    let head = format!("POST /v1/chunk HTTP/1.1\r\nHost: x\r\nExpect: 100-continue\r\nContent-Length: {}\r\n\r\n", good.len());
    inflight.write_all(head.as_bytes()).unwrap();
    let mut continued = [0u8; 25];
    inflight.read_exact(&mut continued).unwrap();
    assert!(continued.starts_with(b"HTTP/1.1 100 Continue"), "{:?}", String::from_utf8_lossy(&continued));
    common::signal(server.0.id(), "TERM");
    let stopping = Instant::now();
    while !std::fs::read_to_string(&log).unwrap_or_default().contains("serve: stopping") {
        assert!(stopping.elapsed() < Duration::from_secs(60), "no shutdown after SIGTERM");
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(TcpStream::connect(&addr).is_err(), "a new connection is refused while stopping");
    inflight.write_all(&good).unwrap();
    let mut answer = Vec::new();
    let _ = inflight.read_to_end(&mut answer);
    assert!(answer.starts_with(b"HTTP/1.1 200"), "{}", String::from_utf8_lossy(&answer[..answer.len().min(200)]));
    let mut server = server;
    let status = server.0.wait().unwrap();
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(status.success() && text.contains("serve: stopped"), "{status}\n{text}");
    assert!(text.contains("serve: request method=POST path=/v1/chunk status=200 bytes_in="), "{text}");
}

/// A request past `--request-timeout-s` is answered 504 at its deadline, and the worker, held at
/// the request's first sampler step until then, abandons it there instead of finishing it.
#[test]
fn a_request_past_its_time_limit_is_answered_504_and_abandoned() {
    let Some(py) = python_with(Dep::Python, &["msgpack", "numpy"]) else { return };
    let dir = temp_dir("serve-timeout");
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 4);
    let log = dir.join("serve.stdout");
    let hold = dir.join("hold");
    let (_server, addr) = start_server(
        &[OsStr::new("--random-weights"), OsStr::new("tiny"), OsStr::new("--vae"), vae.as_os_str()],
        &["--request-timeout-s", "1", "--hold-while-exists", hold.to_str().unwrap()],
        &log,
    );
    let h = health(&addr);
    assert_eq!((h["max_frame_pixels"].as_u64(), h["request_timeout_s"].as_f64()), (Some(640 * 480), Some(1.0)), "random weights record no training resolution: 640x480: {h}");
    let good = body_of(&py, &dir.join("good.msgpack"), 1, 32, 32, 4, 14);
    std::fs::write(&hold, b"").unwrap();
    let r = http(&addr, "POST", "/v1/chunk", &good, None);
    assert_eq!(r.status, 504, "{}", r.text());
    assert!(r.text().contains("--request-timeout-s 1"), "{}", r.text());
    assert_eq!(health(&addr)["busy"], true, "the worker is still held");
    std::fs::remove_file(&hold).unwrap();
    let h = wait_health(&addr, "freed", |h| h["busy"] == false);
    assert_eq!((h["timed_out"].as_u64(), h["served"].as_u64(), h["failed"].as_u64()), (Some(1), Some(0), Some(0)), "{h}");
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.contains("abandoned at sampler step 1 of 2"), "{text}");
    assert!(request_lines(&log).iter().any(|l| l.contains("status=504") && l.contains(&format!("bytes_in={} ", good.len()))), "{text}");
}

/// With a trained checkpoint, requests are held to its input contract (the latent cache's 64x64
/// frames, 14-D actions, H 8 and K 4): it is served at /v1/contract, frames of another size are
/// refused with 422 naming both sizes, frames of that size are served, and the frame budget is
/// the training resolution.
#[test]
fn a_checkpoints_requests_are_held_to_its_contract() {
    let Some(py) = python_with(Dep::Python, &["msgpack", "numpy"]) else { return };
    let dir = temp_dir("serve-trained");
    write_cache(&dir.join("cache"));
    let run = dir.join("run");
    let trained = Command::new(bwm()).args(["train", "--config"]).arg(write_config(&dir, "run.toml", &run, 1, 1)).output().unwrap();
    assert!(trained.status.success(), "{}", String::from_utf8_lossy(&trained.stderr));
    let checkpoint: PathBuf = run.join("checkpoints/step-00000001");
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 4);
    let log = dir.join("serve.stdout");
    let (_server, addr) =
        start_server(&[OsStr::new("--checkpoint"), checkpoint.as_os_str(), OsStr::new("--vae"), vae.as_os_str()], &[], &log);
    let h = health(&addr);
    assert_eq!((h["max_frame_pixels"].as_u64(), h["history"].as_u64(), h["future"].as_u64()), (Some(64 * 64), Some(8), Some(4)), "{h}");
    let r = http(&addr, "GET", "/v1/contract", b"", None);
    let contract: Value = serde_json::from_slice(&r.body).unwrap();
    assert_eq!((r.status, &contract["frames"]["width"], &contract["actions"]["dim"]), (200, &json!(64), &json!(14)), "{contract}");
    for (h, w) in [(64, 96), (32, 32)] {
        let other = body_of(&py, &dir.join("other.msgpack"), 1, h, w, 4, 14);
        let r = http(&addr, "POST", "/v1/chunk", &other, None);
        assert_eq!(r.status, 422, "{}", r.text());
        assert!(r.text().contains(&format!("'frames': {w}x{h} frames, but this model was trained on 64x64")), "{}", r.text());
    }
    let fits = body_of(&py, &dir.join("fits.msgpack"), 1, 64, 64, 4, 14);
    let r = http(&addr, "POST", "/v1/chunk", &fits, None);
    assert_eq!(r.status, 200, "{}", r.text());
    let h = health(&addr);
    assert_eq!((h["served"].as_u64(), h["failed"].as_u64()), (Some(1), Some(0)), "{h}");
}

/// WorldArena 2.0's environment API on loopback, driven by a client written from that API's
/// documentation (tests/python/worldarena_client.py): /health, /reset of 3 environments from their
/// first frames and raw states, 2 chunk steps of 4 actions, the reply's observation keys and
/// shapes, the same frames again from the same seed, and the refusals of a step for another
/// number of environments and of a reset without states.
#[test]
fn the_worldarena_environment_api_serves_a_batch_of_environments() {
    let Some(py) = python_with(Dep::Python, &["msgpack", "numpy"]) else { return };
    let dir = temp_dir("serve-worldarena");
    let vae = dir.join("vae.safetensors");
    write_random_vae(&vae, 4);
    let stats = common::demo_data().join("stat.json");
    let log = dir.join("serve.stdout");
    let (_server, addr) = start_server(
        &[OsStr::new("--random-weights"), OsStr::new("tiny"), OsStr::new("--vae"), vae.as_os_str(), OsStr::new("--stats"), stats.as_os_str()],
        &[],
        &log,
    );
    let out = Command::new(&py)
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/worldarena_client.py"))
        .args(["episode", &format!("http://{addr}"), "3", "2", "14"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let seen: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!((seen["health_before"]["status"].as_str(), seen["health_before"]["num_envs"].as_u64()), (Some("ok"), Some(0)), "{seen}");
    assert_eq!(seen["health_after"]["num_envs"], 3, "{seen}");
    let obs = &seen["reset_obs"];
    assert_eq!((&obs["main_images"], &obs["states"], &obs["wrist_images"]), (&json!([[3, 32, 32, 3], "|u1"]), &json!([[3, 14], "<f4"]), &Value::Null), "{seen}");
    assert_eq!(obs["task_descriptions"], json!(["task 0", "task 1", "task 2"]), "{seen}");
    assert_eq!((seen["num_envs"].as_u64(), seen["elapsed_steps"].as_u64()), (Some(3), Some(8)), "{seen}");
    assert_eq!(seen["frames_shape"], json!([[3, 4, 32, 32, 3], [3, 4, 32, 32, 3]]), "{seen}");
    assert_eq!(seen["step_keys"], json!(["elapsed_steps", "frames", "obs"]), "no reward, no done: those are the caller's: {seen}");
    for k in ["reset_images_are_the_first_frames", "last_frame_is_main_image", "states_are_the_last_actions", "same_seed_same_frames"] {
        assert_eq!(seen[k], true, "{k}: {seen}");
    }
    assert!(seen["wrong_batch"].as_str().unwrap().contains("HTTP 422") && seen["wrong_batch"].as_str().unwrap().contains("for 1 environments; /reset made 3"), "{seen}");
    assert!(seen["no_states"].as_str().unwrap().contains("HTTP 422: 'states' is missing"), "{seen}");
}
