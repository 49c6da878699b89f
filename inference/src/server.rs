//! The world model over HTTP, one chunk per request, for clients that run the loop themselves
//! (`bwm serve`; protocol: docs/serve.md).
//!
//! The model lives on one worker thread (it holds `Rc`s) behind a bounded queue: a request that
//! finds the queue full is answered 503 at once. HTTP is hyper's on a small tokio runtime, so a
//! client that sends half a request costs a task, not a thread: while many such clients wait,
//! /health and real requests are answered. A body over the limit is refused from its
//! Content-Length before any of it is read, and bounded while it streams; a client gets
//! --read-timeout-s to send its whole request (408 after). SIGTERM or Ctrl-C stops accepting,
//! lets requests in flight finish and closes the connections that have not sent one.

use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{self, Sender};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context, Result};
use bytes::Bytes;
use http_body_util::{BodyExt, Full, LengthLimitError, Limited};
use hyper::body::Incoming;
use hyper::header::{HeaderValue, CONNECTION, CONTENT_LENGTH, CONTENT_TYPE, TRANSFER_ENCODING};
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::TokioIo;
use rmpv::Value;
use tch::{Kind, Tensor};
use tokio::io::AsyncWriteExt;
use tokio::sync::{oneshot, watch};

use crate::msgpack_numpy::{self, map_get, scalar, str_map, Dtype, NdArray};
use crate::world_model::{tensor_rows, WorldModel, WorldModelOptions};

/// How the server listens and what it admits (`bwm serve`'s flags of the same names).
#[derive(Clone, Debug)]
pub struct ServeOptions {
    pub host: String,
    /// Port to listen on (0: any free port; the address is printed).
    pub port: u16,
    /// Requests that may wait while the model is busy; further ones get 503 at once.
    pub queue: usize,
    /// Largest request body in bytes (413 above it).
    pub max_body_bytes: usize,
    /// Open connections at most; further ones get 503 at once.
    pub max_connections: usize,
    /// Seconds a client may take to send its request (408 after).
    pub read_timeout_s: u64,
}

impl Default for ServeOptions {
    fn default() -> Self {
        Self { host: "127.0.0.1".into(), port: 8080, queue: 4, max_body_bytes: 256 << 20, max_connections: 512, read_timeout_s: 60 }
    }
}

/// Request heads above these are answered 431 (by hyper).
const MAX_HEAD: usize = 16 << 10;
const MAX_HEADERS: usize = 64;

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
    reply: oneshot::Sender<Result<Vec<u8>, ApiError>>,
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
    solver: String,
    shift: f64,
    guidance: f64,
    history_sigma: Option<f64>,
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
    /// The model worker's queue (admission is bounded by `Counters::pending`).
    jobs: Sender<Job>,
}

