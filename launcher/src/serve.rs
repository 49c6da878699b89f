//! `bwm serve`: one world-model chunk per HTTP request, for clients that run the loop
//! themselves (protocol: docs/serve.md).
//!
//! The model lives on one worker thread (it holds `Rc`s). Each connection gets a thread that
//! reads and checks the request, then offers it to a bounded queue in front of the worker: a
//! full queue is answered 503 at once. The HTTP/1.1 handling is our own, on std sockets, so that
//! a body over the limit is refused from its Content-Length before any of it is buffered
//! (tiny_http 0.12 allocates the whole unread remainder of a declared body when a request is
//! dropped, which a single header could turn into an abort).

use std::io::{Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{self, Sender};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context, Result};
use bwm_model::rollout::Rollout;
use clap::Args;
use rmpv::Value;
use tch::{Kind, Tensor};

use crate::msgpack_numpy::{self, map_get, scalar, str_map, Dtype, NdArray};
use crate::world_model::{tensor_rows, WorldModel, WorldModelArgs};

#[derive(Args)]
pub struct ServeArgs {
    #[command(flatten)]
    wm: WorldModelArgs,
    #[arg(long, default_value = "127.0.0.1")]
    host: String,
    /// Port to listen on (0: any free port; the address is printed).
    #[arg(long, default_value_t = 8080)]
    port: u16,
    /// Requests that may wait while the model is busy; further ones get 503 at once.
    #[arg(long, default_value_t = 4)]
    queue: usize,
    /// Largest request body in bytes (413 above it).
    #[arg(long, default_value_t = 256 << 20)]
    max_body_bytes: usize,
    /// Open connections at most; further ones get 503 at once.
    #[arg(long, default_value_t = 64)]
    max_connections: usize,
    /// Seconds a client may take to send its request.
    #[arg(long, default_value_t = 60)]
    read_timeout_s: u64,
}

const MAX_HEAD: usize = 16 << 10;

/// A checked /v1/chunk request.
struct ChunkRequest {
    /// uint8 [T, H, W, 3]: x0, then the given history frames.
    frames: Vec<u8>,
    t: usize,
    h: usize,
    w: usize,
    /// [T + n, d] rows, as sent.
    actions: Vec<Vec<f32>>,
    normalized: bool,
    seed: Option<u64>,
}

struct Job {
    request: ChunkRequest,
    received: Instant,
    reply: mpsc::Sender<Result<Vec<u8>, ApiError>>,
}

#[derive(Debug)]
struct ApiError {
    status: u16,
    message: String,
}

fn api(status: u16, message: impl Into<String>) -> ApiError {
    ApiError {
        status,
        message: message.into(),
    }
}

/// What /health reports about the loaded model.
#[derive(Clone)]
struct ModelInfo {
    model: String,
    device: String,
    dtype: String,
    action_dim: usize,
    history: usize,
    future: usize,
    sample_steps: usize,
    stats: bool,
}

#[derive(Default)]
struct Counters {
    /// Requests admitted and not yet answered: the one generating and those waiting.
    pending: AtomicUsize,
    busy: AtomicBool,
    connections: AtomicUsize,
    served: AtomicU64,
    rejected_busy: AtomicU64,
    failed: AtomicU64,
}

struct Shared {
    info: ModelInfo,
    queue_capacity: usize,
    max_body: usize,
    max_connections: usize,
    read_timeout: Duration,
    counters: Arc<Counters>,
}

