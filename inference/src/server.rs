//! The world model over HTTP, one chunk per request, for clients that run the loop themselves
//! (`bwm serve`; protocol: docs/serve.md).
//!
//! The model lives on one worker thread (it holds `Rc`s) behind a bounded queue: a request that
//! finds the queue full is answered 503 at once. HTTP is hyper's on a small tokio runtime, so a
//! client that sends half a request costs a task, not a thread: while many such clients wait,
//! /health and real requests are answered. A body over the limit is refused from its
//! Content-Length before any of it is read, and bounded while it streams; a client gets
//! --read-timeout-s to send its whole request (408 after). Each request's work is bounded before
//! the worker sees it: frames over --max-frame-pixels (default: the training resolution) are
//! refused with 413, and only x0 and the last H given frames are turned into pixels. A request
//! not answered within --request-timeout-s of its admission is answered 504, and the worker
//! abandons it: before it starts, or at its next sampler step (the encode and the decode run to
//! their end). libtorch's failures (an allocation out of memory) are errors naming the request's
//! size, not panics. SIGTERM or Ctrl-C stops accepting, lets requests in flight finish and closes
//! the connections that have not sent one.

use std::cell::RefCell;
use std::convert::Infallible;
use std::fmt;
use std::future::Future;
use std::path::PathBuf;
use std::pin::Pin;
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{self, Sender};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, ensure, Context, Result};
use bytes::Bytes;
use bwm_model::sampler::{Denoiser, Eager};
use bwm_model::BwmModel;
use http_body_util::{BodyExt, Full};
use hyper::body::Incoming;
use hyper::header::{HeaderValue, CONNECTION, CONTENT_LENGTH, CONTENT_TYPE, TRANSFER_ENCODING};
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::TokioIo;
use rmpv::Value;
use tch::{Kind, Tensor};
use tokio::io::AsyncWriteExt;
use tokio::sync::{oneshot, watch};

use crate::fallible::{alloc_error, guarded};
use crate::graphed::GraphedDenoiser;
use crate::msgpack_numpy::{self, map_get, scalar, str_map, Dtype, NdArray};
use crate::world_model::{tensor_rows, WorldModel, WorldModelOptions};

mod worldarena;
use bwm_checkpoints::contract::InputContract;

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
    /// Largest frame in pixels (height x width; 413 above it). None: the training resolution's,
    /// where the weights record it, else 640 x 480.
    pub max_frame_pixels: Option<usize>,
    /// Seconds from a request's admission to its answer (504 after; the worker abandons it).
    /// 0: no limit.
    pub request_timeout_s: u64,
    /// A test hook: while this file exists, the worker waits before each sampler step, so that a
    /// test can hold it busy for as long as it needs.
    pub hold_while_exists: Option<PathBuf>,
}

impl Default for ServeOptions {
    fn default() -> Self {
        Self {
            host: "127.0.0.1".into(),
            port: 8080,
            queue: 4,
            max_body_bytes: 256 << 20,
            max_connections: 512,
            read_timeout_s: 60,
            max_frame_pixels: None,
            request_timeout_s: 300,
            hold_while_exists: None,
        }
    }
}

/// The frame budget of weights that record no training resolution: 640 x 480.
pub const DEFAULT_MAX_FRAME_PIXELS: usize = 640 * 480;

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

/// What a request asks of the model worker.
enum Work {
    /// `/v1/chunk`: one chunk, from the context the request carries.
    Chunk(ChunkRequest),
    /// WorldArena's `/reset`: new environments.
    Reset(worldarena::ResetRequest),
    /// WorldArena's `/chunk_step`: the environments advanced by one chunk.
    Step(worldarena::StepRequest),
}

