//! The launchers' agent store, for jobs of several nodes. Node 0's launcher hosts it; every
//! launcher, node 0's included, connects, introduces itself (`hello`: --nnodes, --node-rank,
//! --nproc-per-node and the rank command, which must agree across nodes) and sends a heartbeat
//! every second. The store decides for all nodes at once: `start` attempt n when every node has
//! joined; `restart` when a node's rank fails, a node drops its connection or misses heartbeats
//! for --heartbeat-timeout (every node stops its ranks, says `ready`, and attempt n + 1 starts
//! when all have); `stop` when the restarts are used up, a node was signalled, or a node does not
//! join within --rdzv-timeout; `finish` when every node's ranks exited 0. The store beats too, so
//! the other launchers notice a lost node 0. Messages are JSON objects, one a line.
//!
//! Written by hand (std sockets, a thread per node, serde_json) because torchrun's elastic agent
//! and its c10d rendezvous have no Rust counterpart; a line protocol between a handful of
//! launchers needs no async runtime, and blocking reads with timeouts are what notice a lost node.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use serde_json::{json, Value};

use super::{Outcome, Plan, Ranks, FAILURE_GRACE};

const BEAT: Duration = Duration::from_secs(1);
/// Longest message line; a peer sending more is not a launcher.
const MAX_LINE: u64 = 64 * 1024;

pub(super) struct Settings {
    pub nnodes: usize,
    pub node_rank: usize,
    pub nproc: usize,
    pub command: Vec<String>,
    pub max_restarts: u32,
    pub heartbeat_timeout: Duration,
    pub rdzv_timeout: Duration,
    pub grace: Duration,
}

fn send(stream: &mut TcpStream, msg: &Value) -> std::io::Result<()> {
    let mut line = msg.to_string();
    line.push('\n');
    stream.write_all(line.as_bytes())
}

/// Reads newline-terminated lines from `stream` into `deliver` until the peer closes (or sends
/// something that is not a line of text), then calls `closed` with the reason.
fn read_lines(
    stream: TcpStream,
    mut deliver: impl FnMut(String) -> bool,
    closed: impl FnOnce(String),
) {
    let mut reader = BufReader::new(stream);
    loop {
        let mut buf = Vec::new();
        match reader.by_ref().take(MAX_LINE).read_until(b'\n', &mut buf) {
            Ok(0) => return closed("closed the connection".into()),
            Ok(_) if buf.last() != Some(&b'\n') => {
                return closed("sent an over-long or unterminated line".into())
            }
            Ok(_) => match String::from_utf8(buf) {
                Ok(line) => {
                    if !deliver(line.trim_end().to_string()) {
                        return;
                    }
                }
                Err(_) => return closed("sent bytes that are not text".into()),
            },
            Err(e) => return closed(format!("connection failed: {e}")),
        }
    }
}

enum Event {
    Opened(u64, TcpStream),
    Line(u64, String),
    Closed(u64, String),
}

/// Binds the store on node 0 and runs it in a thread; the thread's result is the job's: `Ok`
/// after `finish`, the reason after `stop`.
pub(super) fn host(bind: SocketAddr, s: &Settings) -> Result<JoinHandle<Result<()>>> {
    let listener = TcpListener::bind(bind).with_context(|| {
        format!("node 0 cannot host the launchers' agent store on port {} (--agent-port, default --master-port + 1)", bind.port())
    })?;
    listener.set_nonblocking(true)?;
    let (tx, rx) = mpsc::channel();
    let closing = Arc::new(AtomicBool::new(false));
    let accepting = closing.clone();
    std::thread::spawn(move || accept(listener, tx, accepting));
    let store = Store {
        nnodes: s.nnodes,
        nproc: s.nproc,
        command: s.command.clone(),
        max_restarts: s.max_restarts,
        heartbeat_timeout: s.heartbeat_timeout,
        rdzv_timeout: s.rdzv_timeout,
        grace: s.grace,
        conns: HashMap::new(),
        nodes: (0..s.nnodes).map(|_| None).collect(),
        attempt: 0,
        phase: Phase::Gather {
            deadline: Instant::now() + s.rdzv_timeout,
        },
        signalled: None,
    };
    Ok(std::thread::spawn(move || {
        let result = store.serve(rx);
        closing.store(true, Ordering::SeqCst);
        result
    }))
}

