//! Encoding the clips the reader sends: batches assembled in page-locked buffers and queued to the
//! VAE on the device while the next batch is assembled (raw clips are stored without encoding),
//! each finished shard written with this rank's progress.

use std::cell::{Cell, RefCell};
use std::path::Path;
use std::sync::mpsc::Receiver;
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use bwm_data::latent_cache::{shard_file_name, write_shard, CacheIndex, ShardClip};
use bwm_model::vae::WanVae;
use indicatif::{ProgressBar, ProgressStyle};
use tch::{Device, Kind, Tensor};

use crate::folder::{write_progress, FinishedShard, RankProgress, ShardSkip};
use crate::read::{ClipInput, Input};

/// Encodes the clips the reader sends, writes each finished shard and this rank's progress.
pub(crate) struct Encoder<'a> {
    /// None: raw clips, stored without encoding.
    pub(crate) vae: Option<&'a WanVae>,
    pub(crate) device: Device,
    pub(crate) batch: usize,
    pub(crate) keep_frames: bool,
    pub(crate) out: &'a Path,
    pub(crate) index: &'a CacheIndex,
    pub(crate) fault_after: Option<usize>,
    /// Page-locked batch buffers on CUDA, used in turn, and the batches started so far.
    pub(crate) staging: RefCell<[Option<Tensor>; 2]>,
    pub(crate) batches: Cell<usize>,
}

