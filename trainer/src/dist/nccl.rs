//! The GPU back end: NCCL through cudarc's bindings, on CUDA tensors owned by tch.
//!
//! Library. cudarc opens `libnccl.so` by that name, but libtorch has already loaded its own
//! `nvidia/nccl/lib/libnccl.so.2`, and two NCCLs in one process fail ("corrupted comm object").
//! The process must therefore start with a directory first on LD_LIBRARY_PATH whose `libnccl.so`
//! links to libtorch's `libnccl.so.2` (docs/architecture.md, Toolchain facts):
//! ```text
//! TL=$(python3 -c 'import torch,os;print(os.path.dirname(torch.__file__))')/lib
//! NL=$(python3 -c 'import nvidia;print(nvidia.__path__[0])')/nccl/lib
//! mkdir -p /tmp/nccl-link && ln -sf $NL/libnccl.so.2 /tmp/nccl-link/libnccl.so
//! export LD_LIBRARY_PATH=/tmp/nccl-link:$TL:$NL:$LD_LIBRARY_PATH NCCL_NVLS_ENABLE=0
//! ```
//! [`NcclCollective::new`] checks that only one NCCL is mapped and says so otherwise.
//!
//! Streams. tch has no stream API and never sets a current stream, so libtorch issues every kernel
//! and copy on CUDA's legacy default stream (handle 0; the wheels are not built with per-thread
//! default streams). The blocking collectives run on that same stream: they start after the
//! kernels that produced their inputs and finish before any later kernel reads their outputs, and
//! the caching allocator stays correct (it reuses a freed block in stream order, so tch cannot hand
//! memory NCCL is still reading to a new tensor). [`Collective::start_reduce_sum`] is the one
//! overlapping operation: it runs on a non-blocking side stream after an event recorded on the
//! legacy stream, so later kernels run while it communicates. Its tensor must outlive it (the
//! allocator cannot know the side stream reads it: tch has no `recordStream`), which the caller
//! promises; the legacy stream waits for the side stream before any later collective and at
//! [`Collective::finish_started`], so collectives on the communicator never run concurrently and
//! the results are in place before anything reads them.
//!
//! Completion and timeouts. The communicator is non-blocking (`config.blocking = 0`), so neither
//! initialisation nor a launch can hang inside NCCL. After a launch the host records an event on the
//! stream and polls it together with `ncclCommGetAsyncError` and the TCP star (the rendezvous
//! connections stay open: a peer whose process exits closes its socket at once, and every rank tells
//! rank 0 which collective it is entering). When a peer is gone, NCCL reports an error, or the
//! timeout passes, the communicator is aborted (`ncclCommAbort` stops the kernels), rank 0 forwards
//! its diagnosis to the other ranks, and every later call fails. Each collective returns only when
//! it is complete on this GPU, which also waits for the work queued before it.

use super::star::{Op, Replies, Star};
use super::{check_reducible, check_root, check_split, Collective, DistEnv};
use anyhow::{anyhow, bail, Context, Result};
use cudarc::driver::{result as cuda, sys as cuda_sys, CudaContext};
use cudarc::nccl::sys as nccl;
use nccl::ncclResult_t as Nr;
use std::ffi::{c_void, CStr};
use std::path::PathBuf;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};
use tch::{Device, Kind, Tensor};

const SETUP_HINT: &str = "start the process with a directory first on LD_LIBRARY_PATH whose libnccl.so links to the \
libnccl.so.2 that libtorch loads (docs/architecture.md, Toolchain facts: ln -sf $NL/libnccl.so.2 /tmp/nccl-link/libnccl.so; \
LD_LIBRARY_PATH=/tmp/nccl-link:$TL:$NL:...)";

const NCCL_SYMBOLS: [&str; 12] = [
    "ncclGetVersion",
    "ncclGetUniqueId",
    "ncclCommInitRankConfig",
    "ncclCommGetAsyncError",
    "ncclCommAbort",
    "ncclGetErrorString",
    "ncclGetLastError",
    "ncclAllReduce",
    "ncclReduceScatter",
    "ncclAllGather",
    "ncclBroadcast",
    "ncclReduce",
];

