//! The TCP star under the CPU back end and NCCL's rendezvous: rank 0 listens at
//! MASTER_ADDR:MASTER_PORT and every other rank keeps one connection to it. A collective is one
//! request from every rank to rank 0 and one reply back; rank 0 alone does the arithmetic, so every
//! rank receives the same bytes.
//!
//! Rank 0 stops collecting requests a little before the timeout (`margin`) so that its diagnosis
//! ("rank 2 did not join") reaches the waiting ranks before their own timeout fires. Any failure
//! breaks the star: rank 0 sends the message to every rank it can still reach, each side shuts its
//! sending half, and later calls fail at once.
//!
//! Written over std sockets rather than a crate: tch exposes neither c10d's TCPStore nor Gloo,
//! no maintained Rust crate speaks their protocols, and a general store (etcd, Redis clients) needs
//! a server the job does not have. What the trainer needs is small (join, a keyed exchange, and
//! rank 0's deterministic reduction in rank order) and its failure messages must name the rank.

use anyhow::{anyhow, bail, Context, Result};
use std::io::{self, Read, Write};
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, Shutdown, SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};
use tch::Kind;

const MAGIC: u32 = 0x424d_5743;
const PROTOCOL: u32 = 1;
const HELLO_LEN: usize = 16;
const REQUEST_LEN: usize = 34;
const REPLY_LEN: usize = 21;
const OK: u8 = 0;
const FAILED: u8 = 1;
const MAX_MESSAGE: u64 = 1 << 16;
const NO_ROOT: u32 = u32::MAX;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Op {
    AllReduceSum = 1,
    AllReduceMean = 2,
    ReduceScatterSum = 3,
    AllGather = 4,
    Broadcast = 5,
    Barrier = 6,
    /// A rank announcing (NCCL back end) the collective it is entering; never replied to.
    Progress = 7,
    /// A rank telling rank 0 why it gave up; the payload is the message. Never replied to.
    Abort = 8,
    ReduceSum = 9,
}

impl Op {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Op::AllReduceSum => "all_reduce_sum",
            Op::AllReduceMean => "all_reduce_mean",
            Op::ReduceScatterSum => "reduce_scatter_sum",
            Op::AllGather => "all_gather",
            Op::Broadcast => "broadcast",
            Op::Barrier => "barrier",
            Op::Progress => "progress",
            Op::Abort => "abort",
            Op::ReduceSum => "reduce_sum",
        }
    }

    fn from_code(code: u8) -> Option<Op> {
        [Op::AllReduceSum, Op::AllReduceMean, Op::ReduceScatterSum, Op::AllGather, Op::Broadcast, Op::Barrier, Op::Progress, Op::Abort, Op::ReduceSum]
            .into_iter()
            .find(|op| *op as u8 == code)
    }
}

const KINDS: [(Kind, u8); 10] = [
    (Kind::Uint8, 1),
    (Kind::Int8, 2),
    (Kind::Int16, 3),
    (Kind::Int, 4),
    (Kind::Int64, 5),
    (Kind::Half, 6),
    (Kind::Float, 7),
    (Kind::Double, 8),
    (Kind::Bool, 9),
    (Kind::BFloat16, 10),
];

fn kind_code(kind: Kind) -> Result<u8> {
    KINDS.iter().find(|(k, _)| *k == kind).map(|(_, c)| *c).ok_or_else(|| anyhow!("dtype {kind:?} is not supported by collectives"))
}

fn kind_name(code: u8) -> String {
    KINDS.iter().find(|(_, c)| *c == code).map_or_else(|| format!("dtype #{code}"), |(k, _)| format!("{k:?}"))
}