/// Loads the model, listens, and serves until SIGTERM or SIGINT (then finishes the requests in
/// flight). Prints `serve: listening on http://ADDR` once it accepts connections.
pub fn serve(wm: &WorldModelOptions, a: &ServeOptions) -> Result<()> {
    let model = match (&wm.checkpoint, &wm.random_weights) {
        (Some(c), _) => c.clone(),
        (None, Some(p)) => format!("random weights ({p})"),
        (None, None) => "none".into(),
    };
    let (ready_tx, ready_rx) = mpsc::channel::<Result<ModelInfo>>();
    // Admission is bounded by `Counters::pending`, so the channel itself need not be.
    let (job_tx, job_rx) = mpsc::channel::<Job>();
    let wm_args = wm.clone();
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
                solver: wm.spec.solver.to_string(),
                shift: wm.spec.shift,
                guidance: wm.spec.guidance,
                history_sigma: wm.spec.history_sigma,
                stats: wm.stats.is_some(),
            };
            if ready_tx.send(Ok(info)).is_err() {
                return;
            }
            let counters = worker_counters;
            for job in job_rx {
                if job.reply.is_closed() {
                    // The client went away while its request waited: nobody reads this chunk.
                    counters.pending.fetch_sub(1, Ordering::SeqCst);
                    continue;
                }
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
    let listener = std::net::TcpListener::bind((a.host.as_str(), a.port))
        .with_context(|| format!("listening on {}:{}", a.host, a.port))?;
    listener.set_nonblocking(true)?;
    let addr = listener.local_addr()?;
    let shared = Arc::new(Shared {
        info: info.clone(),
        queue_capacity: a.queue,
        max_body: a.max_body_bytes,
        max_connections: a.max_connections.max(1),
        read_timeout: Duration::from_secs(a.read_timeout_s.max(1)),
        counters,
        jobs: job_tx,
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
    // Two threads: the HTTP side only parses, checks and hands requests to the model worker.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the HTTP runtime")?;
    runtime.block_on(accept_loop(listener, addr, shared))
}

async fn accept_loop(listener: std::net::TcpListener, addr: std::net::SocketAddr, shared: Arc<Shared>) -> Result<()> {
    use tokio::signal::unix::{signal, SignalKind};
    let listener = tokio::net::TcpListener::from_std(listener)?;
    let mut terminate = signal(SignalKind::terminate()).context("handling SIGTERM")?;
    let mut interrupt = signal(SignalKind::interrupt()).context("handling SIGINT")?;
    let (stopping, stop) = watch::channel(false);
    let mut connections = tokio::task::JoinSet::new();
    println!("serve: listening on http://{addr}");
    use std::io::Write as _;
    let _ = std::io::stdout().flush();
    loop {
        tokio::select! {
            _ = terminate.recv() => break,
            _ = interrupt.recv() => break,
            Some(_) = connections.join_next(), if !connections.is_empty() => {}
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    let open = shared.counters.connections.fetch_add(1, Ordering::SeqCst) + 1;
                    connections.spawn(connection(stream, open, shared.clone(), stop.clone()));
                }
                Err(e) => {
                    eprintln!("serve: accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            },
        }
    }
    drop(listener);
    println!("serve: stopping: no new connections; {} open ones finish their requests", connections.len());
    let _ = stopping.send(true);
    while connections.join_next().await.is_some() {}
    println!("serve: stopped");
    Ok(())
}

type Reply = Response<Full<Bytes>>;
type ReplyFuture = Pin<Box<dyn Future<Output = Result<Reply, Infallible>> + Send>>;

/// Lowers the open-connection count when the connection's task ends, however it ends.
struct Open(Arc<Counters>);

impl Drop for Open {
    fn drop(&mut self) {
        self.0.connections.fetch_sub(1, Ordering::SeqCst);
    }
}

/// One connection, one request (each response closes it). Until its request head has arrived
/// the connection is closed at shutdown and answered 408 after the read timeout; once it has,
/// the request runs to its end (its body has the rest of the read timeout).
async fn connection(stream: tokio::net::TcpStream, open: usize, shared: Arc<Shared>, mut stop: watch::Receiver<bool>) {
    let _open = Open(shared.counters.clone());
    let _ = stream.set_nodelay(true);
    let mut stream = stream;
    if open > shared.max_connections {
        let e = api(503, format!("server busy: more than {} open connections; retry later", shared.max_connections));
        let _ = stream.write_all(&raw_response(&e)).await;
        let _ = stream.shutdown().await;
        return;
    }
    let arrived = Instant::now();
    let started = Arc::new(AtomicBool::new(false));
    let service = {
        let (shared, started) = (shared.clone(), started.clone());
        hyper::service::service_fn(move |req: Request<Incoming>| -> ReplyFuture {
            started.store(true, Ordering::SeqCst);
            Box::pin(handle(req, shared.clone(), arrived))
        })
    };
    let mut conn = hyper::server::conn::http1::Builder::new()
        .keep_alive(false)
        .max_buf_size(MAX_HEAD)
        .max_headers(MAX_HEADERS)
        .serve_connection(TokioIo::new(stream), service);
    let deadline = tokio::time::sleep(shared.read_timeout);
    tokio::pin!(deadline);
    let mut timer_done = false;
    loop {
        let waiting = !started.load(Ordering::SeqCst);
        tokio::select! {
            _ = &mut conn => return,
            _ = &mut deadline, if waiting && !timer_done => {
                timer_done = true;
                if started.load(Ordering::SeqCst) {
                    continue;
                }
                let e = api(408, format!("no complete request within {} s (--read-timeout-s)", shared.read_timeout.as_secs()));
                let mut io = conn.into_parts().io.into_inner();
                let _ = io.write_all(&raw_response(&e)).await;
                let _ = io.shutdown().await;
                return;
            }
            _ = stop.changed(), if waiting => {
                if !started.load(Ordering::SeqCst) {
                    return;
                }
            }
        }
    }
}

/// A whole HTTP/1.1 error response, for the two cases answered outside hyper's request cycle.
fn raw_response(e: &ApiError) -> Vec<u8> {
    let body = error_json(e);
    let reason = StatusCode::from_u16(e.status).ok().and_then(|s| s.canonical_reason()).unwrap_or("");
    let mut out = format!(
        "HTTP/1.1 {} {reason}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        e.status,
        body.len()
    )
    .into_bytes();
    out.extend_from_slice(body.as_bytes());
    out
}

fn error_json(e: &ApiError) -> String {
    serde_json::json!({ "error": e.message, "status": e.status }).to_string()
}

fn reply(status: u16, content_type: &'static str, body: Vec<u8>) -> Reply {
    let mut r = Response::new(Full::new(Bytes::from(body)));
    *r.status_mut() = StatusCode::from_u16(status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
    r.headers_mut().insert(CONTENT_TYPE, HeaderValue::from_static(content_type));
    r.headers_mut().insert(CONNECTION, HeaderValue::from_static("close"));
    r
}

/// Routes one request and logs it as one line.
async fn handle(req: Request<Incoming>, shared: Arc<Shared>, arrived: Instant) -> Result<Reply, Infallible> {
    let (method, path) = (req.method().clone(), req.uri().path().to_string());
    let start = Instant::now();
    let (response, bytes_in) = match route(req, &shared, arrived).await {
        Ok((r, n)) => (r, n),
        Err(e) => (reply(e.status, "application/json", error_json(&e).into_bytes()), 0),
    };
    println!(
        "serve: request method={method} path={path} status={} bytes_in={bytes_in} bytes_out={} ms={:.1}",
        response.status().as_u16(),
        hyper::body::Body::size_hint(response.body()).exact().unwrap_or(0),
        start.elapsed().as_secs_f64() * 1e3
    );
    Ok(response)
}

async fn route(req: Request<Incoming>, shared: &Shared, arrived: Instant) -> Result<(Reply, usize), ApiError> {
    let path = req.uri().path();
    match (req.method(), path) {
        (&Method::GET, "/health") => Ok((reply(200, "application/json", health(shared).into_bytes()), 0)),
        (&Method::POST, "/v1/chunk") => chunk(req, shared, arrived).await,
        (m, "/health" | "/v1/chunk") => {
            let allowed = if path == "/health" { "GET" } else { "POST" };
            Err(api(405, format!("{m} {path} is not served; use {allowed}")))
        }
        _ => Err(api(404, format!("no endpoint {path} (endpoints: POST /v1/chunk, GET /health)"))),
    }
}

fn health(shared: &Shared) -> String {
    let (i, c) = (&shared.info, &shared.counters);
    serde_json::json!({
        "status": "ok",
        "model": i.model,
        "device": i.device,
        "dtype": i.dtype,
        "action_dim": i.action_dim,
        "history": i.history,
        "future": i.future,
        "sample_steps": i.sample_steps,
        "solver": i.solver,
        "shift": i.shift,
        "guidance": i.guidance,
        "history_sigma": i.history_sigma,
        "stats": i.stats,
        "queue_depth": c.pending.load(Ordering::SeqCst).saturating_sub(usize::from(c.busy.load(Ordering::SeqCst))),
        "queue_capacity": shared.queue_capacity,
        "busy": c.busy.load(Ordering::SeqCst),
        "served": c.served.load(Ordering::SeqCst),
        "rejected_busy": c.rejected_busy.load(Ordering::SeqCst),
        "failed": c.failed.load(Ordering::SeqCst),
    })
    .to_string()
}

/// Reads the body within the limit and the rest of the read timeout, checks it and waits for
/// the model worker's answer.
async fn chunk(req: Request<Incoming>, shared: &Shared, arrived: Instant) -> Result<(Reply, usize), ApiError> {
    if req.headers().contains_key(TRANSFER_ENCODING) {
        return Err(api(411, "send the body with a Content-Length (chunked transfer encoding is not supported)"));
    }
    let declared = match req.headers().get(CONTENT_LENGTH) {
        None => 0,
        Some(v) => v
            .to_str()
            .ok()
            .and_then(|v| v.trim().parse::<u64>().ok())
            .ok_or_else(|| api(400, format!("Content-Length '{}' is not a number", String::from_utf8_lossy(v.as_bytes()))))?,
    };
    let max = shared.max_body;
    if declared > max as u64 {
        return Err(api(413, format!("request body of {declared} bytes exceeds the limit of {max} bytes (--max-body-bytes)")));
    }
    let left = shared.read_timeout.saturating_sub(arrived.elapsed());
    let body = match tokio::time::timeout(left, Limited::new(req.into_body(), max).collect()).await {
        Err(_) => return Err(api(408, format!("the request body did not arrive within {} s (--read-timeout-s)", shared.read_timeout.as_secs()))),
        Ok(Err(e)) if e.downcast_ref::<LengthLimitError>().is_some() => {
            return Err(api(413, format!("request body exceeds the limit of {max} bytes (--max-body-bytes)")))
        }
        Ok(Err(e)) => return Err(api(400, format!("reading the request body: {e}"))),
        Ok(Ok(collected)) => collected.to_bytes(),
    };
    let request = parse_chunk(&body, &shared.info)?;
    let capacity = shared.queue_capacity + 1;
    let admitted = shared
        .counters
        .pending
        .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| (n < capacity).then_some(n + 1))
        .is_ok();
    if !admitted {
        shared.counters.rejected_busy.fetch_add(1, Ordering::SeqCst);
        return Err(api(
            503,
            format!("server busy: the model is generating and the queue is full ({} waiting); retry later", shared.queue_capacity),
        ));
    }
    let (tx, rx) = oneshot::channel();
    let job = Job { request, received: Instant::now(), reply: tx };
    if shared.jobs.send(job).is_err() {
        shared.counters.pending.fetch_sub(1, Ordering::SeqCst);
        return Err(api(500, "the model worker stopped"));
    }
    match rx.await {
        Ok(Ok(out)) => Ok((reply(200, "application/msgpack", out), body.len())),
        Ok(Err(e)) => Err(e),
        Err(_) => Err(api(500, "the model worker stopped")),
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
    let mut rollout = wm.rollout_with(spec, &frames.select(1, 0), &actions.get(0)).map_err(failed)?;
    if t > 1 {
        rollout = rollout
            .with_history(&frames.narrow(1, 1, t - 1), &actions.narrow(0, 1, t - 1))
            .map_err(failed)?;
    }
    let n = actions.size()[0] - t;
    let chunk = rollout
        .next_chunk(&actions.narrow(0, t, n))
        .map_err(failed)?;
    let pixels = bwm_data::frames::unit_to_u8(&chunk.frames).permute([1, 2, 3, 0]).contiguous();
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
            solver: "euler".into(),
            shift: 5.0,
            guidance: 1.0,
            history_sigma: Some(0.2),
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