/// Files mapped into this process whose name starts with `prefix`, resolved and deduplicated.
fn mapped_libraries(prefix: &str) -> Vec<PathBuf> {
    let maps = std::fs::read_to_string("/proc/self/maps").unwrap_or_default();
    let mut found: Vec<PathBuf> = maps
        .lines()
        .filter_map(|line| line.split_whitespace().nth(5))
        .map(PathBuf::from)
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with(prefix)))
        .map(|p| p.canonicalize().unwrap_or(p))
        .collect();
    found.sort();
    found.dedup();
    found
}

/// Makes libtorch's CUDA backend available in a binary whose linker dropped `libtorch_cuda.so`
/// (crates without the `-Wl,--no-as-needed -ltorch_cuda` build script, such as this crate's test
/// binaries). libtorch decides once, at its first CUDA query, whether CUDA exists, so call this
/// before anything asks (`tch::Cuda::is_available`, `Device::cuda_if_available`, ...).
pub fn ensure_torch_cuda_loaded() -> Result<()> {
    static LOADED: OnceLock<Result<(), String>> = OnceLock::new();
    LOADED
        .get_or_init(|| {
            if !mapped_libraries("libtorch_cuda.so").is_empty() {
                return Ok(());
            }
            let beside_cpu = mapped_libraries("libtorch_cpu.so").first().and_then(|p| p.parent().map(|d| d.join("libtorch_cuda.so")));
            let mut last = String::from("libtorch_cpu.so is not loaded");
            for candidate in beside_cpu.into_iter().chain([PathBuf::from("libtorch_cuda.so")]) {
                use libloading::os::unix::{Library, RTLD_GLOBAL, RTLD_NOW};
                // SAFETY: libtorch_cuda's initialisers only register the CUDA backend with the
                // libtorch already loaded; the library is never unloaded.
                match unsafe { Library::open(Some(&candidate), RTLD_NOW | RTLD_GLOBAL) } {
                    Ok(lib) => {
                        std::mem::forget(lib);
                        return Ok(());
                    }
                    Err(e) => last = format!("{}: {e}", candidate.display()),
                }
            }
            Err(format!("cannot load libtorch_cuda.so ({last})"))
        })
        .clone()
        .map_err(|e| anyhow!(e))
}

/// Loads NCCL through cudarc and checks it is the one libtorch uses; returns its version code.
fn load_nccl() -> Result<i32> {
    // SAFETY: probing and opening a shared library by name; its initialisers are NCCL's.
    if !unsafe { nccl::is_culib_present() } {
        bail!("NCCL is not loadable by name libnccl.so: {SETUP_HINT}");
    }
    let lib = unsafe { nccl::culib() };
    for symbol in NCCL_SYMBOLS {
        // SAFETY: only the symbol's presence is checked; nothing is called.
        if unsafe { lib.get::<unsafe extern "C" fn()>(symbol) }.is_err() {
            bail!("the libnccl.so found lacks {symbol} (too old an NCCL?): {SETUP_HINT}");
        }
    }
    let loaded = mapped_libraries("libnccl.so");
    if loaded.len() > 1 {
        let list = loaded.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ");
        bail!("two NCCL libraries are loaded ({list}) and would corrupt each other's communicators: {SETUP_HINT}");
    }
    let mut version = 0;
    // SAFETY: writes one int.
    check(unsafe { nccl::ncclGetVersion(&mut version) }, "ncclGetVersion")?;
    Ok(version)
}

fn error_text(r: Nr) -> String {
    // SAFETY: NCCL returns a static NUL-terminated string for every code.
    let s = unsafe { nccl::ncclGetErrorString(r) };
    if s.is_null() {
        return format!("{r:?}");
    }
    format!("{r:?} ({})", unsafe { CStr::from_ptr(s) }.to_string_lossy())
}

fn check(r: Nr, what: &str) -> Result<()> {
    match r {
        Nr::ncclSuccess => Ok(()),
        e => bail!("{what}: {}", error_text(e)),
    }
}