fn elt_size(code: u8) -> u64 {
    KINDS.iter().find(|(_, c)| *c == code).map_or(0, |(k, _)| k.elt_size_in_bytes() as u64)
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Request {
    seq: u64,
    op: u8,
    kind: u8,
    root: u32,
    numel: u64,
    len: u64,
}

impl Request {
    fn encode(&self) -> [u8; REQUEST_LEN] {
        let mut b = [0u8; REQUEST_LEN];
        b[0..4].copy_from_slice(&MAGIC.to_le_bytes());
        b[4..12].copy_from_slice(&self.seq.to_le_bytes());
        b[12] = self.op;
        b[13] = self.kind;
        b[14..18].copy_from_slice(&self.root.to_le_bytes());
        b[18..26].copy_from_slice(&self.numel.to_le_bytes());
        b[26..34].copy_from_slice(&self.len.to_le_bytes());
        b
    }

    fn decode(b: &[u8; REQUEST_LEN]) -> Option<Self> {
        (u32_at(b, 0) == MAGIC).then(|| Request {
            seq: u64_at(b, 4),
            op: b[12],
            kind: b[13],
            root: u32_at(b, 14),
            numel: u64_at(b, 18),
            len: u64_at(b, 26),
        })
    }

    fn describe(&self) -> String {
        let op = Op::from_code(self.op).map_or_else(|| format!("op code {}", self.op), |o| o.name().to_string());
        let root = if self.root == NO_ROOT { String::new() } else { format!(" from root {}", self.root) };
        format!("{op} of {} x {}{root} (op #{})", self.numel, kind_name(self.kind), self.seq)
    }

    fn same_call(&self, other: &Request) -> bool {
        (self.seq, self.op, self.kind, self.root, self.numel) == (other.seq, other.op, other.kind, other.root, other.numel)
    }
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[at..at + 4]);
    u32::from_le_bytes(a)
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(a)
}

fn reply_header(status: u8, seq: u64, len: u64) -> [u8; REPLY_LEN] {
    let mut b = [0u8; REPLY_LEN];
    b[0..4].copy_from_slice(&MAGIC.to_le_bytes());
    b[4] = status;
    b[5..13].copy_from_slice(&seq.to_le_bytes());
    b[13..21].copy_from_slice(&len.to_le_bytes());
    b
}

enum Fault {
    TimedOut,
    /// The peer's process is gone: end of stream, reset, broken pipe.
    Closed(String),
    Io(io::Error),
    Protocol(String),
    /// Rank 0 sent something (a failure message) before this rank finished sending its request.
    ReplyPending,
}

fn classify(e: io::Error) -> Fault {
    use io::ErrorKind::*;
    match e.kind() {
        WouldBlock | TimedOut => Fault::TimedOut,
        ConnectionReset | ConnectionAborted | BrokenPipe | UnexpectedEof | NotConnected => Fault::Closed(format!("dropped the connection ({e})")),
        _ => Fault::Io(e),
    }
}

fn left(deadline: Instant) -> Option<Duration> {
    deadline.checked_duration_since(Instant::now()).filter(|d| *d >= Duration::from_millis(1))
}

fn read_full(s: &mut TcpStream, buf: &mut [u8], deadline: Instant) -> Result<(), Fault> {
    let mut at = 0;
    while at < buf.len() {
        let Some(wait) = left(deadline) else { return Err(Fault::TimedOut) };
        s.set_read_timeout(Some(wait)).map_err(Fault::Io)?;
        match s.read(&mut buf[at..]) {
            Ok(0) => return Err(Fault::Closed("closed the connection".into())),
            Ok(n) => at += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => match classify(e) {
                Fault::TimedOut => {}
                f => return Err(f),
            },
        }
    }
    Ok(())
}

fn write_full(s: &mut TcpStream, buf: &[u8], deadline: Instant) -> Result<(), Fault> {
    let mut at = 0;
    while at < buf.len() {
        let Some(wait) = left(deadline) else { return Err(Fault::TimedOut) };
        s.set_write_timeout(Some(wait)).map_err(Fault::Io)?;
        match s.write(&buf[at..]) {
            Ok(0) => return Err(Fault::Closed("closed the connection".into())),
            Ok(n) => at += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => match classify(e) {
                Fault::TimedOut => {}
                f => return Err(f),
            },
        }
    }
    Ok(())
}

/// As [`write_full`], but gives up with [`Fault::ReplyPending`] when bytes arrive meanwhile: rank 0
/// only answers a request it has read in full, so those bytes are its failure message.
fn send_watching(s: &mut TcpStream, buf: &[u8], deadline: Instant) -> Result<(), Fault> {
    let mut at = 0;
    while at < buf.len() {
        let Some(wait) = left(deadline) else { return Err(Fault::TimedOut) };
        s.set_write_timeout(Some(wait.min(Duration::from_millis(100)))).map_err(Fault::Io)?;
        match s.write(&buf[at..]) {
            Ok(0) => return Err(Fault::Closed("closed the connection".into())),
            Ok(n) => at += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => match classify(e) {
                Fault::TimedOut => {
                    if matches!(peek_now(s, &mut [0u8]), Ok(n) if n > 0) {
                        return Err(Fault::ReplyPending);
                    }
                }
                f => return Err(f),
            },
        }
    }
    Ok(())
}

