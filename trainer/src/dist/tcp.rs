//! The CPU back end (Gloo's role): collectives through the TCP star, arithmetic on rank 0.
//!
//! Determinism: rank 0 reduces elementwise in rank order, `((x0 + x1) + x2) + ...`, in f32 for
//! f32/bf16/f16 (bf16 and f16 are rounded once at the end) and in f64 for f64, divides by the world
//! size for a mean, and sends the same bytes to every rank. So two ranks give exactly `a + b`, every
//! rank holds bit-identical results, and a rerun gives the same bits. CUDA tensors are copied
//! through host memory (slow, for debugging only).

use super::star::{Op, Replies, Star};
use super::{check_reducible, check_root, check_split, Collective, DistEnv};
use anyhow::{bail, Result};
use half::{bf16, f16};
use std::time::Duration;
use tch::{Device, Kind, Tensor};

pub struct TcpCollective {
    star: Star,
}

impl TcpCollective {
    /// Joins the job of `world` ranks whose rank 0 listens at `master` ("host:port"); rank 0 binds
    /// that port. Returns once every rank has joined, or fails after `timeout`, which also bounds
    /// every later collective.
    pub fn new(rank: usize, world: usize, master: &str, timeout: Duration) -> Result<Self> {
        Ok(Self { star: Star::connect(rank, world, master, timeout)? })
    }

    /// From RANK, WORLD_SIZE, MASTER_ADDR, MASTER_PORT and `BWM_DIST_TIMEOUT` (see [`DistEnv`]).
    pub fn from_env() -> Result<Self> {
        Self::from_dist_env(&DistEnv::from_env()?)
    }

    pub fn from_dist_env(env: &DistEnv) -> Result<Self> {
        Self::new(env.rank, env.world_size, &env.master(), env.timeout)
    }

    pub fn timeout(&self) -> Duration {
        self.star.timeout()
    }

    pub fn set_timeout(&mut self, timeout: Duration) {
        self.star.set_timeout(timeout)
    }

    fn all_reduce(&mut self, tensor: &mut Tensor, op: Op) -> Result<()> {
        let mean = op == Op::AllReduceMean;
        let kind = tensor.f_kind()?;
        check_reducible(kind, mean, op.name())?;
        let bytes = tensor_bytes(tensor)?;
        let len = bytes.len();
        let out = self.star.collective(op, kind, tensor.numel(), None, bytes, len, |p| Ok(Replies::Same(reduce(&p, kind, mean)?)))?;
        write_bytes(tensor, &out)
    }
}

impl Collective for TcpCollective {
    fn rank(&self) -> usize {
        self.star.rank()
    }

    fn world_size(&self) -> usize {
        self.star.world()
    }

    fn all_reduce_sum(&mut self, tensor: &mut Tensor) -> Result<()> {
        self.all_reduce(tensor, Op::AllReduceSum)
    }

    fn all_reduce_mean(&mut self, tensor: &mut Tensor) -> Result<()> {
        self.all_reduce(tensor, Op::AllReduceMean)
    }

    fn reduce_scatter_sum(&mut self, input: &Tensor, output: &mut Tensor) -> Result<()> {
        let op = Op::ReduceScatterSum;
        let world = self.world_size();
        let n = check_split(op.name(), input, output, world)?;
        let kind = input.f_kind()?;
        check_reducible(kind, false, op.name())?;
        let chunk = n * kind.elt_size_in_bytes();
        let out = self.star.collective(op, kind, input.numel(), None, tensor_bytes(input)?, chunk, |p| {
            let sum = reduce(&p, kind, false)?;
            Ok(Replies::PerRank((0..world).map(|r| sum[r * chunk..(r + 1) * chunk].to_vec()).collect()))
        })?;
        write_bytes(output, &out)
    }

    fn all_gather(&mut self, input: &Tensor, output: &mut Tensor) -> Result<()> {
        let op = Op::AllGather;
        let world = self.world_size();
        let n = check_split(op.name(), output, input, world)?;
        let kind = input.f_kind()?;
        let full = world * n * kind.elt_size_in_bytes();
        let out = self.star.collective(op, kind, n, None, tensor_bytes(input)?, full, |p| Ok(Replies::Same(p.concat())))?;
        write_bytes(output, &out)
    }

    fn broadcast(&mut self, tensor: &mut Tensor, root: usize) -> Result<()> {
        let op = Op::Broadcast;
        check_root(op.name(), root, self.world_size())?;
        let kind = tensor.f_kind()?;
        let is_root = self.rank() == root;
        let payload = if is_root { tensor_bytes(tensor)? } else { Vec::new() };
        let len = tensor.numel() * kind.elt_size_in_bytes();
        let out = self.star.collective(op, kind, tensor.numel(), Some(root), payload, len, |mut p| {
            Ok(Replies::Same(std::mem::take(&mut p[root])))
        })?;
        if is_root {
            return Ok(());
        }
        write_bytes(tensor, &out)
    }