fn accept(listener: TcpListener, tx: Sender<Event>, closing: Arc<AtomicBool>) {
    let mut next = 0u64;
    while !closing.load(Ordering::SeqCst) {
        match listener.accept() {
            Ok((stream, _)) => {
                next += 1;
                let id = next;
                if stream.set_nonblocking(false).is_err() {
                    continue;
                }
                let _ = stream.set_nodelay(true);
                let _ = stream.set_write_timeout(Some(Duration::from_secs(5)));
                let (Ok(writer), Ok(reader)) = (stream.try_clone(), stream.try_clone()) else {
                    continue;
                };
                if tx.send(Event::Opened(id, writer)).is_err() {
                    return;
                }
                let (lines, closed) = (tx.clone(), tx.clone());
                std::thread::spawn(move || {
                    read_lines(
                        reader,
                        |l| lines.send(Event::Line(id, l)).is_ok(),
                        |why| {
                            let _ = closed.send(Event::Closed(id, why));
                        },
                    )
                });
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(50))
            }
            Err(_) => std::thread::sleep(Duration::from_millis(200)),
        }
    }
}

struct Member {
    conn: u64,
    last_seen: Instant,
    ready: bool,
    done: bool,
}

enum Phase {
    /// Waiting for every node to join (first attempt) or to report its ranks stopped (restarts).
    Gather {
        deadline: Instant,
    },
    Running,
}

/// How the job ends.
enum End {
    Finish,
    Stop(String),
}

struct Store {
    nnodes: usize,
    nproc: usize,
    command: Vec<String>,
    max_restarts: u32,
    heartbeat_timeout: Duration,
    rdzv_timeout: Duration,
    grace: Duration,
    conns: HashMap<u64, TcpStream>,
    nodes: Vec<Option<Member>>,
    attempt: u32,
    phase: Phase,
    /// A node whose launcher got SIGINT/SIGTERM: the job is ending, so no more restarts.
    signalled: Option<usize>,
}

impl Store {
    fn serve(mut self, rx: Receiver<Event>) -> Result<()> {
        let mut last_beat = Instant::now();
        let end = loop {
            let ended = match rx.recv_timeout(Duration::from_millis(100)) {
                Ok(ev) => self.event(ev),
                Err(RecvTimeoutError::Timeout) => None,
                Err(RecvTimeoutError::Disconnected) => Some(End::Stop(
                    "the agent store stopped accepting connections".into(),
                )),
            };
            if let Some(end) = ended.or_else(|| self.check_timers()) {
                break end;
            }
            if last_beat.elapsed() >= BEAT {
                last_beat = Instant::now();
                self.broadcast(&json!({"type": "beat"}));
            }
        };
        let msg = match &end {
            End::Finish => json!({"type": "finish"}),
            End::Stop(reason) => json!({"type": "stop", "reason": reason}),
        };
        // Every connection, members or not, gets the verdict; then the store reads on until each
        // peer has closed, so that no unread bytes make the kernel reset a connection (which can
        // discard the verdict before the peer reads it).
        for stream in self.conns.values_mut() {
            let _ = send(stream, &msg);
            let _ = stream.shutdown(Shutdown::Write);
        }
        let until = Instant::now() + Duration::from_secs(5);
        while !self.conns.is_empty() {
            let Some(wait) = until.checked_duration_since(Instant::now()) else {
                break;
            };
            match rx.recv_timeout(wait) {
                Ok(Event::Closed(id, _)) => {
                    self.conns.remove(&id);
                }
                Ok(Event::Opened(_, stream)) => {
                    let _ = stream.shutdown(Shutdown::Both);
                }
                Ok(Event::Line(..)) => {}
                Err(_) => break,
            }
        }
        match end {
            End::Finish => Ok(()),
            End::Stop(reason) => bail!("launch: {reason}"),
        }
    }