fn reduce_type(kind: Kind) -> Option<nccl::ncclDataType_t> {
    use nccl::ncclDataType_t as T;
    Some(match kind {
        Kind::Float => T::ncclFloat32,
        Kind::BFloat16 => T::ncclBfloat16,
        Kind::Half => T::ncclFloat16,
        Kind::Double => T::ncclFloat64,
        Kind::Int64 => T::ncclInt64,
        Kind::Int => T::ncclInt32,
        Kind::Int8 => T::ncclInt8,
        Kind::Uint8 => T::ncclUint8,
        _ => return None,
    })
}

/// Checks the device and the library; returns NCCL's version code.
fn local_setup(device: usize) -> Result<i32> {
    if !tch::Cuda::is_available() {
        bail!("NCCL back end: libtorch sees no CUDA device");
    }
    let count = tch::Cuda::device_count();
    if device as i64 >= count {
        bail!("NCCL back end: cuda:{device} requested (LOCAL_RANK), {count} device(s) visible");
    }
    let version = load_nccl()?;
    // libtorch sets up its state and the device's primary context, which cudarc then binds.
    drop(Tensor::f_zeros([1], (Kind::Float, Device::Cuda(device)))?);
    Ok(version)
}

pub struct NcclCollective {
    rank: usize,
    world: usize,
    device: usize,
    /// Null once aborted.
    comm: nccl::ncclComm_t,
    star: Star,
    ctx: Arc<CudaContext>,
    done: cuda_sys::CUevent,
    /// Non-blocking stream of the started reductions, and the events ordering it with the legacy
    /// stream (`ready`: inputs written; `side_done`: reductions finished).
    side: cuda_sys::CUstream,
    ready: cuda_sys::CUevent,
    side_done: cuda_sys::CUevent,
    /// Reductions started on `side` that the legacy stream has not been ordered after yet.
    side_pending: bool,
    /// Timing events around each launched collective, not yet read; spare events.
    timers: Vec<(cuda_sys::CUevent, cuda_sys::CUevent)>,
    spare_timers: Vec<cuda_sys::CUevent>,
    /// GPU time of the collectives read from `timers`.
    collective_time: f64,
    seq: u64,
    broken: Option<String>,
}

// SAFETY: the communicator and event are used by one thread at a time (`&mut self`), and every call
// first binds the device's context to the calling thread.
unsafe impl Send for NcclCollective {}