/// A rank's reason for giving up, if its [`Op::Abort`] note is waiting on `s` (rank 0's side).
fn abort_note(s: &mut TcpStream) -> Option<String> {
    let mut h = [0u8; REQUEST_LEN];
    if !matches!(peek_now(s, &mut h), Ok(REQUEST_LEN)) {
        return None;
    }
    let req = Request::decode(&h).filter(|r| r.op == Op::Abort as u8)?;
    read_full(s, &mut h, Instant::now() + Duration::from_secs(1)).ok()?;
    Some(read_message(s, req.len))
}

/// Rank 0's failure message if one is waiting on `s` (never blocks for long).
fn pending_failure(s: &mut TcpStream) -> Option<String> {
    let mut h = [0u8; REPLY_LEN];
    if !matches!(peek_now(s, &mut h), Ok(REPLY_LEN)) || u32_at(&h, 0) != MAGIC || h[4] != FAILED {
        return None;
    }
    read_full(s, &mut h, Instant::now() + Duration::from_secs(1)).ok()?;
    Some(read_message(s, u64_at(&h, 13)))
}

fn send_frame(s: &mut TcpStream, status: u8, seq: u64, body: &[u8], deadline: Instant) -> Result<(), Fault> {
    write_full(s, &reply_header(status, seq, body.len() as u64), deadline)?;
    write_full(s, body, deadline)
}

/// Bytes waiting on `s` without blocking: `Ok(0)` at end of stream, `Err(WouldBlock)` when none.
fn peek_now(s: &TcpStream, buf: &mut [u8]) -> io::Result<usize> {
    s.set_nonblocking(true)?;
    let r = s.peek(buf);
    s.set_nonblocking(false)?;
    r
}

fn resolve(master: &str) -> Result<Vec<SocketAddr>> {
    let addrs: Vec<SocketAddr> = master.to_socket_addrs().with_context(|| format!("cannot resolve the rendezvous address {master:?} (MASTER_ADDR:MASTER_PORT)"))?.collect();
    if addrs.is_empty() {
        bail!("the rendezvous address {master:?} resolves to no address");
    }
    Ok(addrs)
}

fn rank_list(ranks: &[usize]) -> String {
    ranks.iter().map(|r| r.to_string()).collect::<Vec<_>>().join(", ")
}

pub(crate) enum Replies {
    /// The same bytes to every rank.
    Same(Vec<u8>),
    /// Rank r gets element r.
    PerRank(Vec<Vec<u8>>),
}

struct Link {
    rank: usize,
    stream: TcpStream,
    /// Last collective this peer announced (NCCL back end, rank 0 only).
    reached: u64,
}

pub(crate) struct Star {
    rank: usize,
    world: usize,
    timeout: Duration,
    /// Rank 0: ranks 1..world in order. Other ranks: rank 0.
    links: Vec<Link>,
    seq: u64,
    /// A request is partly written to rank 0, so nothing else may be written after it.
    sending: bool,
    broken: Option<String>,
    /// Wall time spent in [`Star::collective`] since the last [`Star::take_busy`].
    busy: Duration,
}

impl Star {
    /// Rendezvous at `master` ("host:port"): rank 0 listens on that port on every interface (a
    /// host name may resolve differently on other nodes), the others connect, retrying until
    /// `timeout`.
    pub(crate) fn connect(rank: usize, world: usize, master: &str, timeout: Duration) -> Result<Star> {
        if world == 0 || rank >= world {
            bail!("rank {rank} is not a rank of a world of {world}");
        }
        if timeout < Duration::from_millis(10) {
            bail!("collective timeout {timeout:?} is too short");
        }
        let deadline = Instant::now() + timeout;
        let links = match (world, rank) {
            (1, _) => Vec::new(),
            (_, 0) => accept_all(world, master, timeout, deadline)?,
            _ => vec![join(rank, world, master, timeout, deadline)?],
        };
        Ok(Star { rank, world, timeout, links, seq: 0, sending: false, broken: None, busy: Duration::ZERO })
    }

    pub(crate) fn rank(&self) -> usize {
        self.rank
    }

    pub(crate) fn world(&self) -> usize {
        self.world
    }

    pub(crate) fn timeout(&self) -> Duration {
        self.timeout
    }

    pub(crate) fn set_timeout(&mut self, timeout: Duration) {
        self.timeout = timeout.max(Duration::from_millis(10));
    }