    fn broadcast(&mut self, msg: &Value) {
        let conns: Vec<u64> = self.nodes.iter().flatten().map(|m| m.conn).collect();
        for id in conns {
            if let Some(stream) = self.conns.get_mut(&id) {
                let _ = send(stream, msg);
            }
        }
    }

    fn node_of(&self, conn: u64) -> Option<usize> {
        self.nodes
            .iter()
            .position(|m| m.as_ref().is_some_and(|m| m.conn == conn))
    }

    fn drop_conn(&mut self, conn: u64) {
        if let Some(stream) = self.conns.get(&conn) {
            let _ = stream.shutdown(Shutdown::Both);
        }
    }

    fn event(&mut self, ev: Event) -> Option<End> {
        match ev {
            Event::Opened(id, stream) => {
                self.conns.insert(id, stream);
                None
            }
            Event::Closed(id, why) => {
                self.conns.remove(&id);
                let node = self.node_of(id)?;
                self.nodes[node] = None;
                match self.phase {
                    Phase::Running => self.fail(format!("node {node}'s launcher {why}")),
                    Phase::Gather { .. } => {
                        eprintln!("launch agent: node {node}'s launcher {why}; waiting for it to join again");
                        None
                    }
                }
            }
            Event::Line(id, line) => {
                let node = self.node_of(id);
                let Ok(msg) = serde_json::from_str::<Value>(&line) else {
                    return match node {
                        Some(n) => Some(End::Stop(format!(
                            "node {n}'s launcher sent a message that is not JSON: {line:.200}"
                        ))),
                        None => {
                            self.drop_conn(id);
                            None
                        }
                    };
                };
                let kind = msg["type"].as_str().unwrap_or("");
                let Some(node) = node else {
                    if kind == "hello" {
                        return self.hello(id, &msg);
                    }
                    self.drop_conn(id);
                    return None;
                };
                if let Some(m) = self.nodes[node].as_mut() {
                    m.last_seen = Instant::now();
                }
                let current = msg["attempt"].as_u64() == Some(self.attempt as u64);
                match (kind, &self.phase) {
                    ("beat", _) => None,
                    ("signal", Phase::Gather { .. }) => Some(End::Stop(format!(
                        "node {node}'s launcher was stopped by a signal before its ranks started"
                    ))),
                    ("signal", Phase::Running) => {
                        eprintln!("launch agent: node {node}'s launcher got a signal; its ranks checkpoint and stop, and with them all others");
                        self.signalled = Some(node);
                        None
                    }
                    ("ready", Phase::Gather { .. }) if current => {
                        if let Some(m) = self.nodes[node].as_mut() {
                            m.ready = true;
                        }
                        None
                    }
                    ("failed", Phase::Running) if current => {
                        let reason = msg["reason"].as_str().unwrap_or("a rank failed");
                        self.fail(format!("node {node}: {reason}"))
                    }
                    ("done", Phase::Running) if current => {
                        if let Some(m) = self.nodes[node].as_mut() {
                            m.done = true;
                        }
                        self.nodes
                            .iter()
                            .all(|m| m.as_ref().is_some_and(|m| m.done))
                            .then_some(End::Finish)
                    }
                    // Reports of an earlier attempt, or of ranks stopped for the coming restart.
                    ("ready" | "failed" | "done", _) => None,
                    _ => Some(End::Stop(format!(
                        "node {node}'s launcher sent an unexpected message: {line:.200}"
                    ))),
                }
            }
        }
    }