struct Job {
    request: Work,
    received: Instant,
    /// When the request's time limit ends (None: no limit).
    deadline: Option<Instant>,
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
    /// Largest frame in pixels, and where that bound comes from.
    max_frame_pixels: usize,
    frame_budget: String,
    /// The per-request time limit (None: none).
    request_timeout: Option<Duration>,
    /// What requests must send (`GET /v1/contract`); frames and actions are checked against it.
    contract: InputContract,
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
    /// Requests answered 504: abandoned by the worker past their time limit.
    timed_out: AtomicU64,
    /// WorldArena environments of the last `/reset` (0: none yet).
    envs: AtomicUsize,
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

/// The longest timeout taken (about 31 years): a deadline further ahead would overflow the clock.
const MAX_TIMEOUT_S: u64 = 1_000_000_000;

/// Loads the model, listens, and serves until SIGTERM or SIGINT (then finishes the requests in
/// flight). Prints `serve: listening on http://ADDR` once it accepts connections.
pub fn serve(wm: &WorldModelOptions, a: &ServeOptions) -> Result<()> {
    for (flag, s) in [("--read-timeout-s", a.read_timeout_s), ("--request-timeout-s", a.request_timeout_s)] {
        ensure!(s <= MAX_TIMEOUT_S, "{flag} {s}: at most {MAX_TIMEOUT_S} seconds (0 = no limit where the flag allows it)");
    }
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
    let request_timeout = (a.request_timeout_s > 0).then(|| Duration::from_secs(a.request_timeout_s));
    let (max_frame_pixels, hold) = (a.max_frame_pixels, a.hold_while_exists.clone());
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
                max_frame_pixels: 0,
                frame_budget: String::new(),
                request_timeout,
                contract: wm.contract.clone(),
            };
            let info = match (max_frame_pixels, wm.trained_resolution) {
                (Some(n), _) => ModelInfo { max_frame_pixels: n, frame_budget: "--max-frame-pixels".into(), ..info },
                (None, Some((w, h))) => ModelInfo {
                    max_frame_pixels: w as usize * h as usize,
                    frame_budget: format!("the training resolution {w}x{h} (WxH); --max-frame-pixels sets another"),
                    ..info
                },
                (None, None) => ModelInfo {
                    max_frame_pixels: DEFAULT_MAX_FRAME_PIXELS,
                    frame_budget: "640x480: the weights record no training resolution; --max-frame-pixels sets another".into(),
                    ..info
                },
            };
            if ready_tx.send(Ok(info)).is_err() {
                return;
            }
            let counters = worker_counters;
            // The WorldArena environments, between `/reset` and the next one.
            let mut envs: Option<worldarena::Envs> = None;
            for job in job_rx {
                let past = |job: &Job| job.deadline.is_some_and(|d| Instant::now() >= d);
                if job.reply.is_closed() || past(&job) {
                    // The client went away while its request waited, or was answered 504: nobody
                    // reads this chunk.
                    if past(&job) {
                        counters.timed_out.fetch_add(1, Ordering::SeqCst);
                        println!("serve: request abandoned before it started: past its time limit (--request-timeout-s)");
                    }
                    counters.pending.fetch_sub(1, Ordering::SeqCst);
                    continue;
                }
                counters.busy.store(true, Ordering::SeqCst);
                let queued = job.received.elapsed().as_secs_f64();
                let watch = Watch { deadline: job.deadline, hold: hold.clone() };
                // A panic that is not libtorch's (those are errors already) still answers 500.
                let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match &job.request {
                    Work::Chunk(request) => generate(&wm, request, queued, watch),
                    Work::Reset(request) => {
                        // A failed reset leaves no environments behind.
                        envs = None;
                        counters.envs.store(0, Ordering::SeqCst);
                        let (new, out) = answered("resetting the environments", || worldarena::Envs::reset(&wm, request))?;
                        counters.envs.store(new.len(), Ordering::SeqCst);
                        envs = Some(new);
                        Ok(out)
                    }
                    Work::Step(request) => match envs.as_mut() {
                        None => Err(api(409, "no environments: POST /reset first")),
                        Some(e) if e.len() != request.len() => Err(api(422, format!("'actions' is for {} environments; /reset made {}", request.len(), e.len()))),
                        Some(e) => answered("stepping the environments", || e.step(&wm, request, watch)),
                    },
                }))
                .unwrap_or_else(|_| Err(api(500, "the model worker panicked on this request")));
                let result = match result {
                    Err(e) if e.status == 504 => {
                        counters.timed_out.fetch_add(1, Ordering::SeqCst);
                        println!("serve: request {}", e.message);
                        Err(e)
                    }
                    Ok(_) if past(&job) => {
                        counters.timed_out.fetch_add(1, Ordering::SeqCst);
                        println!("serve: request finished past its time limit (--request-timeout-s) and was dropped: its client was answered 504");
                        Err(api(504, "past the time limit"))
                    }
                    Ok(out) => {
                        counters.served.fetch_add(1, Ordering::SeqCst);
                        Ok(out)
                    }
                    Err(e) => {
                        counters.failed.fetch_add(1, Ordering::SeqCst);
                        Err(e)
                    }
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
        "serve: {} on {} ({}), d_a = {}, H = {}, K = {}, {} steps; queue {}, body limit {} bytes, frames up to {} pixels ({}), {}",
        info.model,
        info.device,
        info.dtype,
        info.action_dim,
        info.history,
        info.future,
        info.sample_steps,
        a.queue,
        a.max_body_bytes,
        info.max_frame_pixels,
        info.frame_budget,
        match info.request_timeout {
            Some(t) => format!("{} s per request", t.as_secs()),
            None => "no time limit per request".into(),
        }
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
    let mut bytes_in = 0;
    let response = match route(req, &shared, arrived, &mut bytes_in).await {
        Ok(r) => r,
        Err(e) => reply(e.status, "application/json", error_json(&e).into_bytes()),
    };
    println!(
        "serve: request method={method} path={path} status={} bytes_in={bytes_in} bytes_out={} ms={:.1}",
        response.status().as_u16(),
        hyper::body::Body::size_hint(response.body()).exact().unwrap_or(0),
        start.elapsed().as_secs_f64() * 1e3
    );
    Ok(response)
}