impl NcclCollective {
    /// Joins the job through the TCP rendezvous at `master` ("host:port"), gets NCCL's unique id
    /// from rank 0 over it and builds the communicator on `cuda:{device}`. `timeout` bounds the
    /// rendezvous, the initialisation and every collective.
    pub fn new(rank: usize, world: usize, device: usize, master: &str, timeout: Duration) -> Result<Self> {
        ensure_torch_cuda_loaded()?;
        // Joined first, so that a rank that cannot set up tells the others at once.
        let mut star = Star::connect(rank, world, master, timeout)?;
        let version = match local_setup(device) {
            Ok(v) => v,
            Err(e) => return Err(star.fail(format!("rank {rank}: {e:#}"))),
        };
        let mut id = nccl::ncclUniqueId { internal: [0; 128] };
        let mine = if rank == 0 {
            // SAFETY: writes one ncclUniqueId.
            if let Err(e) = check(unsafe { nccl::ncclGetUniqueId(&mut id) }, "ncclGetUniqueId") {
                return Err(star.fail(format!("rank 0 could not create the NCCL id: {e:#}")));
            }
            id.internal.iter().map(|&c| c as u8).collect()
        } else {
            Vec::new()
        };
        let bytes = star.collective(Op::Broadcast, Kind::Uint8, 128, Some(0), mine, 128, |mut p| Ok(Replies::Same(std::mem::take(&mut p[0]))))?;
        for (dst, src) in id.internal.iter_mut().zip(&bytes) {
            *dst = *src as _;
        }
        let cuda_state = CudaContext::new(device).and_then(|ctx| {
            let event = || cuda::event::create(cuda_sys::CUevent_flags::CU_EVENT_DISABLE_TIMING);
            Ok((ctx, [event()?, event()?, event()?], cuda::stream::create(cuda::stream::StreamKind::NonBlocking)?))
        });
        let (ctx, [done, ready, side_done], side) = match cuda_state {
            Ok(s) => s,
            Err(e) => return Err(star.fail(format!("rank {rank}: setting up cuda:{device} failed: {e}"))),
        };
        let mut this = Self {
            rank,
            world,
            device,
            comm: std::ptr::null_mut(),
            star,
            ctx,
            done,
            side,
            ready,
            side_done,
            side_pending: false,
            timers: Vec::new(),
            spare_timers: Vec::new(),
            collective_time: 0.0,
            seq: 0,
            broken: None,
        };
        const UNDEF: i32 = i32::MIN;
        let mut config = nccl::ncclConfig_t {
            size: std::mem::size_of::<nccl::ncclConfig_t>(),
            magic: 0xcafe_beef,
            version: version as u32,
            blocking: 0,
            cgaClusterSize: UNDEF,
            minCTAs: UNDEF,
            maxCTAs: UNDEF,
            netName: std::ptr::null(),
            splitShare: UNDEF,
            trafficClass: UNDEF,
            commName: std::ptr::null(),
            collnetEnable: UNDEF,
            CTAPolicy: UNDEF,
            shrinkShare: UNDEF,
            nvlsCTAs: UNDEF,
            nChannelsPerNetPeer: UNDEF,
            nvlinkCentricSched: UNDEF,
            graphUsageMode: UNDEF,
            numRmaCtx: UNDEF,
            maxP2pPeers: UNDEF,
        };
        let what = format!("NCCL communicator init on rank {rank} (cuda:{device}, NCCL {version})");
        let start = Instant::now();
        // SAFETY: valid out-pointer and config; NCCL copies what its version knows of the config
        // (it reads `size` first), so a config newer than the library is accepted.
        let r = unsafe { nccl::ncclCommInitRankConfig(&mut this.comm, world as i32, id, rank as i32, &mut config) };
        if !matches!(r, Nr::ncclSuccess | Nr::ncclInProgress) {
            return Err(this.abort(format!("{what}: {}", error_text(r))));
        }
        let deadline = start + this.star.timeout();
        this.wait_until(&what, 0, start, deadline, Self::comm_ready)?;
        Ok(this)
    }

    /// From RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT and `BWM_DIST_TIMEOUT`.
    pub fn from_env() -> Result<Self> {
        Self::from_dist_env(&DistEnv::from_env()?)
    }

    pub fn from_dist_env(env: &DistEnv) -> Result<Self> {
        Self::new(env.rank, env.world_size, env.local_rank, &env.master(), env.timeout)
    }

    pub fn device(&self) -> Device {
        Device::Cuda(self.device)
    }

    pub fn timeout(&self) -> Duration {
        self.star.timeout()
    }

    pub fn set_timeout(&mut self, timeout: Duration) {
        self.star.set_timeout(timeout)
    }

    /// Aborts the communicator (if still alive), breaks the star with `msg` and returns it.
    fn abort(&mut self, msg: String) -> anyhow::Error {
        if !self.comm.is_null() {
            let _ = self.ctx.bind_to_thread();
            // SAFETY: a live communicator, never used again.
            let _ = unsafe { nccl::ncclCommAbort(self.comm) };
            self.comm = std::ptr::null_mut();
        }
        self.broken.get_or_insert_with(|| msg.clone());
        self.star.fail(msg)
    }

    fn comm_state(&self) -> Result<Nr, String> {
        let mut state = Nr::ncclSuccess;
        // SAFETY: live communicator (checked by the callers), one out-value.
        let r = unsafe { nccl::ncclCommGetAsyncError(self.comm, &mut state) };
        if r != Nr::ncclSuccess {
            return Err(format!("ncclCommGetAsyncError failed: {}", error_text(r)));
        }
        Ok(state)
    }

    fn comm_ready(&mut self) -> Result<bool, String> {
        match self.comm_state()? {
            Nr::ncclSuccess => Ok(true),
            Nr::ncclInProgress => Ok(false),
            e => Err(format!("NCCL reported {}", error_text(e))),
        }
    }