pub fn run(a: ServeArgs) -> Result<()> {
    let model = match (&a.wm.checkpoint, &a.wm.random_weights) {
        (Some(c), _) => c.clone(),
        (None, Some(p)) => format!("random weights ({p})"),
        (None, None) => "none".into(),
    };
    let (ready_tx, ready_rx) = mpsc::channel::<Result<ModelInfo>>();
    // Admission is bounded by `Counters::pending`, so the channel itself need not be.
    let (job_tx, job_rx) = mpsc::channel::<Job>();
    let wm_args = a.wm.clone();
    let counters = Arc::new(Counters::default());
    let worker_counters = counters.clone();
    std::thread::Builder::new()
        .name("model".into())
        .spawn(move || {
            let wm = match wm_args.load() {
                Ok(wm) => wm,
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                    return;
                }
            };
            let info = ModelInfo {
                model,
                device: match wm.device {
                    tch::Device::Cuda(i) => format!("cuda:{i}"),
                    _ => "cpu".into(),
                },
                dtype: match wm.model.store.kind() {
                    Kind::BFloat16 => "bf16".into(),
                    Kind::Half => "f16".into(),
                    Kind::Float => "f32".into(),
                    k => format!("{k:?}").to_lowercase(),
                },
                action_dim: wm.action_dim(),
                history: wm.spec.history,
                future: wm.spec.future,
                sample_steps: wm.spec.steps,
                stats: wm.stats.is_some(),
            };
            if ready_tx.send(Ok(info)).is_err() {
                return;
            }
            let counters = worker_counters;
            for job in job_rx {
                counters.busy.store(true, Ordering::SeqCst);
                let queued = job.received.elapsed().as_secs_f64();
                let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    generate(&wm, &job.request, queued)
                }))
                .unwrap_or_else(|_| Err(api(500, "the model worker panicked on this request")));
                match &result {
                    Ok(_) => counters.served.fetch_add(1, Ordering::SeqCst),
                    Err(_) => counters.failed.fetch_add(1, Ordering::SeqCst),
                };
                counters.busy.store(false, Ordering::SeqCst);
                counters.pending.fetch_sub(1, Ordering::SeqCst);
                let _ = job.reply.send(result);
            }
        })
        .context("starting the model worker")?;
    let info = ready_rx
        .recv()
        .map_err(|_| anyhow!("the model worker stopped while loading"))??;
    let listener = TcpListener::bind((a.host.as_str(), a.port))
        .with_context(|| format!("listening on {}:{}", a.host, a.port))?;
    let addr = listener.local_addr()?;
    let shared = Arc::new(Shared {
        info: info.clone(),
        queue_capacity: a.queue,
        max_body: a.max_body_bytes,
        max_connections: a.max_connections.max(1),
        read_timeout: Duration::from_secs(a.read_timeout_s.max(1)),
        counters,
    });
    println!(
        "serve: {} on {} ({}), d_a = {}, H = {}, K = {}, {} steps; queue {}, body limit {} bytes",
        info.model,
        info.device,
        info.dtype,
        info.action_dim,
        info.history,
        info.future,
        info.sample_steps,
        a.queue,
        a.max_body_bytes
    );
    println!("serve: listening on http://{addr}");
    let _ = std::io::stdout().flush();
    for stream in listener.incoming() {
        let stream = match stream {
            Ok(s) => s,
            Err(e) => {
                eprintln!("serve: accept failed: {e}");
                std::thread::sleep(Duration::from_millis(50));
                continue;
            }
        };
        let (shared, jobs) = (shared.clone(), job_tx.clone());
        shared.counters.connections.fetch_add(1, Ordering::SeqCst);
        let spawned = std::thread::Builder::new()
            .name("http".into())
            .spawn(move || {
                connection(stream, &shared, &jobs);
                shared.counters.connections.fetch_sub(1, Ordering::SeqCst);
            });
        if let Err(e) = spawned {
            eprintln!("serve: cannot start a connection thread: {e}");
        }
    }
    Ok(())
}

struct HttpRequest {
    method: String,
    path: String,
    body: Vec<u8>,
}