    /// How much earlier than the others rank 0 gives up waiting, so its diagnosis arrives first.
    pub(crate) fn margin(&self) -> Duration {
        (self.timeout / 10).min(Duration::from_secs(2))
    }

    pub(crate) fn usable(&self, what: &str) -> Result<()> {
        match &self.broken {
            Some(m) => bail!("{what}: the communicator failed earlier and cannot be used: {m}"),
            None => Ok(()),
        }
    }

    /// Breaks the star with `msg`: rank 0 forwards it to every rank it can reach, another rank
    /// tells rank 0 (unless it is cut off in the middle of a request).
    pub(crate) fn fail(&mut self, msg: String) -> anyhow::Error {
        if self.broken.is_none() {
            let until = Instant::now() + Duration::from_secs(1);
            for link in &mut self.links {
                if self.rank == 0 {
                    let _ = send_frame(&mut link.stream, FAILED, self.seq, msg.as_bytes(), until);
                } else if !self.sending {
                    let note = Request { seq: self.seq, op: Op::Abort as u8, kind: 0, root: NO_ROOT, numel: 0, len: msg.len() as u64 };
                    let _ = write_full(&mut link.stream, &note.encode(), until).and_then(|()| write_full(&mut link.stream, msg.as_bytes(), until));
                }
                let _ = link.stream.shutdown(Shutdown::Write);
            }
            self.broken = Some(msg.clone());
        }
        anyhow!(msg)
    }

