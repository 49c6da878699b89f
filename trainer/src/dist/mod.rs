//! Collective communication for data-parallel training: the [`Collective`] interface with three back
//! ends ([`LocalCollective`] for one process, [`TcpCollective`] over TCP for CPU tests and debugging,
//! [`NcclCollective`] for GPUs), torchrun-style environment parsing, and the flat-buffer helpers of
//! the sharded optimizer ([`shard_range`], [`FlatBuffer`]).
//!
//! Every collective is blocking and bounded by the communicator's timeout: when a peer stops
//! responding or dies, the call returns an error naming the operation (and the ranks, where they can
//! be known) and the communicator refuses all later calls, so the process can exit cleanly.

mod env;
mod flat;
mod local;
mod nccl;
mod star;
mod tcp;

pub use env::{DistEnv, TIMEOUT_VAR};
pub use flat::{shard_range, FlatBuffer, Segment};
pub use local::LocalCollective;
pub use nccl::{ensure_torch_cuda_loaded, NcclCollective};
pub use tcp::TcpCollective;

use anyhow::{bail, Result};
use std::time::Duration;
use tch::{Kind, Tensor};

/// Timeout of every collective unless configured otherwise (torch's default for NCCL is 10 min;
/// 5 min is ample for one gradient bucket and short enough to free a stuck job quickly).
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(300);

/// Collective operations over the ranks of one job. All ranks must call the same operations in the
/// same order with tensors of the same dtype and size; a mismatch is reported as an error where the
/// back end can see it (the TCP back end always does).
///
/// Tensors may be non-contiguous and may require grad (they are written without recording
/// autograd history). Reductions accept floating-point tensors (f32, bf16, f16, f64) and, for
/// sums, integer tensors; gathers and broadcasts accept any of those dtypes and `Bool`/`Uint8`.
pub trait Collective: Send {
    fn rank(&self) -> usize;
    fn world_size(&self) -> usize;
    /// In place: every rank ends with the elementwise sum over ranks.
    fn all_reduce_sum(&mut self, tensor: &mut Tensor) -> Result<()>;
    /// In place: every rank ends with the elementwise mean over ranks (floating point only).
    fn all_reduce_mean(&mut self, tensor: &mut Tensor) -> Result<()>;
    /// `input` holds `world_size * n` elements (read flat); `output` (n elements) receives this
    /// rank's chunk `[rank * n, (rank + 1) * n)` of the elementwise sum over ranks.
    fn reduce_scatter_sum(&mut self, input: &Tensor, output: &mut Tensor) -> Result<()>;
    /// `output` holds `world_size * n` elements (written flat) and receives every rank's `input`
    /// (n elements) in rank order.
    fn all_gather(&mut self, input: &Tensor, output: &mut Tensor) -> Result<()>;
    /// In place: every rank ends with `root`'s tensor.
    fn broadcast(&mut self, tensor: &mut Tensor, root: usize) -> Result<()>;
    /// Returns once every rank has entered the barrier.
    fn barrier(&mut self) -> Result<()>;
    /// Starts summing `tensor` over the ranks in place: into `root`'s copy (the other ranks' copies
    /// keep their values), or into every rank's copy when `root` is `None`. It may return before the
    /// sum is complete (NCCL runs it on a side stream while later kernels run); the sum is ready
    /// for work issued after [`Collective::finish_started`] or after any other collective, and
    /// `tensor` must be neither written nor freed before then. The other back ends finish it here.
    fn start_reduce_sum(&mut self, tensor: &Tensor, root: Option<usize>) -> Result<()>;
    /// Orders all work issued from now on after the reductions started so far.
    fn finish_started(&mut self) -> Result<()> {
        Ok(())
    }
    /// Seconds spent in collectives since the last call: NCCL counts the time its kernels ran on
    /// the GPU (overlapped with computation or not, completed ones only), the TCP back end the
    /// host's wall time in them.
    fn take_collective_seconds(&mut self) -> f64 {
        0.0
    }
}

/// Which implementation [`init`] builds for a job of more than one process.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    Tcp,
    Nccl,
}

/// The collective for the process described by `env`: [`LocalCollective`] when the job has one
/// rank, else the chosen back end (NCCL on `cuda:LOCAL_RANK`).
pub fn init(backend: Backend, env: &DistEnv) -> Result<Box<dyn Collective>> {
    if env.world_size == 1 {
        return Ok(Box::new(LocalCollective::new()));
    }
    Ok(match backend {
        Backend::Tcp => Box::new(TcpCollective::from_dist_env(env)?),
        Backend::Nccl => Box::new(NcclCollective::from_dist_env(env)?),
    })
}

pub(crate) fn check_reducible(kind: Kind, mean: bool, op: &str) -> Result<()> {
    match kind {
        Kind::Float | Kind::Double | Kind::BFloat16 | Kind::Half => Ok(()),
        Kind::Int64 | Kind::Int | Kind::Int16 | Kind::Int8 | Kind::Uint8 if !mean => Ok(()),
        _ if mean => bail!("{op}: needs a floating-point tensor, got {kind:?}"),
        _ => bail!("{op}: unsupported dtype {kind:?}"),
    }
}

/// The shard length `n` of a reduce-scatter / all-gather, checked against the other tensor.
pub(crate) fn check_split(op: &str, full: &Tensor, shard: &Tensor, world: usize) -> Result<usize> {
    let (full_kind, shard_kind) = (full.f_kind()?, shard.f_kind()?);
    if full_kind != shard_kind {
        bail!("{op}: dtypes differ ({full_kind:?} full, {shard_kind:?} shard)");
    }
    if full.device() != shard.device() {
        bail!("{op}: devices differ ({:?} full, {:?} shard)", full.device(), shard.device());
    }
    let (n_full, n_shard) = (full.numel(), shard.numel());
    if n_shard.checked_mul(world) != Some(n_full) {
        bail!("{op}: the full tensor has {n_full} elements, expected world size {world} x shard {n_shard}");
    }
    Ok(n_shard)
}

pub(crate) fn check_root(op: &str, root: usize, world: usize) -> Result<()> {
    if root >= world {
        bail!("{op}: root {root} is not a rank of a world of {world}");
    }
    Ok(())
}