/// Reads one request; Err carries the response to send (and whether body bytes were left
/// unread). Ok(None): the client closed without sending a request.
fn read_request(
    stream: &mut TcpStream,
    max_body: usize,
) -> Result<Option<HttpRequest>, (ApiError, bool)> {
    let mut buf = Vec::with_capacity(4096);
    let mut chunk = [0u8; 4096];
    let (head_len, method, path, length) = loop {
        let n = match stream.read(&mut chunk) {
            Ok(0) if buf.is_empty() => return Ok(None),
            Ok(0) => {
                return Err((
                    api(400, "the connection closed inside the request head"),
                    false,
                ))
            }
            Ok(n) => n,
            Err(e) => return Err((api(408, format!("reading the request: {e}")), false)),
        };
        buf.extend_from_slice(&chunk[..n]);
        let mut headers = [httparse::EMPTY_HEADER; 64];
        let mut req = httparse::Request::new(&mut headers);
        match req.parse(&buf) {
            Ok(httparse::Status::Complete(len)) => {
                let mut length: Option<usize> = None;
                let mut expect_continue = false;
                for h in req.headers.iter() {
                    let value = String::from_utf8_lossy(h.value).trim().to_string();
                    if h.name.eq_ignore_ascii_case("content-length") {
                        let v: usize = value.parse().map_err(|_| {
                            (
                                api(400, format!("Content-Length '{value}' is not a number")),
                                true,
                            )
                        })?;
                        if length.is_some_and(|l| l != v) {
                            return Err((api(400, "conflicting Content-Length headers"), true));
                        }
                        length = Some(v);
                    } else if h.name.eq_ignore_ascii_case("transfer-encoding") {
                        return Err((api(411, "send the body with a Content-Length (chunked transfer encoding is not supported)"), true));
                    } else if h.name.eq_ignore_ascii_case("expect")
                        && value.eq_ignore_ascii_case("100-continue")
                    {
                        expect_continue = true;
                    }
                }
                let method = req.method.unwrap_or_default().to_string();
                let path = req
                    .path
                    .unwrap_or_default()
                    .split('?')
                    .next()
                    .unwrap_or_default()
                    .to_string();
                let length = length.unwrap_or(0);
                if length > max_body {
                    return Err((api(413, format!("request body of {length} bytes exceeds the limit of {max_body} bytes (--max-body-bytes)")), true));
                }
                if expect_continue && length > buf.len() - len {
                    let _ = stream.write_all(b"HTTP/1.1 100 Continue\r\n\r\n");
                }
                break (len, method, path, length);
            }
            Ok(httparse::Status::Partial) if buf.len() > MAX_HEAD => {
                return Err((
                    api(431, format!("request head longer than {MAX_HEAD} bytes")),
                    true,
                ));
            }
            Ok(httparse::Status::Partial) => {}
            Err(httparse::Error::TooManyHeaders) => {
                return Err((api(431, "more than 64 request headers"), true))
            }
            Err(e) => return Err((api(400, format!("malformed HTTP request: {e}")), true)),
        }
    };
    let mut body = buf.split_off(head_len);
    if body.len() > length {
        return Err((
            api(
                400,
                "more body bytes than the Content-Length says (pipelining is not supported)",
            ),
            false,
        ));
    }
    let missing = length - body.len();
    body.reserve_exact(missing);
    if let Err(e) = stream.take(missing as u64).read_to_end(&mut body) {
        return Err((api(408, format!("reading the request body: {e}")), false));
    }
    if body.len() < length {
        return Err((
            api(
                400,
                format!("the body ended after {} of {length} bytes", body.len()),
            ),
            false,
        ));
    }
    Ok(Some(HttpRequest { method, path, body }))
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        411 => "Length Required",
        413 => "Content Too Large",
        415 => "Unsupported Media Type",
        422 => "Unprocessable Content",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        503 => "Service Unavailable",
        _ => "Unknown",
    }
}

fn respond(stream: &mut TcpStream, status: u16, content_type: &str, body: &[u8]) {
    let head = format!(
        "HTTP/1.1 {status} {}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        reason(status),
        body.len()
    );
    let _ = stream
        .write_all(head.as_bytes())
        .and_then(|_| stream.write_all(body))
        .and_then(|_| stream.flush());
}

fn respond_error(stream: &mut TcpStream, e: &ApiError) {
    let body = serde_json::json!({ "error": e.message, "status": e.status }).to_string();
    respond(stream, e.status, "application/json", body.as_bytes());
}

/// Closes after an early reply while the client may still be sending: stop writing, keep
/// reading for a moment so that the unread bytes do not turn into a reset that would hide the
/// reply from the client.
fn lingering_close(stream: &mut TcpStream) {
    let _ = stream.shutdown(Shutdown::Write);
    let _ = stream.set_read_timeout(Some(Duration::from_millis(500)));
    let deadline = Instant::now() + Duration::from_secs(2);
    let mut sink = [0u8; 65536];
    while Instant::now() < deadline {
        match stream.read(&mut sink) {
            Ok(0) | Err(_) => break,
            Ok(_) => {}
        }
    }
}

