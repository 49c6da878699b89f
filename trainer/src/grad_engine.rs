//! The data-parallel gradient engine under the optimizer: the trained tensors packed end to end
//! into one flat buffer (in the model dtype; the model's parameters become views of it), their
//! gradients handed after each micro-step into one fp32 flat accumulator (the step's first
//! hand-off of a tensor copies, later ones add, so the accumulator is never zeroed), the sum over
//! the data-parallel ranks (each element into the rank that owns it when the optimizer state is
//! sharded, ZeRO-1; into every rank when it is replicated), parts of it started early while the
//! backward walk goes on ([`GradEngine::reduce_early`]), and the updated weights written back to
//! every rank (all-gathered from the owners' slices when sharded).
//!
//! A step of one micro-step on one rank whose update reads model-dtype gradients in place (the
//! fused kernel, bf16 weights) skips the accumulator: those gradients are kept as autograd made
//! them ([`GradEngine::take_grads`], [`GradEngine::take_kept`]). What the update does with the
//! reduced gradient is `optim`'s.

use std::ops::Range;

use anyhow::{ensure, Context, Result};
use tch::{Device, Kind, Tensor};

use crate::dist::{Collective, FlatBuffer};
use crate::fused_adamw::GradTable;

/// How the optimizer state is spread over the data-parallel ranks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sharding {
    pub rank: usize,
    pub world: usize,
    /// Each rank keeps 1/world of the state (ZeRO-1); otherwise every rank keeps all of it.
    pub sharded: bool,
}

impl Sharding {
    pub const SINGLE: Self = Self {
        rank: 0,
        world: 1,
        sharded: false,
    };
}

pub struct TrainParam {
    pub name: String,
    /// The model's tensor (requires grad), in the model dtype: a view of the flat weights.
    pub param: Tensor,
    /// Its fp32 gradient accumulator: a view of the flat gradient.
    pub grad: Tensor,
}

/// The flat weights and gradients of the trained tensors and their movement across the
/// data-parallel ranks.
pub struct GradEngine {
    pub sharding: Sharding,
    weights: FlatBuffer,
    grads: FlatBuffer,
    /// Per trained tensor, its fp32 accumulator (a view of `grads`).
    accumulators: Vec<Tensor>,
    /// The elements of the flat buffers this rank's optimizer state covers.
    slice: Range<usize>,
    /// Ranges of the flat gradient whose reduction started before this step ([`GradEngine::reduce_early`]).
    started: Vec<Range<usize>>,
    /// Per trained tensor: whether its accumulator holds a gradient of this step yet.
    written: Vec<bool>,
    /// The model-dtype gradients of this step's only micro-step, for the update to read in place.
    pending: Option<Vec<Tensor>>,
    /// Where each trained tensor lies in the flat buffers, for reading `pending` (built at first use).
    table: Option<GradTable>,
}

impl GradEngine {
    /// Moves `tensors` (all of one dtype and device) into one flat buffer: each of them, and every
    /// module holding it, now reads the buffer's storage and requires grad. Returns the engine and
    /// the trained tensors with their accumulators, in packing order.
    pub fn pack(tensors: &[(String, Tensor)], sharding: Sharding) -> Result<(Self, Vec<TrainParam>)> {
        let first = tensors.first().context("no trained tensor to pack")?;
        let (kind, device) = (first.1.kind(), first.1.device());
        let shallow: Vec<Tensor> = tensors.iter().map(|(_, t)| t.shallow_clone()).collect();
        let world = sharding.world.max(1);
        let weights = FlatBuffer::pack_as(&shallow, world, kind, device)
            .context("packing the trained weights")?;
        let layout: Vec<(Vec<i64>, Kind)> =
            shallow.iter().map(|t| (t.size(), Kind::Float)).collect();
        let grads = FlatBuffer::zeros(&layout, world, Kind::Float, device)?;
        let mut params = Vec::with_capacity(tensors.len());
        let mut accumulators = Vec::with_capacity(tensors.len());
        for (i, (name, t)) in tensors.iter().enumerate() {
            let mut t = t.shallow_clone();
            // The parameter (and every module holding it) now reads the flat buffer's storage.
            let view = weights.view(i)?;
            tch::no_grad(|| t.set_data(&view));
            let _ = t.set_requires_grad(true);
            let grad = grads.view(i)?;
            accumulators.push(grad.shallow_clone());
            params.push(TrainParam {
                name: name.clone(),
                param: t,
                grad,
            });
        }
        let sharding = Sharding { world, ..sharding };
        let slice = if sharding.sharded && world > 1 {
            weights.shard_range(sharding.rank)
        } else {
            0..weights.len()
        };
        let engine = Self {
            sharding,
            weights,
            grads,
            accumulators,
            slice,
            started: Vec::new(),
            written: vec![false; tensors.len()],
            pending: None,
            table: None,
        };
        Ok((engine, params))
    }