/// Answers one request; `bytes_in` counts the body bytes read, whatever the answer.
async fn route(req: Request<Incoming>, shared: &Shared, arrived: Instant, bytes_in: &mut usize) -> Result<Reply, ApiError> {
    let path = req.uri().path();
    match (req.method(), path) {
        (&Method::GET, "/health") => Ok(reply(200, "application/json", health(shared).into_bytes())),
        (&Method::POST, "/reset") => submit(req, shared, arrived, bytes_in, |b, i| worldarena::parse_reset(b, i).map(Work::Reset)).await,
        (&Method::POST, "/chunk_step") => submit(req, shared, arrived, bytes_in, |b, i| worldarena::parse_step(b, i).map(Work::Step)).await,
        (&Method::GET, "/v1/contract") => {
            let text = serde_json::to_string_pretty(&shared.info.contract).map_err(|e| api(500, format!("the contract: {e}")))?;
            Ok(reply(200, "application/json", text.into_bytes()))
        }
        (&Method::POST, "/v1/chunk") => submit(req, shared, arrived, bytes_in, |b, i| parse_chunk(b, i).map(Work::Chunk)).await,
        (m, "/health" | "/v1/chunk" | "/v1/contract" | "/reset" | "/chunk_step") => {
            let allowed = if path == "/health" || path == "/v1/contract" { "GET" } else { "POST" };
            Err(api(405, format!("{m} {path} is not served; use {allowed}")))
        }
        _ => Err(api(404, format!("no endpoint {path} (endpoints: POST /v1/chunk, GET /v1/contract, GET /health; WorldArena's POST /reset, POST /chunk_step)"))),
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
        "max_frame_pixels": i.max_frame_pixels,
        "request_timeout_s": i.request_timeout.map(|t| t.as_secs()),
        "queue_depth": c.pending.load(Ordering::SeqCst).saturating_sub(usize::from(c.busy.load(Ordering::SeqCst))),
        "queue_capacity": shared.queue_capacity,
        "busy": c.busy.load(Ordering::SeqCst),
        "served": c.served.load(Ordering::SeqCst),
        "num_envs": c.envs.load(Ordering::SeqCst),
        "rejected_busy": c.rejected_busy.load(Ordering::SeqCst),
        "failed": c.failed.load(Ordering::SeqCst),
        "timed_out": c.timed_out.load(Ordering::SeqCst),
    })
    .to_string()
}