fn connection(mut stream: TcpStream, shared: &Shared, jobs: &Sender<Job>) {
    let _ = stream.set_read_timeout(Some(shared.read_timeout));
    let _ = stream.set_write_timeout(Some(Duration::from_secs(60)));
    let _ = stream.set_nodelay(true);
    if shared.counters.connections.load(Ordering::SeqCst) > shared.max_connections {
        respond_error(
            &mut stream,
            &api(
                503,
                format!(
                    "server busy: more than {} open connections; retry later",
                    shared.max_connections
                ),
            ),
        );
        lingering_close(&mut stream);
        return;
    }
    let request = match read_request(&mut stream, shared.max_body) {
        Ok(Some(r)) => r,
        Ok(None) => return,
        Err((e, unread)) => {
            respond_error(&mut stream, &e);
            if unread {
                lingering_close(&mut stream);
            }
            return;
        }
    };
    match (request.method.as_str(), request.path.as_str()) {
        ("GET", "/health") => {
            let i = &shared.info;
            let body = serde_json::json!({
                "status": "ok",
                "model": i.model,
                "device": i.device,
                "dtype": i.dtype,
                "action_dim": i.action_dim,
                "history": i.history,
                "future": i.future,
                "sample_steps": i.sample_steps,
                "stats": i.stats,
                "queue_depth": shared.counters.pending.load(Ordering::SeqCst)
                    .saturating_sub(usize::from(shared.counters.busy.load(Ordering::SeqCst))),
                "queue_capacity": shared.queue_capacity,
                "busy": shared.counters.busy.load(Ordering::SeqCst),
                "served": shared.counters.served.load(Ordering::SeqCst),
                "rejected_busy": shared.counters.rejected_busy.load(Ordering::SeqCst),
                "failed": shared.counters.failed.load(Ordering::SeqCst),
            });
            respond(
                &mut stream,
                200,
                "application/json",
                body.to_string().as_bytes(),
            );
        }
        ("POST", "/v1/chunk") => match parse_chunk(&request.body, &shared.info) {
            Err(e) => respond_error(&mut stream, &e),
            Ok(chunk) => {
                let capacity = shared.queue_capacity + 1;
                let admitted = shared
                    .counters
                    .pending
                    .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| (n < capacity).then_some(n + 1))
                    .is_ok();
                if !admitted {
                    shared.counters.rejected_busy.fetch_add(1, Ordering::SeqCst);
                    let message = format!(
                        "server busy: the model is generating and the queue is full ({} waiting); retry later",
                        shared.queue_capacity
                    );
                    respond_error(&mut stream, &api(503, message));
                    return;
                }
                let (tx, rx) = mpsc::channel();
                let job = Job { request: chunk, received: Instant::now(), reply: tx };
                if jobs.send(job).is_err() {
                    shared.counters.pending.fetch_sub(1, Ordering::SeqCst);
                    respond_error(&mut stream, &api(500, "the model worker stopped"));
                    return;
                }
                match rx.recv() {
                    Ok(Ok(body)) => respond(&mut stream, 200, "application/msgpack", &body),
                    Ok(Err(e)) => respond_error(&mut stream, &e),
                    Err(_) => respond_error(&mut stream, &api(500, "the model worker stopped")),
                }
            }
        },
        (_, "/health" | "/v1/chunk") => {
            let allowed = if request.path == "/health" {
                "GET"
            } else {
                "POST"
            };
            respond_error(
                &mut stream,
                &api(
                    405,
                    format!(
                        "{} {} is not served; use {allowed}",
                        request.method, request.path
                    ),
                ),
            );
        }
        _ => respond_error(
            &mut stream,
            &api(
                404,
                format!(
                    "no endpoint {} (endpoints: POST /v1/chunk, GET /health)",
                    request.path
                ),
            ),
        ),
    }
}