    fn launched_work_done(&mut self) -> Result<bool, String> {
        match self.comm_state()? {
            Nr::ncclSuccess | Nr::ncclInProgress => {}
            e => return Err(format!("NCCL reported {}", error_text(e))),
        }
        // SAFETY: an event created in `new`, recorded by `run`.
        match unsafe { cuda::event::query(self.done) } {
            Ok(()) => Ok(true),
            Err(e) if e.0 == cuda_sys::CUresult::CUDA_ERROR_NOT_READY => Ok(false),
            Err(e) => Err(format!("CUDA error while waiting: {e}")),
        }
    }

    /// Polls `ready` until it holds, watching the star and the deadline; aborts on any failure.
    fn wait_until(
        &mut self,
        what: &str,
        seq: u64,
        start: Instant,
        deadline: Instant,
        mut ready: impl FnMut(&mut Self) -> Result<bool, String>,
    ) -> Result<()> {
        let mut polls = 0u64;
        let mut next_watch = Instant::now();
        loop {
            match ready(self) {
                Ok(true) => return Ok(()),
                Ok(false) => {}
                Err(m) => {
                    let peers = self.star.poll().err().map(|p| format!(" ({p})")).unwrap_or_default();
                    return Err(self.abort(format!("{what}: {m}{peers}")));
                }
            }
            let now = Instant::now();
            if now >= next_watch {
                if let Err(m) = self.star.poll() {
                    return Err(self.abort(format!("{what}: {m}")));
                }
                next_watch = now + Duration::from_millis(20);
            }
            if now >= deadline {
                let _ = self.star.poll();
                let why = self.diagnose(seq);
                return Err(self.abort(format!("{what} did not complete within {:.1?}; {why}", start.elapsed())));
            }
            polls += 1;
            if polls < 2000 {
                std::thread::yield_now();
            } else {
                std::thread::sleep(Duration::from_micros(50));
            }
        }
    }

    fn diagnose(&self, seq: u64) -> String {
        if seq == 0 {
            return "a rank did not join NCCL's initialisation".into();
        }
        if self.rank != 0 {
            return "no peer is known to have exited, and rank 0, which names the ranks that did not start a collective, sent no \
                    diagnosis first, so rank 0 itself may not have started it"
                .into();
        }
        let behind = self.star.behind(seq);
        if behind.is_empty() {
            return "every rank started it, so NCCL itself is stuck (run with NCCL_DEBUG=WARN for details)".into();
        }
        let list = behind.iter().map(|(r, at)| format!("rank {r} (last at op #{at})")).collect::<Vec<_>>().join(", ");
        format!("{list} did not start it")
    }

    /// Checks the communicator, binds the device and tells rank 0 which collective this rank
    /// enters; returns the collective's description and number.
    fn begin(&mut self, op: Op, detail: &str) -> Result<(String, u64)> {
        let name = op.name();
        if let Some(m) = &self.broken {
            bail!("{name}: the NCCL communicator was aborted after an earlier failure: {m}");
        }
        self.ctx.bind_to_thread().with_context(|| format!("{name}: binding cuda:{}", self.device))?;
        self.seq += 1;
        let seq = self.seq;
        let what = format!("NCCL {name} (op #{seq}, {detail}) on rank {}", self.rank);
        if let Err(m) = self.star.announce(seq) {
            return Err(self.abort(format!("{what}: {m}")));
        }
        Ok((what, seq))
    }

    /// The deadline of a collective that starts now.
    fn deadline(&self, start: Instant) -> Instant {
        let budget = if self.rank == 0 { self.star.timeout().saturating_sub(self.star.margin()) } else { self.star.timeout() };
        start + budget
    }