    fn hello(&mut self, conn: u64, msg: &Value) -> Option<End> {
        let (nnodes, node, nproc) = (
            msg["nnodes"].as_u64(),
            msg["node_rank"].as_u64(),
            msg["nproc"].as_u64(),
        );
        let command: Option<Vec<String>> = msg["command"].as_array().map(|a| {
            a.iter()
                .map(|c| c.as_str().unwrap_or("").to_string())
                .collect()
        });
        let (Some(nnodes), Some(node), Some(nproc), Some(command)) = (nnodes, node, nproc, command)
        else {
            return Some(End::Stop(format!(
                "a launcher sent an incomplete hello: {msg}"
            )));
        };
        let node = node as usize;
        let problem = if nnodes as usize != self.nnodes {
            Some(format!(
                "node {node} was started with --nnodes {nnodes}, node 0 with --nnodes {}",
                self.nnodes
            ))
        } else if node >= self.nnodes {
            Some(format!(
                "--node-rank {node} is not below --nnodes {}",
                self.nnodes
            ))
        } else if nproc as usize != self.nproc {
            Some(format!("node {node} runs --nproc-per-node {nproc}, node 0 runs {}; every node must run as many ranks", self.nproc))
        } else if command != self.command {
            Some(format!(
                "node {node} runs `{}`, node 0 runs `{}`; every node must run the same command",
                command.join(" "),
                self.command.join(" ")
            ))
        } else if self.nodes[node].is_some() {
            Some(format!(
                "two launchers were started with --node-rank {node}"
            ))
        } else {
            None
        };
        if let Some(problem) = problem {
            // The offending launcher is not a member, so the verdict goes to every connection.
            return Some(End::Stop(format!("inconsistent nodes: {problem}")));
        }
        if let Phase::Running = self.phase {
            self.drop_conn(conn);
            return Some(End::Stop(format!(
                "node {node}'s launcher joined while the job was running"
            )));
        }
        self.nodes[node] = Some(Member {
            conn,
            last_seen: Instant::now(),
            ready: true,
            done: false,
        });
        let joined = self.nodes.iter().flatten().count();
        eprintln!(
            "launch agent: node {node} joined ({joined}/{} nodes)",
            self.nnodes
        );
        None
    }

    fn check_timers(&mut self) -> Option<End> {
        let now = Instant::now();
        let silent: Vec<usize> = (0..self.nnodes)
            .filter(|&n| {
                self.nodes[n]
                    .as_ref()
                    .is_some_and(|m| now.duration_since(m.last_seen) > self.heartbeat_timeout)
            })
            .collect();
        for &node in &silent {
            let conn = self.nodes[node].take().map(|m| m.conn);
            if let Some(conn) = conn {
                self.drop_conn(conn);
            }
            let why = format!(
                "node {node}'s launcher sent no heartbeat for {:.0} s",
                self.heartbeat_timeout.as_secs_f64()
            );
            match self.phase {
                Phase::Running => return self.fail(why),
                Phase::Gather { .. } => {
                    eprintln!("launch agent: {why}; waiting for it to join again")
                }
            }
        }
        let Phase::Gather { deadline } = self.phase else {
            return None;
        };
        if self
            .nodes
            .iter()
            .all(|m| m.as_ref().is_some_and(|m| m.ready))
        {
            self.phase = Phase::Running;
            for m in self.nodes.iter_mut().flatten() {
                m.done = false;
                m.last_seen = now;
            }
            let attempt = self.attempt;
            self.broadcast(&json!({"type": "start", "attempt": attempt}));
            return None;
        }
        if now >= deadline {
            let missing: Vec<usize> = (0..self.nnodes)
                .filter(|&n| self.nodes[n].as_ref().is_none_or(|m| !m.ready))
                .collect();
            let rdzv = self.rdzv_timeout.as_secs_f64();
            return Some(End::Stop(if self.attempt == 0 {
                format!("node(s) {missing:?} did not join within {rdzv:.0} s (is `bwm launch` running there with the same --master-addr and --master-port?)")
            } else {
                format!("node(s) {missing:?} did not come back for the restart within {rdzv:.0} s of stopping their ranks")
            }));
        }
        None
    }