/// Checks a /v1/chunk body against the model: every problem is a 4xx naming it.
fn parse_chunk(body: &[u8], info: &ModelInfo) -> Result<ChunkRequest, ApiError> {
    let v = msgpack_numpy::decode(body).map_err(|e| api(400, format!("body: {e:#}")))?;
    let entries = v.as_map().ok_or_else(|| {
        api(
            400,
            "body: expected a msgpack map {frames, actions, normalized, seed}",
        )
    })?;
    for (k, _) in entries {
        let name = k
            .as_str()
            .map(str::to_string)
            .unwrap_or_else(|| format!("{k}"));
        if !["frames", "actions", "normalized", "seed"].contains(&name.as_str()) {
            return Err(api(
                422,
                format!("unknown entry '{name}' (expected frames, actions, normalized, seed)"),
            ));
        }
    }
    let frames = msgpack_numpy::array_at(&v, "frames").map_err(|e| api(422, format!("{e:#}")))?;
    if frames.dtype != Dtype::U8 {
        return Err(api(
            422,
            format!("'frames' must be uint8, got {}", frames.describe()),
        ));
    }
    let (t, h, w) = match frames.shape.as_slice() {
        &[t, h, w, 3] if t >= 1 => (t, h, w),
        _ => {
            return Err(api(
                422,
                format!(
                    "'frames' must be (T >= 1, H, W, 3): x0 then the history frames; got {}",
                    frames.describe()
                ),
            ))
        }
    };
    if h == 0 || w == 0 || h % 32 != 0 || w % 32 != 0 {
        return Err(api(
            422,
            format!("frames are {h}x{w} (HxW); height and width must be positive multiples of 32"),
        ));
    }
    let actions = msgpack_numpy::array_at(&v, "actions").map_err(|e| api(422, format!("{e:#}")))?;
    if !matches!(actions.dtype, Dtype::F32 | Dtype::F64) {
        return Err(api(
            422,
            format!(
                "'actions' must be float32 (or float64), got {}",
                actions.describe()
            ),
        ));
    }
    let (rows, d) = match actions.shape.as_slice() {
        &[f, d] => (f, d),
        _ => {
            return Err(api(
                422,
                format!("'actions' must be (F, d_a), got {}", actions.describe()),
            ))
        }
    };
    if d != info.action_dim {
        return Err(api(
            422,
            format!(
                "'actions' has {d} values per row; the model takes {}",
                info.action_dim
            ),
        ));
    }
    if rows <= t || rows - t > info.future {
        return Err(api(
            422,
            format!(
                "'actions' has {rows} rows; expected one per given frame ({t}) plus 1..={} future actions (K), i.e. {}..={} rows",
                info.future,
                t + 1,
                t + info.future
            ),
        ));
    }
    let values = actions.to_f32();
    if values.iter().any(|x| !x.is_finite()) {
        return Err(api(422, "'actions' holds NaN or infinite values"));
    }
    let normalized = match map_get(&v, "normalized").map(scalar) {
        Some(Value::Boolean(b)) => *b,
        Some(other) => return Err(api(422, format!("'normalized' must be a bool, got {other}"))),
        None => return Err(api(422, "'normalized' (bool) is required: true when the actions are already in the model's [-1, 1]")),
    };
    if !normalized && !info.stats {
        return Err(api(422, "raw actions ('normalized': false) need the server to run with --stats; send normalized actions instead"));
    }
    let seed = match map_get(&v, "seed").map(scalar) {
        None | Some(Value::Nil) => None,
        Some(s) => Some(s.as_u64().ok_or_else(|| {
            api(
                422,
                format!("'seed' must be a non-negative integer, got {s}"),
            )
        })?),
    };
    Ok(ChunkRequest {
        frames: frames.data,
        t,
        h,
        w,
        actions: values.chunks(d).map(<[f32]>::to_vec).collect(),
        normalized,
        seed,
    })
}