    /// Enqueues one collective on `stream` between two timing events; returns when it started and
    /// its deadline.
    fn launch(
        &mut self,
        what: &str,
        seq: u64,
        stream: cuda_sys::CUstream,
        launch: impl FnOnce(nccl::ncclComm_t, nccl::cudaStream_t) -> Nr,
    ) -> Result<(Instant, Instant)> {
        let start = Instant::now();
        let deadline = self.deadline(start);
        if self.timers.len() >= 1024 {
            // Nobody is reading the times: keep the event count bounded.
            self.read_timers();
        }
        let timer = (self.timer_event(), self.timer_event());
        if let (Ok(begin), Ok(_)) = timer {
            // SAFETY: our event, recorded on a stream of this context. Timing is best effort.
            let _ = unsafe { cuda::event::record(begin, stream) };
        }
        let r = launch(self.comm, stream as nccl::cudaStream_t);
        if !matches!(r, Nr::ncclSuccess | Nr::ncclInProgress) {
            return Err(self.abort(format!("{what}: {}", error_text(r))));
        }
        // A non-blocking communicator may still be enqueuing; the events must follow the kernels.
        self.wait_until(what, seq, start, deadline, Self::comm_ready)?;
        match timer {
            // SAFETY: as above.
            (Ok(begin), Ok(end)) if unsafe { cuda::event::record(end, stream) }.is_ok() => self.timers.push((begin, end)),
            (a, b) => self.spare_timers.extend(a.into_iter().chain(b)),
        }
        Ok((start, deadline))
    }

    /// Adds the GPU time of the collectives that completed to `collective_time` (those still
    /// running are read later) and keeps their events for reuse.
    fn read_timers(&mut self) {
        if self.ctx.bind_to_thread().is_err() {
            return;
        }
        let mut running = Vec::new();
        for (begin, end) in std::mem::take(&mut self.timers) {
            // SAFETY: events created by this communicator, both recorded.
            match unsafe { cuda::event::query(end) } {
                Ok(()) => {
                    if let Ok(ms) = unsafe { cuda::event::elapsed(begin, end) } {
                        self.collective_time += ms as f64 / 1e3;
                    }
                    self.spare_timers.extend([begin, end]);
                }
                Err(_) => running.push((begin, end)),
            }
        }
        self.timers = running;
    }

    fn timer_event(&mut self) -> Result<cuda_sys::CUevent, cuda::DriverError> {
        match self.spare_timers.pop() {
            Some(e) => Ok(e),
            None => cuda::event::create(cuda_sys::CUevent_flags::CU_EVENT_DEFAULT),
        }
    }

    /// Makes the legacy stream wait for the reductions started on the side stream.
    fn join_side_stream(&mut self, what: &str) -> Result<()> {
        if !self.side_pending {
            return Ok(());
        }
        // SAFETY: our events and streams, alive for the communicator's life.
        let joined = unsafe {
            cuda::event::record(self.side_done, self.side)
                .and_then(|()| cuda::stream::wait_event(std::ptr::null_mut(), self.side_done, cuda_sys::CUevent_wait_flags::CU_EVENT_WAIT_DEFAULT))
        };
        if let Err(e) = joined {
            return Err(self.abort(format!("{what}: ordering the default stream after the started reductions failed: {e}")));
        }
        self.side_pending = false;
        Ok(())
    }

    /// Launches one collective on the legacy default stream and waits for it (see the module doc).
    fn run(&mut self, op: Op, detail: String, launch: impl FnOnce(nccl::ncclComm_t, nccl::cudaStream_t) -> Nr) -> Result<()> {
        let (what, seq) = self.begin(op, &detail)?;
        self.join_side_stream(&what)?;
        let (start, deadline) = self.launch(&what, seq, std::ptr::null_mut(), launch)?;
        // SAFETY: our event, recorded on the legacy default stream (null handle).
        if let Err(e) = unsafe { cuda::event::record(self.done, std::ptr::null_mut()) } {
            return Err(self.abort(format!("{what}: recording the completion event failed: {e}")));
        }
        self.wait_until(&what, seq, start, deadline, Self::launched_work_done)
    }

    fn check_device(&self, op: &str, t: &Tensor) -> Result<()> {
        if t.device() != Device::Cuda(self.device) {
            bail!("{op}: tensor on {:?}, the NCCL communicator is on cuda:{}", t.device(), self.device);
        }
        Ok(())
    }

    /// Runs `f` on a contiguous version of `t`, copying the result back when that was a copy.
    fn in_place(&mut self, t: &mut Tensor, f: impl FnOnce(&mut Self, &Tensor) -> Result<()>) -> Result<()> {
        if t.is_contiguous() {
            return f(self, t);
        }
        let c = t.f_contiguous()?;
        f(self, &c)?;
        tch::no_grad(|| t.f_copy_(&c))?;
        Ok(())
    }