    fn barrier(&mut self) -> Result<()> {
        self.star.collective(Op::Barrier, Kind::Uint8, 0, None, Vec::new(), 0, |_| Ok(Replies::Same(Vec::new())))?;
        Ok(())
    }

    /// Complete when it returns: rank 0 sums in rank order, as for the other reductions.
    fn start_reduce_sum(&mut self, tensor: &Tensor, root: Option<usize>) -> Result<()> {
        let op = Op::ReduceSum;
        if let Some(r) = root {
            check_root(op.name(), r, self.world_size())?;
        }
        let kind = tensor.f_kind()?;
        check_reducible(kind, false, op.name())?;
        let bytes = tensor_bytes(tensor)?;
        let len = bytes.len();
        let out = self.star.collective(op, kind, tensor.numel(), root, bytes, len, |p| Ok(Replies::Same(reduce(&p, kind, false)?)))?;
        if root.is_none_or(|r| r == self.rank()) {
            write_bytes(&mut tensor.shallow_clone(), &out)?;
        }
        Ok(())
    }

    fn take_collective_seconds(&mut self) -> f64 {
        self.star.take_busy().as_secs_f64()
    }
}

/// The tensor's elements in row-major order, native little-endian bytes (any device).
pub(crate) fn tensor_bytes(t: &Tensor) -> Result<Vec<u8>> {
    let n = t.numel();
    let mut buf = vec![0u8; n * t.f_kind()?.elt_size_in_bytes()];
    if n > 0 {
        t.f_copy_data_u8(&mut buf, n)?;
    }
    Ok(buf)
}

/// Overwrites `t` (any device, any layout) with `bytes` as produced by [`tensor_bytes`].
pub(crate) fn write_bytes(t: &mut Tensor, bytes: &[u8]) -> Result<()> {
    let kind = t.f_kind()?;
    if bytes.len() != t.numel() * kind.elt_size_in_bytes() {
        bail!("{} bytes do not fill a {kind:?} tensor of {} elements", bytes.len(), t.numel());
    }
    if t.numel() == 0 {
        return Ok(());
    }
    let src = Tensor::f_from_data_size(bytes, &t.size(), kind)?;
    let src = if t.device() == Device::Cpu { src } else { src.f_to_device(t.device())? };
    tch::no_grad(|| t.f_copy_(&src))?;
    Ok(())
}

/// Elementwise sum (or mean) of equally long little-endian buffers, in rank order.
fn reduce(payloads: &[Vec<u8>], kind: Kind, mean: bool) -> Result<Vec<u8>> {
    let Some(len) = payloads.first().map(Vec::len) else { bail!("nothing to reduce") };
    if payloads.iter().any(|p| p.len() != len) {
        bail!("buffers of different lengths");
    }
    let world = payloads.len();
    Ok(match kind {
        Kind::Float => fold(payloads, f32::from_le_bytes, |a, b| a + b, |s| (if mean { s / world as f32 } else { s }).to_le_bytes()),
        Kind::Double => fold(payloads, f64::from_le_bytes, |a, b| a + b, |s| (if mean { s / world as f64 } else { s }).to_le_bytes()),
        Kind::BFloat16 => fold(
            payloads,
            |b| bf16::from_le_bytes(b).to_f32(),
            |a, b| a + b,
            |s| bf16::from_f32(if mean { s / world as f32 } else { s }).to_le_bytes(),
        ),
        Kind::Half => fold(
            payloads,
            |b| f16::from_le_bytes(b).to_f32(),
            |a, b| a + b,
            |s| f16::from_f32(if mean { s / world as f32 } else { s }).to_le_bytes(),
        ),
        Kind::Int64 => fold(payloads, i64::from_le_bytes, i64::wrapping_add, i64::to_le_bytes),
        Kind::Int => fold(payloads, i32::from_le_bytes, i32::wrapping_add, i32::to_le_bytes),
        Kind::Int16 => fold(payloads, i16::from_le_bytes, i16::wrapping_add, i16::to_le_bytes),
        Kind::Int8 => fold(payloads, i8::from_le_bytes, i8::wrapping_add, i8::to_le_bytes),
        Kind::Uint8 => fold(payloads, u8::from_le_bytes, u8::wrapping_add, u8::to_le_bytes),
        _ => bail!("cannot reduce {kind:?} tensors"),
    })
}

fn fold<const N: usize, A: Copy>(
    payloads: &[Vec<u8>],
    load: impl Fn([u8; N]) -> A,
    add: impl Fn(A, A) -> A,
    store: impl Fn(A) -> [u8; N],
) -> Vec<u8> {
    let element = |p: &[u8], i: usize| {
        let mut a = [0u8; N];
        a.copy_from_slice(&p[i * N..(i + 1) * N]);
        load(a)
    };
    let n = payloads[0].len() / N;
    let mut out = Vec::with_capacity(n * N);
    for i in 0..n {
        let acc = payloads[1..].iter().fold(element(&payloads[0], i), |acc, p| add(acc, element(p, i)));
        out.extend_from_slice(&store(acc));
    }
    out
}