    /// One collective: `payload` from this rank; rank 0 turns all payloads (in rank order) into
    /// the replies with `combine`. Returns this rank's reply, which must be `reply_len` bytes.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn collective(
        &mut self,
        op: Op,
        kind: Kind,
        numel: usize,
        root: Option<usize>,
        payload: Vec<u8>,
        reply_len: usize,
        combine: impl FnOnce(Vec<Vec<u8>>) -> Result<Replies>,
    ) -> Result<Vec<u8>> {
        self.usable(op.name())?;
        let kind = kind_code(kind).with_context(|| op.name())?;
        self.seq += 1;
        let request = Request {
            seq: self.seq,
            op: op as u8,
            kind,
            root: root.map_or(NO_ROOT, |r| r as u32),
            numel: numel as u64,
            len: payload.len() as u64,
        };
        let start = Instant::now();
        let out = if self.rank == 0 {
            self.coordinate(op, request, payload, reply_len, combine)
        } else {
            self.participate(op, request, payload, reply_len)
        };
        self.busy += start.elapsed();
        out
    }

    /// Wall time spent in collectives since the last call.
    pub(crate) fn take_busy(&mut self) -> Duration {
        std::mem::take(&mut self.busy)
    }

    fn expected_len(request: &Request, rank: usize) -> u64 {
        let bytes = request.numel.saturating_mul(elt_size(request.kind));
        match Op::from_code(request.op) {
            Some(Op::Broadcast) if request.root as usize == rank => bytes,
            Some(Op::Broadcast | Op::Barrier | Op::Progress | Op::Abort) => 0,
            _ => bytes,
        }
    }

    fn coordinate(
        &mut self,
        op: Op,
        mine: Request,
        payload: Vec<u8>,
        reply_len: usize,
        combine: impl FnOnce(Vec<Vec<u8>>) -> Result<Replies>,
    ) -> Result<Vec<u8>> {
        let (name, seq) = (op.name(), mine.seq);
        let start = Instant::now();
        let gather_deadline = start + self.timeout.saturating_sub(self.margin());
        let mut payloads = Vec::with_capacity(self.world);
        payloads.push(payload);
        let mut missing = Vec::new();
        for i in 0..self.links.len() {
            let r = self.links[i].rank;
            if !missing.is_empty() {
                if !matches!(peek_now(&self.links[i].stream, &mut [0u8]), Ok(n) if n > 0) {
                    missing.push(r);
                }
                continue;
            }
            match self.receive_request(i, &mine, Self::expected_len(&mine, r), gather_deadline) {
                Ok(p) => payloads.push(p),
                Err(Fault::TimedOut) => missing.push(r),
                Err(Fault::Closed(why)) => {
                    return Err(self.fail(format!("{name} (op #{seq}): rank {r} {why}; its process probably exited")))
                }
                Err(Fault::Io(e)) => return Err(self.fail(format!("{name} (op #{seq}): the connection to rank {r} failed: {e}"))),
                Err(Fault::Protocol(m)) => return Err(self.fail(m)),
                Err(Fault::ReplyPending) => return Err(self.fail(format!("{name} (op #{seq}): unexpected message from rank {r}"))),
            }
        }
        if !missing.is_empty() {
            return Err(self.fail(format!(
                "{name} (op #{seq}) timed out after {:.1?}: rank(s) {} did not join (the other ranks did)",
                start.elapsed(),
                rank_list(&missing)
            )));
        }
        for i in 0..self.links.len() {
            if let Some(why) = abort_note(&mut self.links[i].stream) {
                let r = self.links[i].rank;
                return Err(self.fail(format!("{name} (op #{seq}): rank {r} failed: {why}")));
            }
        }
        let replies = match combine(payloads) {
            Ok(r) => r,
            Err(e) => return Err(self.fail(format!("{name} (op #{seq}) failed on rank 0: {e:#}"))),
        };
        let send_deadline = (start + self.timeout).max(Instant::now() + self.margin());
        let mut own = Vec::new();
        let mut per_rank = match replies {
            Replies::Same(b) => {
                own = b;
                None
            }
            Replies::PerRank(v) if v.len() == self.world => Some(v),
            Replies::PerRank(v) => {
                return Err(self.fail(format!("{name} (op #{seq}): rank 0 produced {} replies for {} ranks", v.len(), self.world)))
            }
        };
        if let Some(v) = &mut per_rank {
            own = std::mem::take(&mut v[0]);
        }
        for i in 0..self.links.len() {
            let r = self.links[i].rank;
            let body: &[u8] = match &per_rank {
                Some(v) => &v[r],
                None => &own,
            };
            match send_frame(&mut self.links[i].stream, OK, seq, body, send_deadline) {
                Ok(()) => {}
                Err(Fault::TimedOut) => {
                    return Err(self.fail(format!("{name} (op #{seq}): sending the result to rank {r} timed out; rank {r} is not reading")))
                }
                Err(Fault::Closed(why)) => {
                    return Err(self.fail(format!("{name} (op #{seq}): rank {r} {why}; its process probably exited")))
                }
                Err(Fault::Io(e)) => return Err(self.fail(format!("{name} (op #{seq}): the connection to rank {r} failed: {e}"))),
                Err(Fault::Protocol(m)) => return Err(self.fail(m)),
                Err(Fault::ReplyPending) => return Err(self.fail(format!("{name} (op #{seq}): unexpected message from rank {r}"))),
            }
        }
        if own.len() != reply_len {
            bail!("{name} (op #{seq}): internal error: result of {} bytes, expected {reply_len}", own.len());
        }
        Ok(own)
    }

    fn receive_request(&mut self, i: usize, mine: &Request, expected_len: u64, deadline: Instant) -> Result<Vec<u8>, Fault> {
        let link = &mut self.links[i];
        loop {
            let mut h = [0u8; REQUEST_LEN];
            read_full(&mut link.stream, &mut h, deadline)?;
            let Some(req) = Request::decode(&h) else {
                return Err(Fault::Protocol(format!("{} (op #{}): rank {} sent a malformed message", Op::from_code(mine.op).map_or("collective", Op::name), mine.seq, link.rank)));
            };
            if req.op == Op::Progress as u8 {
                link.reached = link.reached.max(req.seq);
                continue;
            }
            if req.op == Op::Abort as u8 {
                let why = read_message(&mut link.stream, req.len);
                return Err(Fault::Protocol(format!("{}: rank {} failed: {why}", mine.describe(), link.rank)));
            }
            if !req.same_call(mine) {
                return Err(Fault::Protocol(format!(
                    "collective mismatch: rank 0 called {} but rank {} called {}",
                    mine.describe(),
                    link.rank,
                    req.describe()
                )));
            }
            if req.len != expected_len {
                return Err(Fault::Protocol(format!(
                    "{}: rank {} sent {} bytes, expected {expected_len}",
                    mine.describe(),
                    link.rank,
                    req.len
                )));
            }
            let mut p = vec![0u8; req.len as usize];
            read_full(&mut link.stream, &mut p, deadline)?;
            return Ok(p);
        }
    }

    fn participate(&mut self, op: Op, mine: Request, payload: Vec<u8>, reply_len: usize) -> Result<Vec<u8>> {
        let (name, seq, rank, timeout, margin) = (op.name(), mine.seq, self.rank, self.timeout, self.margin());
        let start = Instant::now();
        let deadline = start + timeout;
        let stream = &mut self.links[0].stream;
        self.sending = true;
        let sent = send_watching(stream, &mine.encode(), deadline).and_then(|()| send_watching(stream, &payload, deadline));
        self.sending = sent.is_err();
        let sent = match sent {
            Err(Fault::ReplyPending) => Ok(()),
            Err(f) => match pending_failure(stream) {
                Some(msg) => return Err(self.fail(format!("{name} (op #{seq}) failed on rank {rank}; rank 0 reports: {msg}"))),
                None => Err(f),
            },
            ok => ok,
        };
        let mut header = [0u8; REPLY_LEN];
        let got = sent.and_then(|()| read_full(stream, &mut header, deadline));
        match got {
            Ok(()) => {}
            Err(Fault::ReplyPending) => return Err(self.fail(format!("{name} (op #{seq}) on rank {rank}: unexpected message from rank 0"))),
            Err(Fault::TimedOut) => {
                return Err(self.fail(format!(
                    "{name} (op #{seq}) timed out after {:.1?} on rank {rank}: no reply from rank 0 (rank 0, or a rank it waits for, is not responding)",
                    start.elapsed()
                )))
            }
            Err(Fault::Closed(why)) => {
                return Err(self.fail(format!("{name} (op #{seq}) on rank {rank}: rank 0 {why}; its process probably exited")))
            }
            Err(Fault::Io(e)) => return Err(self.fail(format!("{name} (op #{seq}) on rank {rank}: the connection to rank 0 failed: {e}"))),
            Err(Fault::Protocol(m)) => return Err(self.fail(m)),
        }
        let (status, reply_seq, len) = (header[4], u64_at(&header, 5), u64_at(&header, 13));
        if u32_at(&header, 0) != MAGIC {
            return Err(self.fail(format!("{name} (op #{seq}) on rank {rank}: malformed reply from rank 0")));
        }
        if status != OK {
            let msg = read_message(stream, len);
            return Err(self.fail(format!("{name} (op #{seq}) failed on rank {rank}; rank 0 reports: {msg}")));
        }
        if reply_seq != seq || len != reply_len as u64 {
            return Err(self.fail(format!(
                "{name} (op #{seq}) on rank {rank}: rank 0 replied to op #{reply_seq} with {len} bytes, expected {reply_len}"
            )));
        }
        let mut out = vec![0u8; reply_len];
        match read_full(stream, &mut out, deadline.max(Instant::now() + margin)) {
            Ok(()) => Ok(out),
            Err(Fault::TimedOut) => Err(self.fail(format!("{name} (op #{seq}) on rank {rank}: the reply from rank 0 stalled"))),
            Err(Fault::Closed(why)) => Err(self.fail(format!("{name} (op #{seq}) on rank {rank}: rank 0 {why}; its process probably exited"))),
            Err(Fault::Io(e)) => Err(self.fail(format!("{name} (op #{seq}) on rank {rank}: the connection to rank 0 failed: {e}"))),
            Err(Fault::Protocol(m)) => Err(self.fail(m)),
            Err(Fault::ReplyPending) => Err(self.fail(format!("{name} (op #{seq}) on rank {rank}: unexpected message from rank 0"))),
        }
    }

    /// Non-blocking health check while a collective runs elsewhere (NCCL): on rank 0, records the
    /// peers' announcements and reports a peer whose connection closed; on the others, reports
    /// rank 0's failure message or its closed connection. `Err` carries the diagnosis.
    pub(crate) fn poll(&mut self) -> Result<(), String> {
        if let Some(m) = &self.broken {
            return Err(m.clone());
        }
        if self.rank == 0 {
            for link in &mut self.links {
                loop {
                    let mut h = [0u8; REQUEST_LEN];
                    match peek_now(&link.stream, &mut h) {
                        Ok(0) => return Err(format!("rank {} closed its connection; its process probably exited", link.rank)),
                        Ok(n) if n == REQUEST_LEN => {
                            let until = Instant::now() + Duration::from_secs(1);
                            if read_full(&mut link.stream, &mut h, until).is_err() {
                                return Err(format!("rank {} dropped its connection", link.rank));
                            }
                            match Request::decode(&h) {
                                Some(req) if req.op == Op::Progress as u8 => link.reached = link.reached.max(req.seq),
                                Some(req) if req.op == Op::Abort as u8 => {
                                    return Err(format!("rank {} failed: {}", link.rank, read_message(&mut link.stream, req.len)))
                                }
                                _ => return Err(format!("rank {} sent an unexpected message", link.rank)),
                            }
                        }
                        Ok(_) => break,
                        Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                        Err(e) => return Err(format!("the connection to rank {} failed: {e}", link.rank)),
                    }
                }
            }
            Ok(())
        } else {
            let Some(link) = self.links.first_mut() else { return Ok(()) };
            if let Some(msg) = pending_failure(&mut link.stream) {
                return Err(format!("rank 0 reports: {msg}"));
            }
            let mut h = [0u8; REPLY_LEN];
            match peek_now(&link.stream, &mut h) {
                Ok(0) => Err("rank 0 closed its connection; its process probably exited".into()),
                Ok(n) if n == REPLY_LEN => Err("rank 0 sent an unexpected message".into()),
                Ok(_) => Ok(()),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => Ok(()),
                Err(e) => Err(format!("the connection to rank 0 failed: {e}")),
            }
        }
    }

    /// Tells rank 0 that this rank is entering collective number `seq` (NCCL back end).
    pub(crate) fn announce(&mut self, seq: u64) -> Result<(), String> {
        if self.rank == 0 || self.broken.is_some() {
            return Ok(());
        }
        let Some(link) = self.links.first_mut() else { return Ok(()) };
        let msg = Request { seq, op: Op::Progress as u8, kind: 0, root: NO_ROOT, numel: 0, len: 0 };
        write_full(&mut link.stream, &msg.encode(), Instant::now() + Duration::from_secs(1))
            .map_err(|_| "cannot reach rank 0; its process probably exited".to_string())
    }

    /// Rank 0: the peers whose last announced collective is before `seq`, with that number.
    pub(crate) fn behind(&self, seq: u64) -> Vec<(usize, u64)> {
        self.links.iter().filter(|l| l.reached < seq).map(|l| (l.rank, l.reached)).collect()
    }
}