    fn all_reduce(&mut self, tensor: &mut Tensor, op: Op) -> Result<()> {
        let (name, mean) = (op.name(), op == Op::AllReduceMean);
        let kind = tensor.f_kind()?;
        check_reducible(kind, mean, name)?;
        let dtype = reduce_type(kind).ok_or_else(|| anyhow!("{name}: NCCL cannot reduce {kind:?}"))?;
        self.check_device(name, tensor)?;
        let n = tensor.numel();
        if n == 0 {
            return Ok(());
        }
        let red = if mean { nccl::ncclRedOp_t::ncclAvg } else { nccl::ncclRedOp_t::ncclSum };
        self.in_place(tensor, |s, t| {
            let p = t.data_ptr();
            // SAFETY: `t` is a contiguous CUDA tensor of n elements of `dtype`, alive until `run` returns.
            s.run(op, format!("{n} x {kind:?}"), |comm, stream| unsafe { nccl::ncclAllReduce(p, p, n, dtype, red, comm, stream) })
        })
    }
}

impl Drop for NcclCollective {
    fn drop(&mut self) {
        let _ = self.ctx.bind_to_thread();
        if !self.comm.is_null() {
            // SAFETY: every collective completed before its call returned; abort only frees.
            let _ = unsafe { nccl::ncclCommAbort(self.comm) };
        }
        let timers = self.timers.drain(..).flat_map(|(a, b)| [a, b]);
        // SAFETY: created by this communicator, not used after this; destroying a stream or event
        // with work still queued releases it once the work completes.
        unsafe {
            for e in [self.done, self.ready, self.side_done].into_iter().chain(timers).chain(self.spare_timers.drain(..)) {
                let _ = cuda::event::destroy(e);
            }
            let _ = cuda::stream::destroy(self.side);
        }
    }
}

impl Collective for NcclCollective {
    fn rank(&self) -> usize {
        self.rank
    }

    fn world_size(&self) -> usize {
        self.world
    }

    fn all_reduce_sum(&mut self, tensor: &mut Tensor) -> Result<()> {
        self.all_reduce(tensor, Op::AllReduceSum)
    }

    fn all_reduce_mean(&mut self, tensor: &mut Tensor) -> Result<()> {
        self.all_reduce(tensor, Op::AllReduceMean)
    }

    fn reduce_scatter_sum(&mut self, input: &Tensor, output: &mut Tensor) -> Result<()> {
        let op = Op::ReduceScatterSum;
        let name = op.name();
        let n = check_split(name, input, output, self.world)?;
        let kind = input.f_kind()?;
        check_reducible(kind, false, name)?;
        let dtype = reduce_type(kind).ok_or_else(|| anyhow!("{name}: NCCL cannot reduce {kind:?}"))?;
        self.check_device(name, input)?;
        if n == 0 {
            return Ok(());
        }
        let input = input.f_contiguous()?;
        let src = input.data_ptr() as *const c_void;
        self.in_place(output, |s, out| {
            let dst = out.data_ptr();
            // SAFETY: contiguous CUDA tensors of world*n (input, alive in this scope) and n elements.
            s.run(op, format!("{n} x {kind:?} per rank"), |comm, stream| unsafe {
                nccl::ncclReduceScatter(src, dst, n, dtype, nccl::ncclRedOp_t::ncclSum, comm, stream)
            })
        })
    }

    fn all_gather(&mut self, input: &Tensor, output: &mut Tensor) -> Result<()> {
        let op = Op::AllGather;
        let name = op.name();
        let n = check_split(name, output, input, self.world)?;
        let kind = input.f_kind()?;
        self.check_device(name, input)?;
        let bytes = n * kind.elt_size_in_bytes();
        if bytes == 0 {
            return Ok(());
        }
        let input = input.f_contiguous()?;
        let src = input.data_ptr() as *const c_void;
        self.in_place(output, |s, out| {
            let dst = out.data_ptr();
            // SAFETY: contiguous CUDA buffers of `bytes` (input) and world*bytes (output).
            s.run(op, format!("{n} x {kind:?} per rank"), |comm, stream| unsafe {
                nccl::ncclAllGather(src, dst, bytes, nccl::ncclDataType_t::ncclUint8, comm, stream)
            })
        })
    }

