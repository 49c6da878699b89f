//! Background loading: a worker thread computes the results of a known sequence of keys (e.g. the
//! sample indices of the next micro-batches) ahead of the consumer, at most `depth` results
//! ahead, and the consumer's time spent waiting for them is measured.

use std::sync::mpsc::{sync_channel, Receiver, TryRecvError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use tch::Tensor;

use crate::latent_cache::LatentCache;

pub struct Prefetcher<K, T> {
    rx: Option<Receiver<(K, Result<T>)>>,
    worker: Option<JoinHandle<()>>,
    waited: Duration,
}

impl<K, T> Prefetcher<K, T>
where
    K: PartialEq + Send + 'static,
    T: Send + 'static,
{
    /// Starts a worker running `work` over `keys` in order. At most `depth` (>= 1) finished
    /// results wait in the queue; the worker stops after the last key, after an error (which is
    /// delivered), or when the prefetcher is dropped.
    pub fn spawn<I, F>(depth: usize, keys: I, mut work: F) -> Result<Self>
    where
        I: IntoIterator<Item = K>,
        I::IntoIter: Send + 'static,
        F: FnMut(&K) -> Result<T> + Send + 'static,
    {
        let (tx, rx) = sync_channel(depth.max(1));
        let keys = keys.into_iter();
        let worker = std::thread::Builder::new()
            .name("bwm-prefetch".into())
            .spawn(move || {
                for key in keys {
                    let result = work(&key);
                    let failed = result.is_err();
                    if tx.send((key, result)).is_err() || failed {
                        break;
                    }
                }
            })
            .context("starting the prefetch thread")?;
        Ok(Self { rx: Some(rx), worker: Some(worker), waited: Duration::ZERO })
    }

    /// The result for `key`, which must be the next key of the sequence; blocks until it is
    /// ready. None when the sequence is exhausted or its next key is another one: the
    /// prefetcher is then stopped, and the caller computes the result itself or starts a new one.
    pub fn next(&mut self, key: &K) -> Option<Result<T>> {
        let rx = self.rx.as_ref()?;
        // A result already queued costs no waiting; only a blocking receive is timed.
        let got = match rx.try_recv() {
            Err(TryRecvError::Empty) => {
                let start = Instant::now();
                let got = rx.recv().ok();
                self.waited += start.elapsed();
                got
            }
            other => other.ok(),
        };
        match got {
            Some((k, result)) if &k == key => Some(result),
            _ => {
                self.stop();
                None
            }
        }
    }

    /// Time spent blocked in `next` since the last call.
    pub fn take_waited(&mut self) -> Duration {
        std::mem::take(&mut self.waited)
    }

    /// Whether the worker may still deliver results.
    pub fn is_running(&self) -> bool {
        self.rx.is_some()
    }

    fn stop(&mut self) {
        // Dropping the receiver makes the worker's pending send fail, so it ends promptly.
        self.rx = None;
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

impl<K, T> Drop for Prefetcher<K, T> {
    fn drop(&mut self) {
        self.rx = None;
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

/// Clips of the cache, stacked along a new first dimension, as f32 values (raw clips: u8 pixel
/// frames instead of latents).
pub struct ClipBatch {
    pub clips: usize,
    /// [clips, C, F, h, w], row-major; empty for raw clips.
    pub latents: Vec<f32>,
    /// [clips, F_pixel, d_a], row-major.
    pub actions: Vec<f32>,
    /// [clips, 3, F_pixel, H, W], row-major; raw clips only.
    pub frames: Vec<u8>,
}

/// Reads clips `clips` of the cache (the work of a cache prefetcher). No tensor operation runs
/// here: torch's OpenMP threads started from a loader thread would spin on the cores the
/// consumer computes on; the consumer makes tensors of the values (one copy each).
pub fn load_clips(cache: &LatentCache, clips: &[usize]) -> Result<ClipBatch> {
    anyhow::ensure!(!clips.is_empty(), "an empty batch of clips");
    let mut batch = ClipBatch { clips: clips.len(), latents: Vec::new(), actions: Vec::new(), frames: Vec::new() };
    for &c in clips {
        let v = cache.load_values(c)?;
        batch.latents.extend(v.latents);
        batch.actions.extend(v.actions);
        batch.frames.extend(v.frames);
    }
    Ok(batch)
}

impl ClipBatch {
    /// [B, C, F, h, w] f32 latents (None for raw clips), [B, F_pixel, d_a] f32 actions, as CPU tensors.
    pub fn tensors(&self, cache: &LatentCache) -> (Option<Tensor>, Tensor) {
        let b = self.clips as i64;
        (
            cache.index.has_latents.then(|| Tensor::from_slice(&self.latents).view(batched(b, cache.index.latent_shape.clone()).as_slice())),
            Tensor::from_slice(&self.actions).view(batched(b, cache.index.action_shape()).as_slice()),
        )
    }

    /// [B, 3, F_pixel, H, W] u8 pixel frames of raw clips (None otherwise), a CPU tensor.
    pub fn frames(&self, cache: &LatentCache) -> Option<Tensor> {
        (!cache.index.has_latents).then(|| Tensor::from_slice(&self.frames).view(batched(self.clips as i64, cache.index.frame_shape()).as_slice()))
    }
}

/// `shape` with a leading batch dimension `b`.
fn batched(b: i64, shape: Vec<i64>) -> Vec<i64> {
    std::iter::once(b).chain(shape).collect()
}

/// A prefetcher of cache batches: key = the clip indices of a batch.
pub fn prefetch_clips<I>(cache: LatentCache, batches: I, depth: usize) -> Result<Prefetcher<Vec<usize>, ClipBatch>>
where
    I: IntoIterator<Item = Vec<usize>>,
    I::IntoIter: Send + 'static,
{
    Prefetcher::spawn(depth, batches, move |clips: &Vec<usize>| load_clips(&cache, clips))
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    use super::*;

    #[test]
    fn results_come_in_order_and_at_most_depth_ahead() {
        let produced = Arc::new(AtomicUsize::new(0));
        let p2 = produced.clone();
        let mut p = Prefetcher::spawn(2, 0u64.., move |&k: &u64| {
            p2.fetch_add(1, Ordering::SeqCst);
            Ok(k * 10)
        })
        .unwrap();
        std::thread::sleep(Duration::from_millis(100));
        // Two queued and one finished result waiting to be sent.
        assert!(produced.load(Ordering::SeqCst) <= 3, "{}", produced.load(Ordering::SeqCst));
        for k in 0..5u64 {
            assert_eq!(p.next(&k).unwrap().unwrap(), k * 10);
        }
        // An out-of-sequence key stops the worker; the infinite sequence does not keep drop waiting.
        assert!(p.next(&99).is_none());
        assert!(!p.is_running());
        assert!(p.next(&6).is_none());
    }

    #[test]
    fn waiting_is_measured_and_errors_are_delivered_then_stop() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        use std::sync::{mpsc, Arc};
        // The first result is held back until the consumer is already inside `next`, so it must
        // block; nothing here depends on how fast the machine is.
        let (release, hold) = mpsc::channel::<()>();
        let mut p = Prefetcher::spawn(2, 0u64..3, move |&k: &u64| {
            if k == 0 {
                hold.recv().unwrap();
            }
            if k == 1 {
                anyhow::bail!("clip {k} is unreadable")
            }
            Ok(k)
        })
        .unwrap();
        let releaser = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(30));
            release.send(()).unwrap();
        });
        let call = Instant::now();
        assert_eq!(p.next(&0).unwrap().unwrap(), 0);
        let took = call.elapsed();
        releaser.join().unwrap();
        let waited = p.take_waited();
        assert!(waited > Duration::ZERO && waited <= took, "{waited:?} of {took:?}");
        assert_eq!(p.take_waited(), Duration::ZERO);
        let e = p.next(&1).unwrap().unwrap_err();
        assert!(e.to_string().contains("unreadable"));
        assert!(p.next(&2).is_none(), "the worker stops after an error");

        // A consumer that finds its result queued does not wait at all.
        let calls = Arc::new(AtomicUsize::new(0));
        let counted = calls.clone();
        let mut fast = Prefetcher::spawn(2, 0u64..4, move |&k: &u64| {
            counted.fetch_add(1, Ordering::SeqCst);
            Ok(k)
        })
        .unwrap();
        // The worker computes key 1 only after key 0 was queued.
        while calls.load(Ordering::SeqCst) < 2 {
            std::thread::yield_now();
        }
        assert_eq!(fast.next(&0).unwrap().unwrap(), 0);
        assert_eq!(fast.take_waited(), Duration::ZERO);
        drop(fast);
    }

    #[test]
    fn cache_batches_equal_clip_by_clip_loads() {
        use crate::latent_cache::{CacheIndex, CacheWriter, ClipEntry};
        use tch::{Device, Kind};
        let dir = bwm_testdir::TestDir::new("prefetch-cache");
        let index = CacheIndex::new(vec![4, 2, 2, 2], 3, 0, 4, [32, 32], 10.0, "test");
        let mut w = CacheWriter::with_shard_size(&dir, index, 3).unwrap();
        for i in 0..7 {
            let latents = Tensor::randn([4, 2, 2, 2], (Kind::Float, Device::Cpu));
            let actions = Tensor::rand([5, 3], (Kind::Float, Device::Cpu));
            w.add(ClipEntry { file: String::new(), episode: i, frames: vec![0; 5], task: String::new() }, &latents, &actions, None).unwrap();
        }
        w.finish().unwrap();
        let cache = LatentCache::open(&dir).unwrap();
        let batches = vec![vec![6, 0], vec![3, 4], vec![5, 5]];
        let mut p = prefetch_clips(cache.clone(), batches.clone(), 2).unwrap();
        for b in &batches {
            let got = p.next(b).unwrap().unwrap();
            let (latents, actions) = got.tensors(&cache);
            let latents = latents.unwrap();
            let clips: Vec<_> = b.iter().map(|&i| cache.load(i, Device::Cpu).unwrap()).collect();
            assert!(latents.equal(&Tensor::stack(&clips.iter().map(|c| c.latents.shallow_clone()).collect::<Vec<_>>(), 0)), "{b:?}");
            assert!(actions.equal(&Tensor::stack(&clips.iter().map(|c| c.actions.shallow_clone()).collect::<Vec<_>>(), 0)), "{b:?}");
        }
        assert!(p.next(&vec![0]).is_none(), "the sequence is exhausted");
    }
}