impl Drop for Star {
    /// Closing a socket with unread bytes makes the kernel reset the connection, which can discard
    /// a failure message the peer has not read yet; so drain what has arrived first.
    fn drop(&mut self) {
        let mut scratch = vec![0u8; 1 << 16];
        for link in &mut self.links {
            if link.stream.set_nonblocking(true).is_err() {
                continue;
            }
            let mut drained = 0usize;
            while drained < 1 << 28 {
                match link.stream.read(&mut scratch) {
                    Ok(n) if n > 0 => drained += n,
                    _ => break,
                }
            }
        }
    }
}

fn read_message(s: &mut TcpStream, len: u64) -> String {
    let mut body = vec![0u8; len.min(MAX_MESSAGE) as usize];
    match read_full(s, &mut body, Instant::now() + Duration::from_secs(1)) {
        Ok(()) => String::from_utf8_lossy(&body).into_owned(),
        Err(_) => "(the message was cut off)".into(),
    }
}

fn hello(rank: usize, world: usize) -> [u8; HELLO_LEN] {
    let mut b = [0u8; HELLO_LEN];
    b[0..4].copy_from_slice(&MAGIC.to_le_bytes());
    b[4..8].copy_from_slice(&PROTOCOL.to_le_bytes());
    b[8..12].copy_from_slice(&(rank as u32).to_le_bytes());
    b[12..16].copy_from_slice(&(world as u32).to_le_bytes());
    b
}