/// Reads the body within the limit and the rest of the read timeout (counting what it read into
/// `bytes_in`), checks it with `parse` and waits for the model worker's answer until the
/// request's time limit.
async fn submit(
    req: Request<Incoming>,
    shared: &Shared,
    arrived: Instant,
    bytes_in: &mut usize,
    parse: impl FnOnce(&[u8], &ModelInfo) -> Result<Work, ApiError>,
) -> Result<Reply, ApiError> {
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
    let deadline = tokio::time::Instant::from_std(arrived + shared.read_timeout);
    let mut incoming = req.into_body();
    let mut body = Vec::with_capacity(declared as usize);
    loop {
        let frame = match tokio::time::timeout_at(deadline, incoming.frame()).await {
            Err(_) => return Err(api(408, format!("the request body did not arrive within {} s (--read-timeout-s)", shared.read_timeout.as_secs()))),
            Ok(None) => break,
            Ok(Some(Err(e))) => return Err(api(400, format!("reading the request body: {e}"))),
            Ok(Some(Ok(frame))) => frame,
        };
        if let Ok(data) = frame.into_data() {
            *bytes_in += data.len();
            if body.len() + data.len() > max {
                return Err(api(413, format!("request body exceeds the limit of {max} bytes (--max-body-bytes)")));
            }
            body.extend_from_slice(&data);
        }
    }
    let request = parse(&body, &shared.info)?;
    drop(body);
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
    let received = Instant::now();
    let limit = shared.info.request_timeout;
    let job = Job { request, received, deadline: limit.map(|l| received + l), reply: tx };
    if shared.jobs.send(job).is_err() {
        shared.counters.pending.fetch_sub(1, Ordering::SeqCst);
        return Err(api(500, "the model worker stopped"));
    }
    let answer = match limit {
        Some(l) => match tokio::time::timeout_at(tokio::time::Instant::from_std(received + l), rx).await {
            Ok(answer) => answer,
            Err(_) => {
                return Err(api(
                    504,
                    format!(
                        "the request was not answered within its time limit of {} s from admission (--request-timeout-s {}); the model worker abandons it",
                        l.as_secs(),
                        l.as_secs()
                    ),
                ))
            }
        },
        None => rx.await,
    };
    match answer {
        Ok(Ok(out)) => Ok(reply(200, "application/msgpack", out)),
        Ok(Err(e)) => Err(e),
        Err(_) => Err(api(500, "the model worker stopped")),
    }
}

/// The body as a msgpack map holding only `keys` (400 when it is no map, 422 naming an unknown
/// entry).
fn body_map(body: &[u8], keys: &[&str]) -> Result<Value, ApiError> {
    let v = msgpack_numpy::decode(body).map_err(|e| api(400, format!("body: {e:#}")))?;
    let entries = v.as_map().ok_or_else(|| api(400, format!("body: expected a msgpack map {{{}}}", keys.join(", "))))?;
    for (k, _) in entries {
        let name = k.as_str().map(str::to_string).unwrap_or_else(|| format!("{k}"));
        if !keys.contains(&name.as_str()) {
            return Err(api(422, format!("unknown entry '{name}' (expected {})", keys.join(", "))));
        }
    }
    Ok(v)
}