fn generate(wm: &WorldModel, req: &ChunkRequest, queued: f64) -> Result<Vec<u8>, ApiError> {
    let start = Instant::now();
    let failed = |e: anyhow::Error| api(500, format!("generation failed: {e:#}"));
    let (t, h, w) = (req.t as i64, req.h as i64, req.w as i64);
    let frames = (Tensor::from_slice(&req.frames)
        .view([t, h, w, 3])
        .permute([3, 0, 1, 2])
        .to_kind(Kind::Float)
        / 127.5
        - 1.0)
        .contiguous();
    let actions = if req.normalized {
        wm.rows_to_tensor(req.actions.clone())
    } else {
        wm.normalize(&req.actions)
    }
    .map_err(failed)?;
    let spec = bwm_model::rollout::RolloutSpec {
        seed: req.seed.unwrap_or(wm.spec.seed),
        ..wm.spec.clone()
    };
    let mut rollout = Rollout::new(
        &wm.model,
        &wm.vae,
        spec,
        &frames.select(1, 0),
        &actions.get(0),
    )
    .map_err(failed)?;
    if t > 1 {
        rollout = rollout
            .with_history(&frames.narrow(1, 1, t - 1), &actions.narrow(0, 1, t - 1))
            .map_err(failed)?;
    }
    let n = actions.size()[0] - t;
    let chunk = rollout
        .next_chunk(&actions.narrow(0, t, n))
        .map_err(failed)?;
    let pixels = ((chunk.frames.clamp(-1.0, 1.0) + 1.0) * 127.5)
        .round()
        .to_kind(Kind::Uint8)
        .permute([1, 2, 3, 0])
        .contiguous();
    let pixels = Vec::<u8>::try_from(pixels.view([-1])).map_err(|e| failed(e.into()))?;
    let applied = if req.normalized {
        tensor_rows(&chunk.actions)
    } else {
        Ok(req.actions[req.t..].to_vec())
    }
    .map_err(failed)?;
    let d = wm.action_dim();
    let flat: Vec<f32> = applied.into_iter().flatten().collect();
    let timings = str_map(vec![
        ("queue_s", Value::F64(queued)),
        ("encode_s", Value::F64(chunk.encode_seconds)),
        ("dit_s", Value::F64(chunk.dit_seconds)),
        ("decode_s", Value::F64(chunk.decode_seconds)),
        ("total_s", Value::F64(start.elapsed().as_secs_f64())),
    ]);
    let out = str_map(vec![
        (
            "frames",
            NdArray::from_u8(vec![n as usize, req.h, req.w, 3], pixels)
                .map_err(failed)?
                .to_value(),
        ),
        (
            "actions",
            NdArray::from_f32(vec![n as usize, d], &flat)
                .map_err(failed)?
                .to_value(),
        ),
        ("normalized", Value::Boolean(req.normalized)),
        ("timings", timings),
    ]);
    Ok(msgpack_numpy::encode(&out))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info() -> ModelInfo {
        ModelInfo {
            model: "m".into(),
            device: "cpu".into(),
            dtype: "f32".into(),
            action_dim: 2,
            history: 4,
            future: 4,
            sample_steps: 1,
            stats: false,
        }
    }

    fn body(frames: NdArray, actions: NdArray, extra: Vec<(&str, Value)>) -> Vec<u8> {
        let mut entries = vec![
            ("frames", frames.to_value()),
            ("actions", actions.to_value()),
        ];
        entries.extend(extra);
        msgpack_numpy::encode(&str_map(entries))
    }

    fn frames(t: usize, h: usize, w: usize) -> NdArray {
        NdArray::from_u8(vec![t, h, w, 3], vec![7; t * h * w * 3]).unwrap()
    }

    fn actions(rows: usize, d: usize) -> NdArray {
        NdArray::from_f32(vec![rows, d], &vec![0.5; rows * d]).unwrap()
    }

    fn err(b: &[u8]) -> String {
        match parse_chunk(b, &info()) {
            Err(e) => format!("{} {}", e.status, e.message),
            Ok(_) => "accepted".into(),
        }
    }

    #[test]
    fn good_requests_are_accepted() {
        let r = parse_chunk(
            &body(
                frames(2, 32, 64),
                actions(5, 2),
                vec![
                    ("normalized", Value::Boolean(true)),
                    ("seed", Value::from(3)),
                ],
            ),
            &info(),
        )
        .unwrap();
        assert_eq!(
            (r.t, r.h, r.w, r.actions.len(), r.seed),
            (2, 32, 64, 5, Some(3))
        );
    }

    #[test]
    fn each_problem_is_named() {
        let yes = || vec![("normalized", Value::Boolean(true))];
        assert!(err(b"\x92\x01").starts_with("400"));
        assert!(err(&msgpack_numpy::encode(&Value::from(3))).contains("expected a msgpack map"));
        assert!(err(&body(frames(1, 33, 32), actions(2, 2), yes())).contains("33x32"));
        let floats = NdArray::from_f32(vec![1, 32, 32, 3], &vec![0.0; 3072]).unwrap();
        assert!(err(&body(floats, actions(2, 2), yes()))
            .contains("'frames' must be uint8, got float32 (1, 32, 32, 3)"));
        assert!(err(&body(frames(1, 32, 32), actions(2, 3), yes())).contains("3 values per row"));
        assert!(err(&body(frames(1, 32, 32), actions(6, 2), yes())).contains("2..=5 rows"));
        assert!(err(&body(frames(1, 32, 32), actions(1, 2), yes())).contains("2..=5 rows"));
        assert!(err(&body(frames(1, 32, 32), actions(2, 2), vec![]))
            .contains("'normalized' (bool) is required"));
        assert!(err(&body(
            frames(1, 32, 32),
            actions(2, 2),
            vec![("normalized", Value::Boolean(false))]
        ))
        .contains("--stats"));
        assert!(err(&body(
            frames(1, 32, 32),
            actions(2, 2),
            vec![
                ("normalized", Value::Boolean(true)),
                ("seeds", Value::from(1))
            ]
        ))
        .contains("unknown entry 'seeds'"));
        assert!(err(&body(
            frames(1, 32, 32),
            actions(2, 2),
            vec![
                ("normalized", Value::Boolean(true)),
                ("seed", Value::from(-1))
            ]
        ))
        .contains("'seed'"));
        let ints = NdArray::new(Dtype::I64, vec![2, 2], vec![0; 32]).unwrap();
        assert!(err(&body(frames(1, 32, 32), ints, yes())).contains("'actions' must be float32"));
    }
}