fn accept_all(world: usize, master: &str, timeout: Duration, deadline: Instant) -> Result<Vec<Link>> {
    let first = resolve(master)?[0];
    let any = match first.ip() {
        IpAddr::V4(_) => IpAddr::V4(Ipv4Addr::UNSPECIFIED),
        IpAddr::V6(_) => IpAddr::V6(Ipv6Addr::UNSPECIFIED),
    };
    let listener = TcpListener::bind(SocketAddr::new(any, first.port()))
        .with_context(|| format!("rank 0 cannot listen on port {} (MASTER_PORT)", first.port()))?;
    listener.set_nonblocking(true)?;
    let mut slots: Vec<Option<TcpStream>> = (1..world).map(|_| None).collect();
    let joined = accept_loop(&listener, &mut slots, world, master, timeout, deadline);
    let until = Instant::now() + Duration::from_secs(1);
    if let Err(e) = joined {
        for s in slots.iter_mut().flatten() {
            let _ = send_frame(s, FAILED, 0, format!("rendezvous failed on rank 0: {e:#}").as_bytes(), until);
            let _ = s.shutdown(Shutdown::Write);
        }
        return Err(e);
    }
    let mut links = Vec::with_capacity(world - 1);
    for (i, s) in slots.into_iter().enumerate() {
        let Some(mut stream) = s else { bail!("rendezvous: rank {} is missing", i + 1) };
        if send_frame(&mut stream, OK, 0, &[], deadline.max(until)).is_err() {
            bail!("rendezvous: rank {} dropped its connection before the job started", i + 1);
        }
        links.push(Link { rank: i + 1, stream, reached: 0 });
    }
    Ok(links)
}