/// `key`'s uint8 images, shaped `(..., H, W, 3)` with `lead` leading dimensions (each at least
/// 1; `shape` names them in errors), checked against the model: multiples of 32 (422), the
/// contract's frame size (422), the frame budget (413). Returns the array and (H, W).
fn images(v: &Value, key: &str, lead: usize, shape: &str, info: &ModelInfo) -> Result<(NdArray, usize, usize), ApiError> {
    let frames = msgpack_numpy::array_at(v, key).map_err(|e| api(422, format!("{e:#}")))?;
    if frames.dtype != Dtype::U8 {
        return Err(api(422, format!("'{key}' must be uint8, got {}", frames.describe())));
    }
    let s = &frames.shape;
    if s.len() != lead + 3 || s[lead + 2] != 3 || s[..lead].contains(&0) {
        return Err(api(422, format!("'{key}' must be {shape}; got {}", frames.describe())));
    }
    let (h, w) = (s[lead], s[lead + 1]);
    if h == 0 || w == 0 || h % 32 != 0 || w % 32 != 0 {
        return Err(api(422, format!("frames are {h}x{w} (HxW); height and width must be positive multiples of 32")));
    }
    info.contract.check_frame_size(w as u32, h as u32, &format!("'{key}'")).map_err(|e| api(422, e.to_string()))?;
    let pixels = h.saturating_mul(w);
    if pixels > info.max_frame_pixels {
        return Err(api(
            413,
            format!("frames are {h}x{w} (HxW), {pixels} pixels; this server takes at most {} pixels per frame ({})", info.max_frame_pixels, info.frame_budget),
        ));
    }
    Ok((frames, h, w))
}

/// `key`'s float32 (or float64) action values of `rank` dimensions, the last the model's action
/// width (the contract's check); finite. Returns the shape and the values.
fn action_values(v: &Value, key: &str, rank: usize, shape: &str, info: &ModelInfo) -> Result<(Vec<usize>, Vec<f32>), ApiError> {
    let actions = msgpack_numpy::array_at(v, key).map_err(|e| api(422, format!("{e:#}")))?;
    if !matches!(actions.dtype, Dtype::F32 | Dtype::F64) {
        return Err(api(422, format!("'{key}' must be float32 (or float64), got {}", actions.describe())));
    }
    if actions.shape.len() != rank {
        return Err(api(422, format!("'{key}' must be {shape}, got {}", actions.describe())));
    }
    info.contract.check_action_dim(actions.shape[rank - 1], &format!("'{key}'")).map_err(|e| api(422, e.to_string()))?;
    let values = actions.to_f32();
    if values.iter().any(|x| !x.is_finite()) {
        return Err(api(422, format!("'{key}' holds NaN or infinite values")));
    }
    Ok((actions.shape.clone(), values))
}

/// `normalized`: required, or when `default` is given, that when absent; raw actions need the
/// server's statistics.
fn normalized_flag(v: &Value, default: Option<bool>, info: &ModelInfo) -> Result<bool, ApiError> {
    let normalized = match (map_get(v, "normalized").map(scalar), default) {
        (Some(Value::Boolean(b)), _) => *b,
        (Some(other), _) => return Err(api(422, format!("'normalized' must be a bool, got {other}"))),
        (None, Some(d)) => d,
        (None, None) => return Err(api(422, "'normalized' (bool) is required: true when the actions are already in the model's [-1, 1]")),
    };
    if !normalized && !info.stats {
        return Err(api(422, "raw actions ('normalized': false) need the training statistics, and neither the weights' contract nor --stats gives them; send normalized actions, or restart the server with --stats"));
    }
    Ok(normalized)
}

/// The optional `seed`.
fn seed_of(v: &Value) -> Result<Option<u64>, ApiError> {
    match map_get(v, "seed").map(scalar) {
        None | Some(Value::Nil) => Ok(None),
        Some(s) => s.as_u64().map(Some).ok_or_else(|| api(422, format!("'seed' must be a non-negative integer, got {s}"))),
    }
}