    /// Whether each rank keeps only its slice of the optimizer state.
    pub fn is_sharded(&self) -> bool {
        self.sharding.sharded && self.sharding.world > 1
    }

    /// Trained elements in all.
    pub fn numel(&self) -> usize {
        self.weights.numel()
    }

    /// The elements of the flat buffers this rank's optimizer state covers.
    pub fn slice(&self) -> Range<usize> {
        self.slice.clone()
    }

    /// The flat weights in the model dtype (every trained tensor is a view of it).
    pub fn weights(&self) -> &Tensor {
        self.weights.flat()
    }

    /// The flat fp32 gradient accumulator.
    pub fn grads(&self) -> &Tensor {
        self.grads.flat()
    }

    /// This rank's slice of the flat weights, in fp32: the initial masters.
    pub fn slice_of_weights_f32(&self) -> Tensor {
        self.weights
            .flat()
            .narrow(0, self.slice.start as i64, self.slice.len() as i64)
            .to_kind(Kind::Float)
    }

    /// Hands trained tensor `k`'s gradient of one micro-step into its fp32 accumulator: copied
    /// when it is the step's first, added otherwise. An undefined gradient (the tensor was not
    /// used) counts as zeros.
    pub fn accumulate(&mut self, k: usize, g: &Tensor) {
        self.flush_pending();
        let first = !std::mem::replace(&mut self.written[k], true);
        let mut acc = self.accumulators[k].shallow_clone();
        tch::no_grad(|| match (g.defined(), first) {
            (true, true) => acc.copy_(g),
            (true, false) => drop(acc.g_add_(g)),
            (false, true) => drop(acc.zero_()),
            (false, false) => {}
        });
    }

    /// Takes one micro-step's gradients of every trained tensor, in order (undefined for a tensor
    /// not used). With `in_place` (the step's last micro-step, and an update that reads
    /// model-dtype gradients) on the step's first micro-step, on one rank, with bf16 weights, they
    /// are kept as they are for the step to read in place (`take_kept`); otherwise they go into
    /// the accumulators.
    pub fn take_grads(&mut self, grads: Vec<Tensor>, in_place: bool) -> Result<()> {
        ensure!(grads.len() == self.accumulators.len(), "{} gradients for {} trained tensors", grads.len(), self.accumulators.len());
        let direct = in_place
            && self.sharding.world == 1
            && self.pending.is_none()
            && !self.written.iter().any(|&w| w)
            && self.weights.flat().kind() == Kind::BFloat16
            && grads.iter().zip(&self.accumulators).all(|(g, a)| !g.defined() || (g.kind() == Kind::BFloat16 && g.size() == a.size()));
        if !direct {
            for (k, g) in grads.iter().enumerate() {
                self.accumulate(k, g);
            }
            return Ok(());
        }
        let kept = grads
            .into_iter()
            .zip(&self.accumulators)
            .map(|(g, a)| if g.defined() { g.contiguous() } else { Tensor::zeros(a.size(), (Kind::BFloat16, a.device())) })
            .collect();
        self.pending = Some(kept);
        Ok(())
    }

    /// Whether model-dtype gradients are kept for the step to read in place.
    pub fn has_kept(&self) -> bool {
        self.pending.is_some()
    }

    /// The model-dtype gradients kept by `take_grads` for this step, taken out.
    pub fn take_kept(&mut self) -> Option<Vec<Tensor>> {
        self.pending.take()
    }

    /// Where each trained tensor lies in the flat buffers, on `device` (built at first use).
    pub fn table(&mut self, device: Device) -> Result<&GradTable> {
        if self.table.is_none() {
            let (offsets, numels): (Vec<i64>, Vec<i64>) = (0..self.accumulators.len())
                .map(|k| self.grads.range(k).map(|r| (r.start as i64, r.len() as i64)).with_context(|| format!("no trained tensor {k}")))
                .collect::<Result<Vec<_>>>()?
                .into_iter()
                .unzip();
            self.table = Some(GradTable::new(&offsets, &numels, device)?);
        }
        self.table.as_ref().context("the gradient table")
    }

    /// The table built by [`GradEngine::table`].
    pub fn built_table(&self) -> Result<&GradTable> {
        self.table.as_ref().context("the gradient table")
    }

    /// Moves kept model-dtype gradients into the accumulators (a hand-off that cannot read them in
    /// place came after them).
    fn flush_pending(&mut self) {
        if let Some(grads) = self.pending.take() {
            for (k, g) in grads.iter().enumerate() {
                self.accumulate(k, g);
            }
        }
    }

    /// Zeroes the accumulators no hand-off of this step wrote (they hold an earlier step's sum).
    fn zero_unwritten(&mut self) {
        self.flush_pending();
        for k in 0..self.accumulators.len() {
            if !self.written[k] {
                self.accumulate(k, &Tensor::new());
            }
        }
    }

    /// Drops the accumulated gradients (a skipped step). Reductions started early must be
    /// finished first (`comm.finish_started()` or any collective).
    pub fn discard(&mut self) {
        self.started.clear();
        self.pending = None;
        self.written.fill(false);
    }