    /// A node failed while running: restart everyone, or stop.
    fn fail(&mut self, reason: String) -> Option<End> {
        if let Some(node) = self.signalled {
            return Some(End::Stop(format!(
                "{reason}; not restarting: node {node} was stopped by a signal"
            )));
        }
        if self.attempt >= self.max_restarts {
            return Some(End::Stop(format!(
                "{reason} (after {} restarts)",
                self.attempt
            )));
        }
        self.attempt += 1;
        eprintln!(
            "launch agent: {reason}; restarting every node ({}/{})",
            self.attempt, self.max_restarts
        );
        for m in self.nodes.iter_mut().flatten() {
            m.ready = false;
        }
        let attempt = self.attempt;
        self.broadcast(&json!({"type": "restart", "attempt": attempt, "reason": reason}));
        self.phase = Phase::Gather {
            deadline: Instant::now() + self.grace + self.rdzv_timeout,
        };
        None
    }
}

enum Incoming {
    Msg(Value),
    Lost(String),
}

/// Connects to the store, retrying while node 0's launcher is not up yet.
fn connect(addrs: &[SocketAddr], deadline: Instant, stop: &AtomicBool) -> Result<TcpStream> {
    let mut last = None;
    loop {
        for addr in addrs {
            match TcpStream::connect_timeout(addr, Duration::from_secs(2)) {
                Ok(s) => return Ok(s),
                Err(e) => last = Some(e),
            }
        }
        if stop.load(Ordering::SeqCst) {
            bail!("launch: stopped by a signal while waiting for node 0's agent store");
        }
        if Instant::now() >= deadline {
            let e = last.map(|e| e.to_string()).unwrap_or_default();
            bail!(
                "launch: no agent store answered at {} ({e}); is node 0's `bwm launch` running with the same --master-addr and --master-port?",
                addrs.iter().map(|a| a.to_string()).collect::<Vec<_>>().join(", ")
            );
        }
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// This node's part of the job: joins the store, then starts, restarts and stops its ranks as the
/// store says. `Ok` when the store says `finish`.
pub(super) fn member(
    addrs: &[SocketAddr],
    s: &Settings,
    plan: &Plan,
    stop: &AtomicBool,
) -> Result<()> {
    let stream = connect(addrs, Instant::now() + s.rdzv_timeout, stop)?;
    let peer = stream
        .peer_addr()
        .map(|a| a.to_string())
        .unwrap_or_default();
    stream.set_nodelay(true)?;
    stream.set_write_timeout(Some(Duration::from_secs(5)))?;
    let writer = Arc::new(Mutex::new(stream.try_clone()?));
    let say = |msg: Value| -> Result<()> {
        let mut w = writer
            .lock()
            .map_err(|_| anyhow::anyhow!("agent connection lock poisoned"))?;
        send(&mut w, &msg).with_context(|| format!("launch: writing to the agent store at {peer}"))
    };
    say(
        json!({"type": "hello", "nnodes": s.nnodes, "node_rank": s.node_rank, "nproc": s.nproc, "command": s.command}),
    )?;

    let (tx, rx) = mpsc::channel();
    let reader = stream.try_clone()?;
    let lost = tx.clone();
    std::thread::spawn(move || {
        read_lines(
            reader,
            |line| match serde_json::from_str::<Value>(&line) {
                Ok(v) => tx.send(Incoming::Msg(v)).is_ok(),
                Err(_) => {
                    let _ = tx.send(Incoming::Lost(format!(
                        "the service there is not a bwm launch agent store (it sent {line:.80})"
                    )));
                    false
                }
            },
            |why| {
                let _ = lost.send(Incoming::Lost(format!("the agent store {why}")));
            },
        )
    });
    let beating = Arc::new(AtomicBool::new(true));
    {
        let (writer, beating) = (writer.clone(), beating.clone());
        std::thread::spawn(move || {
            while beating.load(Ordering::SeqCst) {
                std::thread::sleep(BEAT);
                let Ok(mut w) = writer.lock() else { return };
                if send(&mut w, &json!({"type": "beat"})).is_err() {
                    return;
                }
            }
        });
    }
    let result = follow(rx, &say, s, plan, stop, &peer);
    beating.store(false, Ordering::SeqCst);
    // Closing our side tells the store we have read its verdict.
    let _ = stream.shutdown(Shutdown::Both);
    result
}

fn follow(
    rx: Receiver<Incoming>,
    say: &dyn Fn(Value) -> Result<()>,
    s: &Settings,
    plan: &Plan,
    stop: &AtomicBool,
    peer: &str,
) -> Result<()> {
    let mut ranks: Option<Ranks> = None;
    let mut attempt = 0u32;
    let mut signalled = false;
    let mut last_heard = Instant::now();
    let stop_ranks =
        |ranks: &mut Option<Ranks>, grace: Duration| ranks.take().and_then(|mut r| r.stop(grace));
    loop {
        if stop.load(Ordering::SeqCst) && !signalled {
            signalled = true;
            say(json!({"type": "signal"}))?;
            if ranks.is_some() {
                eprintln!(
                    "launch: signal received; the ranks checkpoint and stop (grace period {:.0} s)",
                    s.grace.as_secs_f64()
                );
                match stop_ranks(&mut ranks, s.grace) {
                    None => say(json!({"type": "done", "attempt": attempt}))?,
                    Some(why) => say(json!({"type": "failed", "attempt": attempt, "reason": why}))?,
                }
            }
        }
        let first = match rx.recv_timeout(Duration::from_millis(100)) {
            Ok(m) => Some(m),
            Err(RecvTimeoutError::Timeout) => None,
            Err(RecvTimeoutError::Disconnected) => {
                Some(Incoming::Lost("the agent store's connection ended".into()))
            }
        };
        for incoming in first
            .into_iter()
            .chain(std::iter::from_fn(|| rx.try_recv().ok()))
        {
            last_heard = Instant::now();
            let msg = match incoming {
                Incoming::Msg(m) => m,
                Incoming::Lost(why) => {
                    stop_ranks(&mut ranks, FAILURE_GRACE.min(s.grace));
                    bail!("launch: lost node 0's agent store at {peer}: {why}");
                }
            };
            let n = msg["attempt"].as_u64().unwrap_or(0) as u32;
            match msg["type"].as_str().unwrap_or("") {
                "beat" => {}
                "start" if signalled => {
                    say(json!({"type": "failed", "attempt": n, "reason": "stopped by a signal"}))?
                }
                "start" => {
                    attempt = n;
                    match plan.spawn(n) {
                        Ok(r) => ranks = Some(r),
                        Err(e) => {
                            let _ = say(
                                json!({"type": "failed", "attempt": n, "reason": format!("{e:#}")}),
                            );
                            return Err(e);
                        }
                    }
                }
                "restart" => {
                    eprintln!(
                        "launch: {}; stopping this node's ranks for restart {n}",
                        msg["reason"].as_str().unwrap_or("restart")
                    );
                    stop_ranks(&mut ranks, FAILURE_GRACE.min(s.grace));
                    say(json!({"type": "ready", "attempt": n}))?;
                }
                "finish" => return Ok(()),
                "stop" => {
                    stop_ranks(&mut ranks, FAILURE_GRACE.min(s.grace));
                    bail!(
                        "launch: {}",
                        msg["reason"].as_str().unwrap_or("stopped by node 0")
                    );
                }
                other => {
                    stop_ranks(&mut ranks, FAILURE_GRACE.min(s.grace));
                    bail!("launch: unexpected message {other:?} from the agent store at {peer}");
                }
            }
        }
        if last_heard.elapsed() > s.heartbeat_timeout {
            stop_ranks(&mut ranks, FAILURE_GRACE.min(s.grace));
            bail!(
                "launch: node 0's agent store at {peer} sent nothing for {:.0} s",
                s.heartbeat_timeout.as_secs_f64()
            );
        }
        if let Some(r) = ranks.as_mut() {
            match r.poll()? {
                None => {}
                Some(Outcome::Finished) => {
                    ranks = None;
                    say(json!({"type": "done", "attempt": attempt}))?;
                }
                Some(Outcome::Failed(why)) => {
                    eprintln!("launch: {why}");
                    stop_ranks(&mut ranks, FAILURE_GRACE.min(s.grace));
                    say(json!({"type": "failed", "attempt": attempt, "reason": why}))?;
                }
            }
        }
    }
}