/// Checks a /v1/chunk body against the model: every problem is a 4xx naming it.
fn parse_chunk(body: &[u8], info: &ModelInfo) -> Result<ChunkRequest, ApiError> {
    let v = body_map(body, &["frames", "actions", "normalized", "seed"])?;
    let (frames, h, w) = images(&v, "frames", 1, "(T >= 1, H, W, 3): x0 then the history frames", info)?;
    let t = frames.shape[0];
    let (shape, values) = action_values(&v, "actions", 2, "(F, d_a)", info)?;
    let (rows, d) = (shape[0], shape[1]);
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
    let normalized = normalized_flag(&v, None, info)?;
    Ok(ChunkRequest { frames: frames.data, t, h, w, actions: values.chunks(d).map(<[f32]>::to_vec).collect(), normalized, seed: seed_of(&v)? })
}

/// What the worker watches while it generates a request: its deadline and the test hook's file.
struct Watch {
    deadline: Option<Instant>,
    hold: Option<PathBuf>,
}

/// A request abandoned at a sampler step, past its time limit.
#[derive(Debug)]
struct PastDeadline {
    step: usize,
    steps: usize,
}

impl fmt::Display for PastDeadline {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "abandoned at sampler step {} of {}: past its time limit (--request-timeout-s)", self.step, self.steps)
    }
}

impl std::error::Error for PastDeadline {}

/// The sampler's forward passes of one request (eager, or replayed from the model's CUDA graphs),
/// each begun only within the request's time limit.
struct Watched {
    inner: Option<Rc<RefCell<GraphedDenoiser>>>,
    watch: Watch,
    step: usize,
    steps: usize,
}