    /// Ends a step: the next step's first hand-off of each tensor overwrites its accumulator.
    pub fn end_step(&mut self) {
        self.written.fill(false);
    }

    /// Starts summing the gradients of trained tensors `params` over the ranks: they are final
    /// for this optimizer step, and nothing writes them until the step. The step reduces the rest
    /// of the buffer. Nothing to do on one rank.
    pub fn reduce_early(&mut self, params: &[usize], comm: &mut dyn Collective) -> Result<()> {
        if self.sharding.world <= 1 {
            return Ok(());
        }
        let mut ranges = params
            .iter()
            .map(|&k| self.grads.range(k).with_context(|| format!("no trained tensor {k}")))
            .collect::<Result<Vec<_>>>()?;
        ranges.sort_by_key(|r| r.start);
        for r in merge_adjacent(ranges) {
            ensure!(
                self.started.iter().all(|s| s.end <= r.start || r.end <= s.start),
                "the gradients at {r:?} of the flat buffer are already being reduced"
            );
            self.start_reduce(r.clone(), comm)?;
            self.started.push(r);
        }
        Ok(())
    }

    /// Starts the sum of `range` of the flat gradient: each part into the rank whose slice holds
    /// it when sharded, into every rank otherwise.
    fn start_reduce(&self, range: Range<usize>, comm: &mut dyn Collective) -> Result<()> {
        let part = |r: &Range<usize>| self.grads.flat().narrow(0, r.start as i64, r.len() as i64);
        if !self.is_sharded() {
            return comm.start_reduce_sum(&part(&range), None).with_context(|| format!("reducing gradients {range:?}"));
        }
        for rank in 0..self.sharding.world {
            let owned = self.grads.shard_range(rank);
            let piece = range.start.max(owned.start)..range.end.min(owned.end);
            if !piece.is_empty() {
                comm.start_reduce_sum(&part(&piece), Some(rank))
                    .with_context(|| format!("reducing gradients {piece:?} into rank {rank}"))?;
            }
        }
        Ok(())
    }

    /// Sums the step's accumulated gradients over the ranks (what `reduce_early` has not started;
    /// accumulators no hand-off wrote count as zeros) and returns this rank's slice of the sum
    /// (all of it when the state is replicated).
    pub fn reduce(&mut self, comm: &mut dyn Collective) -> Result<Tensor> {
        self.zero_unwritten();
        let started = std::mem::take(&mut self.started);
        if self.sharding.world > 1 && started.is_empty() {
            // Nothing reduced early: one collective over the whole buffer.
            if self.is_sharded() {
                // In place: this rank's slice of the flat gradient receives the sum (NCCL allows
                // an output at input + rank * n).
                let mut mine = self.grads.shard(self.sharding.rank)?;
                comm.reduce_scatter_sum(self.grads.flat(), &mut mine)
                    .context("reduce-scatter of the gradients")?;
                return Ok(mine);
            }
            comm.all_reduce_sum(self.grads.flat_mut())
                .context("all-reduce of the gradients")?;
        } else if self.sharding.world > 1 {
            for r in uncovered(started, self.grads.len()) {
                self.start_reduce(r, comm)?;
            }
            comm.finish_started().context("finishing the gradient reductions")?;
        }
        if self.is_sharded() {
            self.grads.shard(self.sharding.rank)
        } else {
            Ok(self.grads.flat().shallow_clone())
        }
    }

    /// Writes `master` (this rank's slice, fp32) into the model's weights on every rank
    /// (all-gather when sharded).
    pub fn publish(&mut self, master: &Tensor, comm: &mut dyn Collective) -> Result<()> {
        let kind = self.weights.flat().kind();
        if self.is_sharded() {
            let mine = master.to_kind(kind);
            comm.all_gather(&mine, self.weights.flat_mut())
                .context("all-gather of the updated weights")?;
        } else {
            tch::no_grad(|| self.weights.flat_mut().copy_(master));
        }
        Ok(())
    }
}

/// Sorted ranges with the touching ones joined.
fn merge_adjacent(sorted: Vec<Range<usize>>) -> Vec<Range<usize>> {
    let mut out: Vec<Range<usize>> = Vec::with_capacity(sorted.len());
    for r in sorted {
        match out.last_mut() {
            Some(last) if last.end == r.start => last.end = r.end,
            _ => out.push(r),
        }
    }
    out
}

/// The parts of `0..len` outside the disjoint `covered` ranges, in order.
fn uncovered(mut covered: Vec<Range<usize>>, len: usize) -> Vec<Range<usize>> {
    covered.sort_by_key(|r| r.start);
    let mut out = Vec::new();
    let mut at = 0;
    for r in covered {
        if r.start > at {
            out.push(at..r.start);
        }
        at = at.max(r.end);
    }
    if at < len {
        out.push(at..len);
    }
    out
}