impl Encoder<'_> {
    /// Returns (clips encoded, planned clips skipped).
    pub(crate) fn run(&self, rx: Receiver<Input>, progress: &mut RankProgress, total: usize) -> Result<(usize, usize)> {
        let bar = std::io::IsTerminal::is_terminal(&std::io::stderr()).then(|| {
            let bar = ProgressBar::new(total as u64);
            if let Ok(style) = ProgressStyle::with_template("{bar:40} {pos}/{len} clips  {per_sec}  {elapsed_precise} elapsed, ETA {eta_precise}") {
                bar.set_style(style);
            }
            bar
        });
        let start = Instant::now();
        let (mut encoded, mut skipped, mut shards_written) = (0usize, 0usize, 0usize);
        let mut pending: Vec<ClipInput> = Vec::new();
        // The batch whose encoding is queued on the device: its latents are read back only after
        // the next batch is assembled and queued, so that the host work overlaps the encoding.
        let mut in_flight: Option<Batch> = None;
        let mut clips: Vec<ShardClip> = Vec::new();
        let mut skips: Vec<ShardSkip> = Vec::new();
        for input in rx {
            match input {
                Input::Clip(c) => {
                    pending.push(c);
                    if pending.len() == self.batch {
                        let queued = self.start(&mut pending)?;
                        if let Some(done) = std::mem::replace(&mut in_flight, queued) {
                            clips.extend(self.finish(done)?);
                        }
                    }
                }
                Input::Skip(s) => {
                    skipped += s.clips;
                    skips.push(s);
                }
                Input::End(shard) => {
                    let last = self.start(&mut pending)?;
                    for done in [in_flight.take(), last].into_iter().flatten() {
                        clips.extend(self.finish(done)?);
                    }
                    let name = shard_file_name(shard);
                    let entries = if clips.is_empty() { Vec::new() } else { write_shard(self.out, self.index, &name, &clips)? };
                    encoded += entries.len();
                    progress.finished.insert(shard, FinishedShard { clips: entries, skipped: std::mem::take(&mut skips) });
                    write_progress(self.out, progress)?;
                    shards_written += 1;
                    match &bar {
                        Some(bar) => bar.inc(clips.len() as u64),
                        None => println!(
                            "  {name}: {} clips ({encoded}/{total}, {:.2} clips/s)",
                            clips.len(),
                            encoded as f64 / start.elapsed().as_secs_f64().max(1e-9)
                        ),
                    }
                    clips.clear();
                    if self.fault_after.is_some_and(|n| shards_written >= n) {
                        // Fault injection for the resumption test: stop as a killed process would.
                        eprintln!("BWM_FAULT_EXIT_AFTER_SHARDS: exiting after {shards_written} shards");
                        std::process::exit(3);
                    }
                }
            }
        }
        if let Some(bar) = bar {
            bar.finish_and_clear();
        }
        Ok((encoded, skipped))
    }

    /// Assembles the pending clips into one batch and queues its encoding on the device (no
    /// wait for the device); `None` when nothing is pending.
    fn start(&self, pending: &mut Vec<ClipInput>) -> Result<Option<Batch>> {
        if pending.is_empty() {
            return Ok(None);
        }
        let [w, h] = self.index.resolution;
        let f = self.index.pixel_frames as i64;
        let clip_bytes = (f * h as i64 * w as i64 * 3) as usize;
        if let Some(c) = pending.iter().find(|c| c.pixels.len() != clip_bytes) {
            bail!("clip pixels ({} bytes) do not match {f} frames of {w}x{h}", c.pixels.len());
        }
        let shape = [self.batch.max(pending.len()) as i64, f, h as i64, w as i64, 3];
        let host = if self.vae.is_some() && self.device.is_cuda() {
            // Page-locked, so that the copy to the device is queued rather than waited for. Two
            // buffers in turn: the one refilled now fed the batch before last, whose latents have
            // been read back, so its copy is done.
            let turn = self.batches.get() % 2;
            self.batches.set(self.batches.get() + 1);
            let mut staging = self.staging.borrow_mut();
            if staging[turn].as_ref().is_none_or(|t| t.size() != shape) {
                staging[turn] = Some(Tensor::empty(shape, (Kind::Uint8, Device::Cpu)).pin_memory(self.device));
            }
            staging[turn].as_ref().map(Tensor::shallow_clone).context("no staging buffer")?
        } else {
            Tensor::empty(shape, (Kind::Uint8, Device::Cpu))
        }
        .narrow(0, 0, pending.len() as i64);
        ensure!(host.is_contiguous() && host.numel() == pending.len() * clip_bytes, "the batch buffer is not one contiguous block");
        // SAFETY: `host` is a contiguous u8 CPU tensor of exactly this many bytes (checked above)
        // that no queued copy reads any more (see the staging buffers) and no other code touches
        // while the slice lives.
        let buffer = unsafe { std::slice::from_raw_parts_mut(host.data_ptr() as *mut u8, host.numel()) };
        for (dst, c) in buffer.chunks_exact_mut(clip_bytes).zip(pending.iter()) {
            dst.copy_from_slice(&c.pixels);
        }
        // Channels move to the front on the encoding device (a strided copy of 75 MB per 81-frame
        // 640x480 clip, slow on the host); raw clips stay on the host.
        let pixels = match self.vae {
            Some(_) => host.to_device_(self.device, Kind::Uint8, true, false),
            None => host,
        }
        .permute([0, 4, 1, 2, 3]);
        let latents = match self.vae {
            Some(vae) => Some(vae.encode_u8(&pixels)?),
            None => None,
        };
        Ok(Some(Batch { clips: std::mem::take(pending), pixels, latents }))
    }

    /// Waits for a batch's latents and turns it into shard clips.
    fn finish(&self, batch: Batch) -> Result<Vec<ShardClip>> {
        let (f, d) = (self.index.pixel_frames as i64, self.index.action_dim);
        let latents = batch.latents.map(|l| l.to_device(Device::Cpu));
        Ok(batch
            .clips
            .into_iter()
            .enumerate()
            .map(|(i, c)| ShardClip {
                entry: c.entry,
                latents: latents.as_ref().map(|l| l.get(i as i64)),
                actions: Tensor::from_slice(&c.actions).view([f, d]),
                frames: self.keep_frames.then(|| batch.pixels.get(i as i64)),
            })
            .collect())
    }
}

/// Clips whose encoding is queued: their pixels [B, 3, F, H, W] (on the device when encoding)
/// and latents (on the device, not yet read back).
pub(crate) struct Batch {
    clips: Vec<ClipInput>,
    pixels: Tensor,
    latents: Option<Tensor>,
}

