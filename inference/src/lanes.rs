//! Episodes in flight split into lanes that take turns: each lane's chunk is queued on a CUDA
//! stream of its own (`Rollout::begin_chunks`) and read back on its next turn
//! (`Rollout::finish_chunks`). While one lane's chunk runs on the device, the host reads another
//! lane's frames, judges them and asks its policies for the next actions; on the device, one
//! lane's decode can run beside another's DiT steps. Within one rollout nothing overlaps: each
//! chunk is conditioned on the frames of the one before.

use anyhow::{ensure, Result};
use bwm_cuda_graph::CudaStream;
use bwm_model::rollout::{Chunk, PendingChunks, Rollout};
use tch::{Device, Tensor};

/// `n` lanes on one device: one stream each on CUDA when there are several, else the current
/// stream (on the CPU the lanes only take turns).
pub struct Lanes {
    streams: Vec<Option<CudaStream>>,
}

impl Lanes {
    pub fn new(device: Device, n: usize) -> Result<Self> {
        ensure!(n >= 1, "streams must be at least 1");
        let streams = (0..n)
            .map(|_| match device {
                Device::Cuda(_) if n > 1 => CudaStream::new(device).map(Some),
                _ => Ok(None),
            })
            .collect::<Result<_>>()?;
        Ok(Self { streams })
    }

    pub fn len(&self) -> usize {
        self.streams.len()
    }

    pub fn is_empty(&self) -> bool {
        self.streams.is_empty()
    }

    /// Runs `body` with lane `lane`'s stream current: every chunk a lane begins must be finished
    /// inside its own lane.
    pub fn on<T>(&self, lane: usize, body: impl FnOnce() -> Result<T>) -> Result<T> {
        match &self.streams[lane] {
            Some(stream) => stream.scope(body),
            None => body(),
        }
    }

    /// How many of `in_flight` episodes each lane carries: as even as they divide, the first
    /// lanes one more. Every lane must carry one.
    pub fn shares(&self, in_flight: usize) -> Result<Vec<usize>> {
        check(in_flight, self.len())?;
        Ok(shares(in_flight, self.len()))
    }
}

/// Whether `in_flight` episodes fill `streams` lanes (before a model is loaded for them).
pub fn check(in_flight: usize, streams: usize) -> Result<()> {
    ensure!(streams >= 1, "streams must be at least 1");
    ensure!(in_flight >= streams, "{in_flight} episode(s) in flight cannot fill {streams} streams: each stream carries at least one");
    Ok(())
}

/// `in_flight` split over `n` lanes as evenly as it divides, the first lanes one more.
fn shares(in_flight: usize, n: usize) -> Vec<usize> {
    (0..n).map(|i| in_flight / n + usize::from(i < in_flight % n)).collect()
}

/// `Rollout::run_together` over lanes: `rollouts` are dealt to the lanes in `Lanes::shares` order
/// (the first share to lane 0, ...; fewer rollouts than lanes leave the last lanes idle); each turn of a lane reads back its last chunk, hands it over
/// as `on_chunk(i, chunk)` and begins its next (those of its rollouts with actions left) before
/// the next lane's turn. Each rollout gets what it gets in `run_together`.
pub fn run_together(lanes: &Lanes, rollouts: &mut [&mut Rollout<'_>], actions: &[Tensor], on_chunk: &mut dyn FnMut(usize, Chunk) -> Result<()>) -> Result<()> {
    ensure!(rollouts.len() == actions.len(), "{} rollouts but {} action sequences", rollouts.len(), actions.len());
    if rollouts.is_empty() {
        return Ok(());
    }
    let shares = shares(rollouts.len(), lanes.len().min(rollouts.len()));
    let mut applied = vec![0i64; actions.len()];
    let mut pending: Vec<Option<(Vec<usize>, PendingChunks)>> = (0..lanes.len()).map(|_| None).collect();
    let mut bounds = Vec::with_capacity(shares.len());
    let mut at = 0;
    for s in &shares {
        bounds.push(at..at + s);
        at += s;
    }
    loop {
        let mut busy = false;
        for (lane, range) in bounds.iter().enumerate() {
            lanes.on(lane, || -> Result<()> {
                if let Some((indices, p)) = pending[lane].take() {
                    let mut batch: Vec<&mut Rollout> = Vec::with_capacity(indices.len());
                    for (i, r) in rollouts.iter_mut().enumerate() {
                        if indices.contains(&i) {
                            batch.push(&mut **r);
                        }
                    }
                    for (i, chunk) in indices.into_iter().zip(Rollout::finish_chunks(&mut batch, p)?) {
                        applied[i] += chunk.actions.size()[0];
                        on_chunk(i, chunk)?;
                    }
                }
                let (mut batch, mut windows, mut indices) = (Vec::new(), Vec::new(), Vec::new());
                for i in range.clone() {
                    let r: &Rollout = &*rollouts[i];
                    if let Some(window) = r.next_window(&actions[i], applied[i]) {
                        windows.push(window);
                        indices.push(i);
                        batch.push(r);
                    }
                }
                if !batch.is_empty() {
                    pending[lane] = Some((indices, Rollout::begin_chunks(&batch, &windows)?));
                }
                Ok(())
            })?;
            busy |= pending[lane].is_some();
        }
        if !busy {
            return Ok(());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shares_split_the_episodes_evenly_and_refuse_empty_lanes() {
        let lanes = Lanes::new(Device::Cpu, 3).unwrap();
        assert_eq!(lanes.shares(8).unwrap(), vec![3, 3, 2]);
        assert_eq!(lanes.shares(3).unwrap(), vec![1, 1, 1]);
        let err = lanes.shares(2).unwrap_err().to_string();
        assert!(err.contains("cannot fill 3 streams"), "{err}");
        assert!(Lanes::new(Device::Cpu, 0).is_err());
        assert!(check(4, 4).is_ok() && check(3, 4).is_err() && check(4, 0).is_err());
    }
}