impl Denoiser for Watched {
    fn velocity(&mut self, model: &BwmModel, latents: &Tensor, frame_timesteps: &Tensor, actions: &Tensor, keep: Option<&Tensor>) -> anyhow::Result<Tensor> {
        if let Some(hold) = &self.watch.hold {
            while hold.exists() {
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        self.step += 1;
        if self.watch.deadline.is_some_and(|d| Instant::now() >= d) {
            return Err(PastDeadline { step: self.step, steps: self.steps }.into());
        }
        match &self.inner {
            Some(graphed) => graphed.borrow_mut().velocity(model, latents, frame_timesteps, actions, keep),
            None => Eager.velocity(model, latents, frame_timesteps, actions, keep),
        }
    }
}

/// x0 and the last H of the given frames (the only ones a chunk's condition reads) as [3, n, H, W]
/// in [-1, 1], through tch's fallible calls.
fn request_frames(req: &ChunkRequest, history: usize) -> anyhow::Result<Tensor> {
    let frame = req.h * req.w * 3;
    let kept = (req.t - 1).min(history);
    let mut bytes = Vec::with_capacity((1 + kept) * frame);
    bytes.extend_from_slice(&req.frames[..frame]);
    bytes.extend_from_slice(&req.frames[(req.t - kept) * frame..req.t * frame]);
    let shape = [(1 + kept) as i64, req.h as i64, req.w as i64, 3];
    let failed = |e| alloc_error("the request's frames", &[3, shape[0], shape[1], shape[2]], Kind::Float, tch::Device::Cpu, e);
    let t = Tensor::f_from_slice(&bytes).and_then(|t| t.f_view(shape)).map_err(failed)?;
    let t = t.f_permute([3, 0, 1, 2]).and_then(|t| t.f_to_kind(Kind::Float)).map_err(failed)?;
    t.f_div_scalar(127.5).and_then(|t| t.f_sub_scalar(1.0)).and_then(|t| t.f_contiguous()).map_err(failed)
}

/// One request's chunk: the frames as uint8 [n, H, W, 3] bytes with n, the actions as sent or as
/// applied, and the phases' seconds.
struct Generated {
    pixels: Vec<u8>,
    n: usize,
    actions: Vec<Vec<f32>>,
    seconds: [f64; 3],
}

/// Generates `req`'s chunk where libtorch's failures are errors (`fallible::guarded`): the whole
/// of the work with tensors, from the request's pixels to the reply's bytes.
fn generate_chunk(wm: &WorldModel, req: &ChunkRequest, watch: Watch) -> anyhow::Result<Generated> {
    let t = req.t as i64;
    let frames = request_frames(req, wm.spec.history)?;
    let kept = frames.size()[1] - 1;
    let actions = if req.normalized { wm.rows_to_tensor(req.actions.clone()) } else { wm.normalize(&req.actions) }?;
    let spec = bwm_model::rollout::RolloutSpec { seed: req.seed.unwrap_or(wm.spec.seed), ..wm.spec.clone() };
    let steps = spec.steps;
    let denoiser = Watched { inner: wm.graphed.clone(), watch, step: 0, steps };
    let mut rollout = wm.rollout_with(spec, &frames.select(1, 0), &actions.get(0))?.with_denoiser(Rc::new(RefCell::new(denoiser)));
    if kept > 0 {
        rollout = rollout.with_history(&frames.narrow(1, 1, kept), &actions.narrow(0, t - kept, kept))?;
    }
    let n = actions.size()[0] - t;
    let chunk = rollout.next_chunk(&actions.narrow(0, t, n))?;
    let pixels = bwm_data::frames::unit_to_u8(&chunk.frames).permute([1, 2, 3, 0]).contiguous();
    let pixels = Vec::<u8>::try_from(pixels.view([-1]))?;
    let actions = if req.normalized { tensor_rows(&chunk.actions)? } else { req.actions[req.t..].to_vec() };
    Ok(Generated { pixels, n: n as usize, actions, seconds: [chunk.encode_seconds, chunk.dit_seconds, chunk.decode_seconds] })
}

/// `work` where libtorch's failures are errors (`fallible::guarded`), as the answer: 504 for a
/// request abandoned past its time limit, 500 naming `what` for any other failure.
fn answered<T>(what: &str, work: impl FnOnce() -> anyhow::Result<T>) -> Result<T, ApiError> {
    guarded(|| what.to_string(), work).map_err(|e| match e.chain().find_map(|c| c.downcast_ref::<PastDeadline>()) {
        Some(past) => api(504, past.to_string()),
        None => api(500, format!("{what} failed: {e:#}")),
    })
}

fn generate(wm: &WorldModel, req: &ChunkRequest, queued: f64, watch: Watch) -> Result<Vec<u8>, ApiError> {
    let start = Instant::now();
    let size = format!("{} given frame(s) of {}x{} (HxW), {} action rows", req.t, req.h, req.w, req.actions.len());
    let failed = |e: anyhow::Error| api(500, format!("generation failed ({size}): {e:#}"));
    let g = answered(&format!("generating the chunk of {size}"), || generate_chunk(wm, req, watch))?;
    let d = wm.action_dim();
    let flat: Vec<f32> = g.actions.into_iter().flatten().collect();
    let timings = str_map(vec![
        ("queue_s", Value::F64(queued)),
        ("encode_s", Value::F64(g.seconds[0])),
        ("dit_s", Value::F64(g.seconds[1])),
        ("decode_s", Value::F64(g.seconds[2])),
        ("total_s", Value::F64(start.elapsed().as_secs_f64())),
    ]);
    let out = str_map(vec![
        ("frames", NdArray::from_u8(vec![g.n, req.h, req.w, 3], g.pixels).map_err(failed)?.to_value()),
        ("actions", NdArray::from_f32(vec![g.n, d], &flat).map_err(failed)?.to_value()),
        ("normalized", Value::Boolean(req.normalized)),
        ("timings", timings),
    ]);
    Ok(msgpack_numpy::encode(&out))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_timeout_past_the_clock_is_refused_before_the_model_loads() {
        for (flag, a) in [
            ("--read-timeout-s", ServeOptions { read_timeout_s: u64::MAX, ..Default::default() }),
            ("--request-timeout-s", ServeOptions { request_timeout_s: MAX_TIMEOUT_S + 1, ..Default::default() }),
        ] {
            let e = serve(&WorldModelOptions::default(), &a).unwrap_err().to_string();
            assert!(e.starts_with(flag) && e.contains("at most 1000000000 seconds"), "{e}");
        }
    }

    pub(super) fn info() -> ModelInfo {
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
            max_frame_pixels: 2048,
            frame_budget: "--max-frame-pixels".into(),
            request_timeout: None,
            contract: InputContract::of_model(2),
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

    pub(super) fn frames(t: usize, h: usize, w: usize) -> NdArray {
        NdArray::from_u8(vec![t, h, w, 3], vec![7; t * h * w * 3]).unwrap()
    }

    pub(super) fn actions(rows: usize, d: usize) -> NdArray {
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
        assert!(err(&body(frames(1, 32, 32), actions(2, 3), yes())).contains("'actions': 3-D actions, but this model takes 2-D actions"));
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

    /// Frames of another size than the contract's and actions of another width are refused with
    /// 422, in one line naming both.
    #[test]
    fn requests_are_checked_against_the_contract() {
        let yes = || vec![("normalized", Value::Boolean(true))];
        let mut contract = InputContract::of_model(2);
        contract.actions.as_mut().unwrap().components = vec!["x".into(), "gripper".into()];
        contract.frames = Some(bwm_checkpoints::contract::FrameContract {
            width: 64,
            height: 32,
            fps: 10.0,
            cameras: vec![],
            layout: bwm_data::CameraLayout::Single,
            resize: bwm_data::ResizeMode::Crop,
        });
        let with = ModelInfo { contract, ..info() };
        let e = |b: &[u8]| parse_chunk(b, &with).err().map(|e| format!("{} {}", e.status, e.message)).unwrap_or_else(|| "accepted".into());
        assert_eq!(e(&body(frames(1, 32, 64), actions(2, 2), yes())), "accepted");
        assert_eq!(e(&body(frames(1, 32, 32), actions(2, 2), yes())), "422 'frames': 32x32 frames, but this model was trained on 64x32 (contract.json; WIDTHxHEIGHT)");
        assert_eq!(e(&body(frames(1, 32, 64), actions(2, 7), yes())), "422 'actions': 7-D actions, but this model takes 2-D actions: x, gripper (contract.json)");
    }

    #[test]
    fn frames_over_the_pixel_budget_are_refused_with_413() {
        let yes = || vec![("normalized", Value::Boolean(true))];
        assert_eq!(err(&body(frames(1, 32, 64), actions(2, 2), yes())), "accepted", "2048 pixels: at the budget");
        let e = err(&body(frames(1, 32, 96), actions(2, 2), yes()));
        assert_eq!(e, "413 frames are 32x96 (HxW), 3072 pixels; this server takes at most 2048 pixels per frame (--max-frame-pixels)");
        // The budget is checked before the actions are read.
        assert!(err(&body(frames(1, 64, 64), actions(9, 5), yes())).starts_with("413 "));
    }

    #[test]
    fn only_x0_and_the_last_h_given_frames_become_pixels() {
        let mut data = Vec::new();
        for i in 0..6u8 {
            data.extend(std::iter::repeat(i * 40).take(32 * 32 * 3));
        }
        let req = ChunkRequest { frames: data, t: 6, h: 32, w: 32, actions: vec![vec![0.0; 2]; 7], normalized: true, seed: None };
        let t = request_frames(&req, 2).unwrap();
        assert_eq!(t.size(), [3, 3, 32, 32]);
        let firsts: Vec<f64> = (0..3).map(|i| t.double_value(&[0, i, 0, 0])).collect();
        let want = [0.0, 160.0, 200.0].map(|v: f64| v / 127.5 - 1.0);
        assert!(firsts.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6), "x0, then frames 4 and 5: {firsts:?}");
        assert_eq!(request_frames(&req, 8).unwrap().size(), [3, 6, 32, 32], "fewer given than H: all of them");
    }
}