fn accept_loop(
    listener: &TcpListener,
    slots: &mut [Option<TcpStream>],
    world: usize,
    master: &str,
    timeout: Duration,
    deadline: Instant,
) -> Result<()> {
    let refuse = |s: &mut TcpStream, msg: &str| {
        let _ = send_frame(s, FAILED, 0, msg.as_bytes(), Instant::now() + Duration::from_secs(1));
    };
    while slots.iter().any(Option::is_none) {
        match listener.accept() {
            Ok((mut s, from)) => {
                s.set_nonblocking(false)?;
                s.set_nodelay(true)?;
                let mut b = [0u8; HELLO_LEN];
                if read_full(&mut s, &mut b, deadline.min(Instant::now() + Duration::from_secs(5))).is_err() || u32_at(&b, 0) != MAGIC {
                    continue;
                }
                let (protocol, r, w) = (u32_at(&b, 4), u32_at(&b, 8) as usize, u32_at(&b, 12) as usize);
                let problem = if protocol != PROTOCOL {
                    Some(format!("a process at {from} speaks protocol {protocol}, rank 0 speaks {PROTOCOL} (mixed builds?)"))
                } else if w != world {
                    Some(format!("rank {r} at {from} was started with WORLD_SIZE={w}, rank 0 with {world}"))
                } else if r == 0 || r >= world {
                    Some(format!("a process at {from} joined as rank {r}, which is not in 1..{world}"))
                } else if slots[r - 1].is_some() {
                    Some(format!("rank {r} joined twice (again from {from})"))
                } else {
                    None
                };
                if let Some(p) = problem {
                    refuse(&mut s, &p);
                    bail!("rendezvous: {p}");
                }
                slots[r - 1] = Some(s);
            }
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                if Instant::now() >= deadline {
                    let missing: Vec<usize> = slots.iter().enumerate().filter(|(_, s)| s.is_none()).map(|(i, _)| i + 1).collect();
                    bail!("rendezvous at {master} timed out after {timeout:?}: rank(s) {} did not connect", rank_list(&missing));
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e).context("rendezvous: accepting a connection failed"),
        }
    }
    Ok(())
}

fn join(rank: usize, world: usize, master: &str, timeout: Duration, deadline: Instant) -> Result<Link> {
    let mut last = String::from("no attempt");
    let mut stream = 'found: loop {
        if Instant::now() >= deadline {
            bail!("rank {rank} could not reach rank 0 at {master} within {timeout:?} ({last})");
        }
        match resolve(master) {
            Err(e) => last = format!("{e:#}"),
            Ok(addrs) => {
                for addr in addrs {
                    let wait = left(deadline).unwrap_or(Duration::from_millis(1)).min(Duration::from_secs(2));
                    match TcpStream::connect_timeout(&addr, wait) {
                        Ok(s) => break 'found s,
                        Err(e) => last = e.to_string(),
                    }
                }
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    stream.set_nodelay(true)?;
    let mut header = [0u8; REPLY_LEN];
    let r = write_full(&mut stream, &hello(rank, world), deadline).and_then(|()| read_full(&mut stream, &mut header, deadline));
    match r {
        Ok(()) if u32_at(&header, 0) != MAGIC => bail!("rank {rank}: the process at {master} is not a rank 0 of this job"),
        Ok(()) if header[4] == OK => Ok(Link { rank: 0, stream, reached: 0 }),
        Ok(()) => bail!("rank {rank}: rank 0 refused to start: {}", read_message(&mut stream, u64_at(&header, 13))),
        Err(Fault::TimedOut) => bail!("rank {rank}: rendezvous at {master} timed out after {timeout:?} (rank 0 waits for other ranks)"),
        Err(Fault::Closed(why)) => bail!("rank {rank}: rank 0 at {master} {why} during the rendezvous"),
        Err(Fault::Io(e)) => bail!("rank {rank}: rendezvous at {master} failed: {e}"),
        Err(Fault::Protocol(m)) => bail!("rank {rank}: {m}"),
        Err(Fault::ReplyPending) => bail!("rank {rank}: unexpected message from rank 0 during the rendezvous"),
    }
}