    fn broadcast(&mut self, tensor: &mut Tensor, root: usize) -> Result<()> {
        let op = Op::Broadcast;
        let name = op.name();
        check_root(name, root, self.world)?;
        let kind = tensor.f_kind()?;
        self.check_device(name, tensor)?;
        let n = tensor.numel();
        let bytes = n * kind.elt_size_in_bytes();
        if bytes == 0 {
            return Ok(());
        }
        self.in_place(tensor, |s, t| {
            let p = t.data_ptr();
            // SAFETY: a contiguous CUDA buffer of `bytes`, alive until `run` returns.
            s.run(op, format!("{n} x {kind:?} from rank {root}"), |comm, stream| unsafe {
                nccl::ncclBroadcast(p, p, bytes, nccl::ncclDataType_t::ncclUint8, root as i32, comm, stream)
            })
        })
    }

    fn barrier(&mut self) -> Result<()> {
        let token = Tensor::f_zeros([1], (Kind::Float, Device::Cuda(self.device)))?;
        let p = token.data_ptr();
        // SAFETY: one f32 on the device, alive until `run` returns.
        self.run(Op::Barrier, "1 x Float".into(), |comm, stream| unsafe {
            nccl::ncclAllReduce(p, p, 1, nccl::ncclDataType_t::ncclFloat32, nccl::ncclRedOp_t::ncclSum, comm, stream)
        })
    }

    fn start_reduce_sum(&mut self, tensor: &Tensor, root: Option<usize>) -> Result<()> {
        let op = Op::ReduceSum;
        let name = op.name();
        if let Some(r) = root {
            check_root(name, r, self.world)?;
        }
        let kind = tensor.f_kind()?;
        check_reducible(kind, false, name)?;
        let dtype = reduce_type(kind).ok_or_else(|| anyhow!("{name}: NCCL cannot reduce {kind:?}"))?;
        self.check_device(name, tensor)?;
        if !tensor.is_contiguous() {
            bail!("{name}: the tensor must be contiguous (the sum is written in place after the call returns)");
        }
        let n = tensor.numel();
        if n == 0 {
            return Ok(());
        }
        let to = root.map_or("every rank".to_string(), |r| format!("rank {r}"));
        let (what, seq) = self.begin(op, &format!("{n} x {kind:?} to {to}"))?;
        // SAFETY: our events and streams; the side stream starts after the work queued so far on
        // the legacy stream, which wrote the tensor.
        let ordered = unsafe {
            cuda::event::record(self.ready, std::ptr::null_mut())
                .and_then(|()| cuda::stream::wait_event(self.side, self.ready, cuda_sys::CUevent_wait_flags::CU_EVENT_WAIT_DEFAULT))
        };
        if let Err(e) = ordered {
            return Err(self.abort(format!("{what}: ordering the side stream after the default stream failed: {e}")));
        }
        let p = tensor.data_ptr();
        let red = nccl::ncclRedOp_t::ncclSum;
        // SAFETY: a contiguous CUDA tensor of n elements of `dtype` that the caller keeps alive and
        // unwritten until the legacy stream is joined with the side stream.
        self.launch(&what, seq, self.side, |comm, stream| unsafe {
            match root {
                Some(r) => nccl::ncclReduce(p, p, n, dtype, red, r as i32, comm, stream),
                None => nccl::ncclAllReduce(p, p, n, dtype, red, comm, stream),
            }
        })?;
        self.side_pending = true;
        Ok(())
    }

    fn finish_started(&mut self) -> Result<()> {
        if self.side_pending {
            self.ctx.bind_to_thread().with_context(|| format!("binding cuda:{}", self.device))?;
        }
        self.join_side_stream("finishing the started reductions")
    }

    fn take_collective_seconds(&mut self) -> f64 {
        self.read_timers();
        std::mem::take(&mut self.collective_time)
    }
}
