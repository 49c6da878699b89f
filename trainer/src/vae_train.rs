//! `bwm train-vae`: fits a Wan2.2-architecture VAE at a small width to a dataset's frames
//! (reconstruction MSE or L1 + KL to N(0, I)), then measures reconstruction PSNR on held-out frames and
//! records the latent statistics its encoder produces, so that normalized latents have zero mean
//! and unit variance per channel as the Wan2.2 constants give the published VAE.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

use anyhow::{ensure, Context, Result};
use bwm_model::vae::{VaeConfig, WanVae, TRAINED_CLIP_FRAMES_KEY, TRAINED_CONFIG_KEY};
use tch::{Device, Kind, Tensor};

use crate::config::OptimSection;
use bwm_metrics::image::psnr;
use crate::keyed_rng::{self, Purpose};
use crate::dist::LocalCollective;
use crate::optim::{AdamW, Sharding};
use bwm_cuda_graph::GraphedStep;

#[derive(Clone)]
pub struct VaeTrainSettings {
    pub cfg: VaeConfig,
    /// Frames per training clip (1 + 4k).
    pub clip_frames: usize,
    pub batch: usize,
    pub steps: u64,
    pub lr: f64,
    pub kl_weight: f64,
    pub seed: u64,
    pub device: Device,
    /// Evaluate held-out PSNR every N steps (0 = only at the end).
    pub eval_every: u64,
    /// Mirror each training clip left-right with probability 1/2.
    pub flip: bool,
    /// Train on a random (width, height) window of each clip (multiples of the spatial stride): the network
    /// cannot tie what it reconstructs to a position in the frame. Evaluation uses whole frames.
    pub crop: Option<(i64, i64)>,
    /// The weights' and activations' dtype: f32, or bf16 with fp32 masters in the optimizer (the
    /// DiT's recipe). Losses are computed in f32 either way; the file holds f32 weights.
    pub dtype: Kind,
    pub recon_loss: ReconLoss,
    /// Record the step's forward and backward pass once as a CUDA graph and replay it (CUDA only):
    /// the small VAE's step is bound by launching its thousands of kernels, not by the GPU.
    pub cuda_graph: bool,
}

/// Eager steps on the graph's stream before the capture (see `CudaGraph::warm_up`).
const GRAPH_WARM_UP_STEPS: u32 = 2;

/// The reconstruction term of the loss. MSE is what PSNR measures; L1 (Wan's VAE training uses
/// it) penalizes small errors as much as large ones, so it does not trade a small object's edges
/// and colour for the frame's broad areas as readily.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReconLoss {
    Mse,
    L1,
}

/// Why the motion loss (`--recon-loss motion`, MSE weighted towards where the clip changes, and
/// its `--motion-weight`) was removed (issue 69).
pub const REMOVED_MOTION_LOSS: &str = "run 34 in docs/fidelity.md at abaed68 did not adopt it: seed 0's world model drew what seed 0 draws \
     with the plain MSE (r 0.861, within its band 0.819-0.910), seed 3's moved (r 0.845), one seed's signal and smaller than the \
     data's; not measured on the recipe's data since";

impl std::fmt::Display for ReconLoss {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Mse => "mse",
            Self::L1 => "l1",
        })
    }
}

impl std::str::FromStr for ReconLoss {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "mse" => Ok(Self::Mse),
            "l1" => Ok(Self::L1),
            "motion" => Err(format!("the motion loss was removed (issue 69) because {REMOVED_MOTION_LOSS}; known: mse, l1")),
            other => Err(format!("unknown reconstruction loss {other:?} (known: mse, l1)")),
        }
    }
}

pub struct VaeTrainReport {
    pub train_psnr: f64,
    pub holdout_psnr: f64,
    pub seconds: f64,
    pub steps: u64,
    /// Frames per training clip.
    pub clip_frames: usize,
    /// The seed of the initial weights and the clip order.
    pub seed: u64,
    /// `(seed, held-out PSNR)` of every candidate `train_best_vae` trained, this one among them.
    pub candidates: Vec<(u64, f64)>,
    /// The step at which the candidates' PSNRs were measured (`steps` when each trained in full).
    pub candidates_step: u64,
}

/// Videos [3, F, H, W] in [-1, 1]: the training episodes and the held-out ones.
#[derive(Debug)]
pub struct FrameSets {
    pub train: Vec<Tensor>,
    pub holdout: Vec<Tensor>,
}

/// Clip starting positions `(video, first frame)` of `frames`-long clips covering `videos`.
pub(crate) fn clip_starts(videos: &[Tensor], frames: usize, stride: usize) -> Vec<(usize, i64)> {
    videos
        .iter()
        .enumerate()
        .flat_map(|(v, t)| {
            let n = t.size()[1] as usize;
            (0..=n.saturating_sub(frames)).step_by(stride.max(1)).filter(move |_| n >= frames).map(move |s| (v, s as i64))
        })
        .collect()
}

/// Step `step`'s `batch` clips of `starts`, drawn from (seed, step, position).
pub(crate) fn pick_clips(starts: &[(usize, i64)], batch: usize, seed: u64, step: u64) -> Vec<(usize, i64)> {
    (0..batch)
        .map(|b| {
            let u = keyed_rng::uniform(seed, step * batch as u64 + b as u64, Purpose::Shuffle);
            starts[((u * starts.len() as f64) as usize).min(starts.len() - 1)]
        })
        .collect()
}

pub(crate) fn stack_clips(videos: &[Tensor], picks: &[(usize, i64)], frames: usize, device: Device) -> Tensor {
    Tensor::stack(&picks.iter().map(|&(v, s)| videos[v].narrow(1, s, frames as i64)).collect::<Vec<_>>(), 0).to_device(device)
}

/// A random `(width, height)` window of each clip of `clips` [B, 3, F, H, W], drawn from
/// (seed, step, clip).
fn random_windows(clips: &Tensor, (w, h): (i64, i64), seed: u64, step: u64) -> Result<Tensor> {
    let size = clips.size();
    ensure!(w <= size[4] && h <= size[3], "crop {w}x{h} is larger than the {}x{} frames", size[4], size[3]);
    let offset = |b: i64, axis: u64, room: i64| {
        let u = keyed_rng::uniform(seed, (1 << 40) + (step * size[0] as u64 + b as u64) * 2 + axis, Purpose::Augment);
        ((u * (room + 1) as f64) as i64).min(room)
    };
    let windows: Vec<Tensor> = (0..size[0]).map(|b| clips.get(b).narrow(2, offset(b, 0, size[3] - h), h).narrow(3, offset(b, 1, size[4] - w), w)).collect();
    Ok(Tensor::stack(&windows, 0))
}

/// Mean reconstruction PSNR (posterior means, no sampling) over non-overlapping clips.
pub fn reconstruction_psnr(vae: &WanVae, videos: &[Tensor], frames: usize, device: Device) -> Result<f64> {
    let starts = clip_starts(videos, frames, frames);
    ensure!(!starts.is_empty(), "no clip of {frames} frames to evaluate");
    let mut sum = 0.0;
    for chunk in starts.chunks(4) {
        let x = stack_clips(videos, chunk, frames, device);
        let recon = tch::no_grad(|| -> Result<Tensor> { vae.decode(&vae.encode(&x)?) })?.to_kind(Kind::Float);
        sum += psnr(&recon.clamp(-1.0, 1.0), &x) * chunk.len() as f64;
    }
    Ok(sum / starts.len() as f64)
}

pub struct TrainedVae {
    pub vae: WanVae,
    /// Its parameters under checkpoint names.
    pub params: Vec<(String, Tensor)>,
    pub report: VaeTrainReport,
}

pub fn train_vae(data: &FrameSets, s: &VaeTrainSettings, on_log: &mut dyn FnMut(&str)) -> Result<TrainedVae> {
    check_inputs(data, s)?;
    let mut run = VaeRun::new(data, s)?;
    run.train_until(data, s.steps, on_log)?;
    run.finish(data)
}

/// One VAE's training, stepped in pieces: several candidates can train side by side in one
/// process and the ones left behind be dropped part way (`train_best_vae`).
struct VaeRun<'a> {
    s: &'a VaeTrainSettings,
    vae: WanVae,
    store: std::rc::Rc<bwm_model::vb::ParamStore>,
    opt: AdamW,
    graph: Option<GraphedStep>,
    starts: Vec<(usize, i64)>,
    /// Steps done.
    step: u64,
    /// Seconds spent in this run's own work (its steps and measurements).
    seconds: f64,
    /// The held-out PSNR last measured and the step it was measured at.
    measured: Option<(u64, f64)>,
}

/// What every VAE trained on `data` with `s` needs, checked once before any trains.
fn check_inputs(data: &FrameSets, s: &VaeTrainSettings) -> Result<()> {
    ensure!(s.clip_frames >= 1 && (s.clip_frames - 1) % 4 == 0, "clip frames must be 1+4k, got {}", s.clip_frames);
    ensure!(!clip_starts(&data.train, s.clip_frames, 1).is_empty(), "no training video has {} frames", s.clip_frames);
    ensure!(!data.holdout.is_empty(), "no held-out video to measure PSNR on");
    let longest_holdout = data.holdout.iter().map(|v| v.size()[1]).max().unwrap_or(0);
    ensure!(
        longest_holdout >= s.clip_frames as i64,
        "the held-out videos have at most {longest_holdout} frames, fewer than one {}-frame clip to measure PSNR on: raise --holdout-tail, hold out whole episodes (--holdout), or lower --clip-frames",
        s.clip_frames
    );
    ensure!(matches!(s.dtype, Kind::Float | Kind::BFloat16), "the VAE trains in f32 or bf16, not {:?}", s.dtype);
    ensure!(!s.cuda_graph || s.device.is_cuda(), "CUDA graphs (--cuda-graph) need a CUDA device; the VAE trains on {:?}", s.device);
    // Checked once here, so that no step waits for the device to check its clips.
    for (i, video) in data.train.iter().enumerate() {
        ensure!(video.isfinite().all().int64_value(&[]) == 1, "training video {i} holds NaN or infinite values");
    }
    Ok(())
}

impl<'a> VaeRun<'a> {
    /// A VAE's training from its seed's initial weights; `check_inputs` has passed.
    fn new(data: &FrameSets, s: &'a VaeTrainSettings) -> Result<Self> {
        let starts = clip_starts(&data.train, s.clip_frames, 1);
        let (mut vae, store) = WanVae::random(&s.cfg, s.dtype, s.device, s.seed as i64)?;
        let z = s.cfg.z_dim;
        let identity = (Tensor::zeros([z], (Kind::Float, s.device)), Tensor::ones([z], (Kind::Float, s.device)));
        vae.set_latent_stats(&identity.0, &identity.1)?;
        let optim: OptimSection =
            toml::from_str(&format!("lr = {}\nweight_decay = 0.0\ngrad_clip = 1.0\nwarmup_steps = 20\nschedule = \"cosine\"\nmin_lr_ratio = 0.05", s.lr))?;
        let opt = AdamW::new(&store.named_parameters(), &["*".into()], &[], &optim, s.steps, Sharding::SINGLE)?;
        let graph = if s.cuda_graph { Some(GraphedStep::new(s.device, GRAPH_WARM_UP_STEPS)?) } else { None };
        Ok(Self { s, vae, store, opt, graph, starts, step: 0, seconds: 0.0, measured: None })
    }

    /// Trains on until `until` steps are done (at most the settings' steps).
    fn train_until(&mut self, data: &FrameSets, until: u64, on_log: &mut dyn FnMut(&str)) -> Result<()> {
        let (s, vae) = (self.s, &self.vae);
        let z = s.cfg.z_dim;
        // The step's losses [mse, kl] after its backward pass.
        let losses = |x: &Tensor, eps: &Tensor| -> Result<Tensor> {
            let moments = vae.encode_moments_of_finite(x)?.to_kind(Kind::Float);
            let (mu, logvar) = (moments.narrow(1, 0, z), moments.narrow(1, z, z).clamp(-30.0, 20.0));
            ensure!(eps.size() == mu.size(), "the posterior noise is {:?}, the latents {:?}", eps.size(), mu.size());
            let sample = &mu + (&logvar * 0.5).exp() * eps;
            let recon = vae.decode(&sample)?.to_kind(Kind::Float);
            let error = &recon - x;
            let mse = error.square().mean(Kind::Float);
            let kl = ((mu.square() + logvar.exp() - 1.0 - &logvar) * 0.5).mean(Kind::Float);
            let reconstruction = match s.recon_loss {
                ReconLoss::Mse => mse.shallow_clone(),
                ReconLoss::L1 => error.abs().mean(Kind::Float),
            };
            (reconstruction + &kl * s.kl_weight).f_backward()?;
            Ok(Tensor::stack(&[mse, kl], 0))
        };
        let start = Instant::now();
        let seconds_before = self.seconds;
        for step in self.step..until.min(s.steps) {
            let mut x = stack_clips(&data.train, &pick_clips(&self.starts, s.batch, s.seed, step), s.clip_frames, s.device);
            if let Some(size) = s.crop {
                x = random_windows(&x, size, s.seed, step)?;
            }
            if s.flip && keyed_rng::uniform(s.seed, step, Purpose::Augment) < 0.5 {
                x = x.flip([-1]);
            }
            let (xs, ss) = (x.size(), s.cfg.spatial_stride());
            let eps_shape = [xs[0], z, 1 + (xs[2] - 1) / s.cfg.temporal_stride(), xs[3] / ss, xs[4] / ss];
            let eps = keyed_rng::normal(&eps_shape, s.seed, step, Purpose::Noise).to_device(s.device);
            let step_losses = match self.graph.as_mut() {
                None => losses(&x, &eps)?,
                Some(g) => g.run(&[&x, &eps], |t| losses(&t[0], &t[1])).context("the VAE's training step as a CUDA graph (--cuda-graph)")?,
            };
            let (mse, kl) = (step_losses.get(0), step_losses.get(1));
            self.opt.collect_grads();
            let report = self.opt.step(1.0, &mut LocalCollective::new())?;
            self.step = step + 1;
            self.seconds = seconds_before + start.elapsed().as_secs_f64();
            let last = step + 1 == s.steps;
            if (step + 1) % 50 == 0 || last || report.is_none() {
                let m = mse.double_value(&[]);
                on_log(&format!(
                    "step {:>5}/{}  mse {m:.5} (PSNR {:.2} dB)  kl {:.4}  {:.2} s/step{}",
                    step + 1,
                    s.steps,
                    10.0 * (4.0 / m).log10(),
                    kl.double_value(&[]),
                    self.seconds / (step + 1) as f64,
                    if report.is_none() { "  (non-finite: update skipped)" } else { "" }
                ));
            }
            if s.eval_every > 0 && (step + 1) % s.eval_every == 0 && !last {
                let p = reconstruction_psnr(vae, &data.holdout, s.clip_frames, s.device)?;
                self.measured = Some((step + 1, p));
                self.seconds = seconds_before + start.elapsed().as_secs_f64();
                on_log(&format!("step {:>5}: held-out reconstruction PSNR {p:.2} dB", step + 1));
            }
        }
        Ok(())
    }

    /// The held-out PSNR at the current step (measured once per step).
    fn holdout_psnr(&mut self, data: &FrameSets) -> Result<f64> {
        if let Some((_, p)) = self.measured.filter(|&(step, _)| step == self.step) {
            return Ok(p);
        }
        let start = Instant::now();
        let p = reconstruction_psnr(&self.vae, &data.holdout, self.s.clip_frames, self.s.device)?;
        self.seconds += start.elapsed().as_secs_f64();
        self.measured = Some((self.step, p));
        Ok(p)
    }

    /// The latent statistics and the final PSNRs; the run must have done all its steps.
    fn finish(mut self, data: &FrameSets) -> Result<TrainedVae> {
        let s = self.s;
        ensure!(self.step == s.steps, "the VAE from seed {} stopped at step {} of {}", s.seed, self.step, s.steps);
        let start = Instant::now();
        let (mean, std) = latent_statistics(&self.vae, &data.train, s.clip_frames, s.device)?;
        self.vae.set_latent_stats(&mean, &std)?;
        let train_psnr = reconstruction_psnr(&self.vae, &data.train, s.clip_frames, s.device)?;
        let holdout_psnr = reconstruction_psnr(&self.vae, &data.holdout, s.clip_frames, s.device)?;
        let report = VaeTrainReport {
            train_psnr,
            holdout_psnr,
            seconds: self.seconds + start.elapsed().as_secs_f64(),
            steps: s.steps,
            clip_frames: s.clip_frames,
            seed: s.seed,
            candidates: vec![(s.seed, holdout_psnr)],
            candidates_step: s.steps,
        };
        let params = self.store.named_parameters().into_iter().map(|(n, t)| (n, t.detach().to_kind(Kind::Float))).collect();
        Ok(TrainedVae { vae: self.vae, params, report })
    }
}

/// Trains one VAE from each seed (same frames and settings) and keeps the one that reconstructs the
/// held-out frames best. Some initialisations settle about 1 dB under the others, and a world model
/// trained on their latents simulates worse (docs/fidelity.md at abaed68, run 31); the held-out
/// PSNR tells them apart before anything trains on the latents, and early: the gap shows from the
/// first few hundred steps. With `choose_at` = Some(k) < the settings' steps every candidate trains
/// k steps, the one with the best held-out PSNR then goes on alone to the end (the others are
/// dropped there; its training is the one an uninterrupted run of its seed does), so N candidates
/// cost (N - 1) k steps more than one VAE; otherwise each trains in full, one after another, and
/// the best at the end is kept. Only the kept one gets its latent statistics and training PSNR. The
/// report's candidates hold every seed's held-out PSNR where it was compared.
pub fn train_best_vae(
    data: &FrameSets,
    s: &VaeTrainSettings,
    seeds: &[u64],
    choose_at: Option<u64>,
    on_log: &mut dyn FnMut(&str),
) -> Result<TrainedVae> {
    ensure!(!seeds.is_empty(), "no seed to train a VAE from");
    check_inputs(data, s)?;
    let start = Instant::now();
    let settings: Vec<VaeTrainSettings> = seeds.iter().map(|&seed| VaeTrainSettings { seed, ..s.clone() }).collect();
    let n = seeds.len();
    if let Some(k) = choose_at {
        ensure!(k > 0, "the candidate VAEs must train at least one step before one is chosen");
        if n > 1 && k >= s.steps {
            on_log(&format!("choosing at step {k} is at or past the last step ({}): every candidate trains in full", s.steps));
        }
    }
    let stop = choose_at.filter(|&k| n > 1 && k < s.steps).unwrap_or(s.steps);
    // A non-finite PSNR (a diverged candidate) never wins.
    let beats = |psnr: f64, other: f64| psnr.is_finite() && (!other.is_finite() || psnr > other);
    // The leading run so far: only the one kept gets its latent statistics and final PSNRs.
    let mut leader: Option<(VaeRun, f64)> = None;
    let mut candidates = Vec::with_capacity(n);
    for (i, settings) in settings.iter().enumerate() {
        let seed = settings.seed;
        if n > 1 {
            on_log(&format!("candidate {}/{n}: seed {seed}", i + 1));
        }
        let mut run = VaeRun::new(data, settings).with_context(|| format!("the VAE from seed {seed}"))?;
        run.train_until(data, stop, on_log).with_context(|| format!("the VAE from seed {seed}"))?;
        // A single VAE is compared with nothing: its held-out PSNR is measured once, at the end.
        let psnr = if n > 1 {
            let psnr = run.holdout_psnr(data).with_context(|| format!("the VAE from seed {seed}"))?;
            on_log(&format!("candidate {}/{n}: seed {seed}: held-out reconstruction PSNR {psnr:.2} dB at step {stop}", i + 1));
            candidates.push((seed, psnr));
            psnr
        } else {
            f64::NAN
        };
        if leader.as_ref().map_or(true, |(_, lead)| beats(psnr, *lead)) {
            leader = Some((run, psnr));
        }
    }
    let (mut run, psnr) = leader.context("no candidate trained")?;
    let seed = run.s.seed;
    if n > 1 {
        ensure!(psnr.is_finite(), "every candidate VAE's held-out PSNR is non-finite at step {stop}: {candidates:?}");
    }
    if stop < s.steps {
        on_log(&format!("seed {seed} goes on from step {stop} to {}", s.steps));
        run.train_until(data, s.steps, on_log).with_context(|| format!("the VAE from seed {seed}"))?;
    }
    let mut best = run.finish(data).with_context(|| format!("the VAE from seed {seed}"))?;
    if n > 1 {
        ensure!(best.report.holdout_psnr.is_finite(), "every candidate VAE's held-out PSNR is non-finite: {candidates:?}");
        best.report.candidates = candidates;
        best.report.candidates_step = stop;
    }
    best.report.seconds = start.elapsed().as_secs_f64();
    Ok(best)
}

/// Per-channel mean and std of the encoder's posterior means over the training clips.
fn latent_statistics(vae: &WanVae, videos: &[Tensor], frames: usize, device: Device) -> Result<(Tensor, Tensor)> {
    let z = vae.cfg.z_dim;
    let mut all = Vec::new();
    for chunk in clip_starts(videos, frames, frames).chunks(4) {
        let x = stack_clips(videos, chunk, frames, device);
        let mu = tch::no_grad(|| vae.encode_moments(&x))?.narrow(1, 0, z).to_kind(Kind::Float);
        all.push(mu.transpose(0, 1).reshape([z, -1]));
    }
    let mu = Tensor::cat(&all, 1);
    Ok((mu.mean_dim(&[1i64][..], false, Kind::Float), mu.std_dim(&[1i64][..], true, false).clamp_min(1e-4)))
}

/// Writes the VAE (weights, latent statistics, config and PSNR in the metadata) atomically.
pub fn save_trained_vae(trained: &TrainedVae, path: &Path) -> Result<()> {
    let (vae, report) = (&trained.vae, &trained.report);
    let (mean, std) = vae.latent_stats();
    let mut tensors: Vec<(String, Tensor)> = trained.params.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
    tensors.push(("latents_mean".into(), mean.to_kind(Kind::Float)));
    tensors.push(("latents_std".into(), std.to_kind(Kind::Float)));
    let meta = BTreeMap::from([
        (TRAINED_CONFIG_KEY.to_string(), serde_json::to_string(&vae.cfg)?),
        ("bwm.holdout_psnr_db".to_string(), format!("{:.3}", report.holdout_psnr)),
        ("bwm.train_psnr_db".to_string(), format!("{:.3}", report.train_psnr)),
        ("bwm.steps".to_string(), report.steps.to_string()),
        ("bwm.seed".to_string(), report.seed.to_string()),
        ("bwm.candidates".to_string(), report.candidates.iter().map(|(seed, p)| format!("{seed}:{p:.3}")).collect::<Vec<_>>().join(",")),
        ("bwm.candidates_step".to_string(), report.candidates_step.to_string()),
        (TRAINED_CLIP_FRAMES_KEY.to_string(), report.clip_frames.to_string()),
    ]);
    bwm_checkpoints::write_tensors_replacing(path, &tensors, &meta)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_windows_are_windows_of_each_clip_at_varying_offsets() {
        let clips = Tensor::arange(2 * 3 * 1 * 8 * 12, (Kind::Float, Device::Cpu)).view([2, 3, 1, 8, 12]);
        let mut corners = std::collections::BTreeSet::new();
        for step in 0..20 {
            let w = random_windows(&clips, (4, 3), 7, step).unwrap();
            assert_eq!(w.size(), [2, 3, 1, 3, 4]);
            for b in 0..2 {
                // Values encode positions: the window's first element names its corner.
                let first = w.get(b).double_value(&[0, 0, 0, 0]) as i64 - b * 3 * 8 * 12;
                let (y, x) = (first / 12, first % 12);
                assert!(y <= 5 && x <= 8);
                assert!(w.get(b).equal(&clips.get(b).narrow(2, y, 3).narrow(3, x, 4)));
                corners.insert((y, x));
            }
        }
        assert!(corners.len() > 10, "offsets vary: {corners:?}");
        assert!(random_windows(&clips, (16, 3), 7, 0).is_err());
    }

    /// A width-4 VAE, one step of one clip of `clip_frames` on the CPU.
    fn tiny_settings(clip_frames: usize) -> VaeTrainSettings {
        VaeTrainSettings {
            cfg: VaeConfig::with_width(4, 4),
            clip_frames,
            batch: 1,
            steps: 1,
            lr: 1e-3,
            kl_weight: 1e-6,
            seed: 0,
            device: Device::Cpu,
            eval_every: 0,
            flip: false,
            crop: None,
            dtype: Kind::Float,
            recon_loss: ReconLoss::Mse,
            cuda_graph: false,
        }
    }

    #[test]
    fn trains_on_windows_and_measures_whole_frames() {
        let video = |seed: i64| {
            bwm_model::vb::with_seed(seed, || Tensor::rand([3, 9, 32, 48], (Kind::Float, Device::Cpu))) * 2.0 - 1.0
        };
        let data = FrameSets { train: vec![video(1)], holdout: vec![video(2)] };
        let s = VaeTrainSettings { batch: 2, steps: 2, flip: true, crop: Some((16, 16)), ..tiny_settings(5) };
        let mut lines = Vec::new();
        let trained = train_vae(&data, &s, &mut |l| lines.push(l.to_string())).unwrap();
        assert!(trained.report.holdout_psnr.is_finite() && trained.report.train_psnr.is_finite(), "{lines:?}");
        assert!(lines.iter().any(|l| l.contains("step     2/2")), "{lines:?}");
    }

    #[test]
    fn trains_in_bf16_against_fp32_masters_and_saves_f32_weights() {
        let video = bwm_model::vb::with_seed(3, || Tensor::rand([3, 5, 16, 16], (Kind::Float, Device::Cpu))) * 2.0 - 1.0;
        let data = FrameSets { train: vec![video.shallow_clone()], holdout: vec![video] };
        let s = VaeTrainSettings { steps: 3, lr: 1e-2, dtype: Kind::BFloat16, ..tiny_settings(5) };
        let (initial, _) = WanVae::random(&s.cfg, Kind::BFloat16, Device::Cpu, s.seed as i64).unwrap();
        let trained = train_vae(&data, &s, &mut |_| {}).unwrap();
        assert!(trained.report.holdout_psnr.is_finite(), "{}", trained.report.holdout_psnr);
        assert!(trained.params.iter().all(|(_, t)| t.kind() == Kind::Float), "the file holds f32 weights");
        // The weights moved: the updates reached the bf16 weights from the fp32 masters.
        let before = initial.encode_moments(&data.train[0].unsqueeze(0)).unwrap();
        let after = trained.vae.encode_moments(&data.train[0].unsqueeze(0)).unwrap();
        assert_eq!(after.kind(), Kind::BFloat16);
        assert!(!before.equal(&after), "three steps changed the encoder");
        let dir = bwm_testdir::TestDir::new("vae-bf16");
        let path = dir.join("vae.safetensors");
        save_trained_vae(&trained, &path).unwrap();
        // The f32 file holds the bf16 weights exactly: loaded back in bf16 it computes the same.
        let loaded = WanVae::load_any(&path, Kind::BFloat16, Device::Cpu).unwrap();
        let x = data.holdout[0].unsqueeze(0);
        assert!(loaded.encode_moments(&x).unwrap().equal(&trained.vae.encode_moments(&x).unwrap()));
        assert!(train_vae(&data, &VaeTrainSettings { dtype: Kind::Half, ..tiny_settings(5) }, &mut |_| {}).is_err());
    }

    #[test]
    fn the_best_of_several_seeds_is_kept_as_that_seed_alone_trains_it_and_the_file_names_them_all() {
        let data = random_clips(5, 16);
        let s = VaeTrainSettings { steps: 4, lr: 1e-2, ..tiny_settings(5) };
        let mut log = Vec::new();
        let best = train_best_vae(&data, &s, &[3, 4, 5], None, &mut |l| log.push(l.to_string())).unwrap();
        let tried = &best.report.candidates;
        assert_eq!(tried.iter().map(|c| c.0).collect::<Vec<_>>(), [3, 4, 5]);
        assert!(tried.windows(2).any(|w| w[0].1 != w[1].1), "the seeds train different VAEs: {tried:?}");
        let top = assert_kept_as_alone(&data, &s, &best);
        // Compared before the kept one's latent statistics are set, which the round trip
        // normalises by and back: the same PSNR up to rounding.
        assert!((best.report.holdout_psnr - top.1).abs() < 1e-3, "trained in full, the PSNR compared is the final one: {} / {}", best.report.holdout_psnr, top.1);
        assert_eq!(best.report.candidates_step, 4);
        assert!(log.iter().any(|l| l.starts_with("candidate 3/3: seed 5: held-out reconstruction PSNR") && l.ends_with("at step 4")), "{log:?}");
        let dir = bwm_testdir::TestDir::new("vae-best-of");
        let path = dir.join("vae.safetensors");
        save_trained_vae(&best, &path).unwrap();
        let meta = bwm_checkpoints::tensor_file::read_metadata(&path).unwrap();
        assert_eq!(meta["bwm.seed"], top.0.to_string());
        let listed: Vec<&str> = meta["bwm.candidates"].split(',').collect();
        assert_eq!(listed.len(), 3);
        assert!(listed[0].starts_with("3:") && listed[2].starts_with("5:"), "{listed:?}");
        assert!(train_best_vae(&data, &s, &[], None, &mut |_| {}).err().unwrap().to_string().contains("no seed"));
    }

    #[test]
    fn candidates_chosen_part_way_leave_the_best_to_train_on_as_its_seed_alone_does() {
        let data = random_clips(5, 16);
        let s = VaeTrainSettings { steps: 5, lr: 1e-2, eval_every: 1, ..tiny_settings(5) };
        let mut log = Vec::new();
        let best = train_best_vae(&data, &s, &[3, 4, 5], Some(2), &mut |l| log.push(l.to_string())).unwrap();
        let tried = &best.report.candidates;
        assert_eq!(tried.iter().map(|c| c.0).collect::<Vec<_>>(), [3, 4, 5]);
        // Each candidate's PSNR is the one after two steps (the eval of step 2 measures the same weights).
        for (seed, psnr) in tried {
            let at_two = log.iter().skip_while(|l| *l != &format!("candidate {}/3: seed {seed}", seed - 2)).find(|l| l.starts_with("step     2: held-out")).unwrap();
            assert!(at_two.contains(&format!("{psnr:.2} dB")), "{at_two} / {psnr}: {log:?}");
        }
        let top = assert_kept_as_alone(&data, &s, &best);
        assert_eq!(best.report.candidates_step, 2);
        assert!(log.iter().any(|l| l == &format!("seed {} goes on from step 2 to 5", top.0)), "{log:?}");
        assert_eq!(log.iter().filter(|l| l.starts_with("step     5/5")).count(), 1, "only the chosen one trains to the end: {log:?}");
        let err = train_best_vae(&data, &s, &[3, 4], Some(0), &mut |_| {}).err().unwrap();
        assert!(err.to_string().contains("at least one step"), "{err}");
    }

    #[test]
    fn a_cuda_graph_on_the_cpu_is_refused_by_name_and_a_nonfinite_frame_before_training() {
        let video = Tensor::zeros([3, 5, 16, 16], (Kind::Float, Device::Cpu));
        let data = FrameSets { train: vec![video.shallow_clone()], holdout: vec![video.shallow_clone()] };
        let err = train_vae(&data, &VaeTrainSettings { cuda_graph: true, ..tiny_settings(5) }, &mut |_| {}).err().unwrap();
        assert!(err.to_string().contains("--cuda-graph"), "{err}");
        let bad = video.copy();
        let _ = bad.get(0).get(2).get(3).get(4).fill_(f64::NAN);
        let data = FrameSets { train: vec![video.shallow_clone(), bad], holdout: vec![video] };
        let err = train_vae(&data, &tiny_settings(5), &mut |_| {}).err().unwrap();
        assert!(err.to_string().contains("training video 1 holds NaN"), "{err}");
    }

    /// On a CUDA machine: training with the step replayed from a CUDA graph gives the eager
    /// training's losses and weights (cuDNN's backward convolutions may sum in another order, so
    /// closely, not bit for bit). `scripts/gpu/unit.sh` runs it (`cuda_clips` says what happens
    /// without CUDA).
    #[test]
    #[ignore = "needs a CUDA device (scripts/gpu/unit.sh)"]
    fn the_cuda_graph_replays_train_as_the_eager_steps_do() {
        let Some((_gpu, data)) = cuda_clips("the graph's training") else { return };
        let train = |cuda_graph: bool| {
            // A held-out measurement runs eagerly between two replays.
            let s = VaeTrainSettings { device: Device::Cuda(0), batch: 2, steps: 6, flip: true, eval_every: 4, cuda_graph, ..tiny_settings(5) };
            let mut log = Vec::new();
            let t = train_vae(&data, &s, &mut |l| log.push(l.to_string())).unwrap();
            (t, log)
        };
        let (eager, eager_log) = train(false);
        let (graphed, graph_log) = train(true);
        assert_eq!(eager_log.len(), graph_log.len());
        assert_weights_as_eager(&eager, &graphed);
        assert!((eager.report.holdout_psnr - graphed.report.holdout_psnr).abs() < 0.01, "{} vs {}", eager.report.holdout_psnr, graphed.report.holdout_psnr);
    }

    #[test]
    fn a_run_resumed_after_another_trained_is_its_uninterrupted_run() {
        let data = random_clips(5, 16);
        let s = VaeTrainSettings { steps: 4, lr: 1e-2, ..tiny_settings(5) };
        let other = VaeTrainSettings { seed: 9, ..s.clone() };
        let mut paused = VaeRun::new(&data, &s).unwrap();
        paused.train_until(&data, 2, &mut |_| {}).unwrap();
        let mut between = VaeRun::new(&data, &other).unwrap();
        between.train_until(&data, 4, &mut |_| {}).unwrap();
        paused.train_until(&data, 4, &mut |_| {}).unwrap();
        assert!(VaeRun::new(&data, &s).unwrap().finish(&data).err().unwrap().to_string().contains("stopped at step 0 of 4"));
        let (resumed, alone) = (paused.finish(&data).unwrap(), train_vae(&data, &s, &mut |_| {}).unwrap());
        // A resume that lost the schedule, the optimizer's moments or its batches would move
        // weights by about lr (1e-2); the same arithmetic in another summation order by 1e-8.
        for ((name, a), (_, b)) in alone.params.iter().zip(&resumed.params) {
            assert!((a - b).abs().max().double_value(&[]) < 1e-6, "{name} differs after the pause");
        }
    }

    /// On a CUDA machine: candidates chosen part way each hold their own graph (two alive at
    /// once), and the chosen one replays its own on to the end, as the eager candidates train.
    #[test]
    #[ignore = "needs a CUDA device (scripts/gpu/unit.sh)"]
    fn the_cuda_graph_candidates_chosen_part_way_train_as_the_eager_ones() {
        let Some((_gpu, data)) = cuda_clips("the graph's candidates") else { return };
        let train = |cuda_graph: bool| {
            let s = VaeTrainSettings { device: Device::Cuda(0), batch: 2, steps: 8, cuda_graph, ..tiny_settings(5) };
            train_best_vae(&data, &s, &[0, 1], Some(4), &mut |_| {}).unwrap()
        };
        let (eager, graphed) = (train(false), train(true));
        let (ce, cg) = (&eager.report.candidates, &graphed.report.candidates);
        for ((seed, a), (_, b)) in ce.iter().zip(cg) {
            assert!((a - b).abs() < 0.01, "seed {seed}'s PSNR at the choice: eager {a}, graph {b}");
        }
        // Two candidates within twice the runs' difference may be chosen either way.
        if (ce[0].1 - ce[1].1).abs() < 0.02 || (cg[0].1 - cg[1].1).abs() < 0.02 {
            return;
        }
        assert_eq!(eager.report.seed, graphed.report.seed, "{ce:?} / {cg:?}");
        assert_weights_as_eager(&eager, &graphed);
    }

    /// Two training and one held-out random clip of 9 frames at 32x32 where CUDA is, with the GPU
    /// to the test alone while it holds the guard: a capture fails when another thread's CUDA work
    /// meanwhile waits on the device (a parallel test's copy to it failed one). Without CUDA there
    /// is nothing to compare a graph with: `None`, after the test failed if BWM_REQUIRE names
    /// cuda (scripts/gpu/unit.sh) or was logged as skipped otherwise.
    fn cuda_clips(what: &str) -> Option<(std::sync::MutexGuard<'static, ()>, FrameSets)> {
        static GPU: std::sync::Mutex<()> = std::sync::Mutex::new(());
        if !bwm_testdir::need(bwm_testdir::Dep::Cuda, (!tch::Cuda::is_available()).then(|| format!("libtorch sees no CUDA device to compare {what} on"))) {
            return None;
        }
        let gpu = GPU.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        Some((gpu, random_clips(9, 32)))
    }

    /// Two training videos and one held-out of `frames` random frames, `side` pixels square. Drawn
    /// under `with_seed`'s lock: a parallel test's draws between a seed and its use would change
    /// a VAE's initial weights that `WanVae::random` draws under it.
    fn random_clips(frames: i64, side: i64) -> FrameSets {
        let video = |seed: i64| bwm_model::vb::with_seed(seed, || Tensor::rand([3, frames, side, side], (Kind::Float, Device::Cpu))) * 2.0 - 1.0;
        FrameSets { train: vec![video(1), video(2)], holdout: vec![video(3)] }
    }

    /// The candidate with the best PSNR, and that the kept VAE's weights are its seed's alone.
    fn assert_kept_as_alone(data: &FrameSets, s: &VaeTrainSettings, best: &TrainedVae) -> (u64, f64) {
        let top = best.report.candidates.iter().cloned().fold((0, f64::NEG_INFINITY), |a, c| if c.1 > a.1 { c } else { a });
        assert_eq!(best.report.seed, top.0, "{:?}", best.report.candidates);
        let alone = train_vae(data, &VaeTrainSettings { seed: top.0, ..s.clone() }, &mut |_| {}).unwrap();
        assert_eq!(best.report.holdout_psnr, alone.report.holdout_psnr);
        for ((name, a), (_, b)) in alone.params.iter().zip(&best.params) {
            assert!((a - b).abs().max().double_value(&[]) < 1e-6, "{name}: the kept VAE is not seed {}'s alone", top.0);
        }
        top
    }

    /// An update moves a weight by about lr; a replay that read stale inputs or lost the gradients
    /// would move some by several lr over the replayed steps.
    fn assert_weights_as_eager(eager: &TrainedVae, graphed: &TrainedVae) {
        let lr = tiny_settings(5).lr;
        for ((name, a), (_, b)) in eager.params.iter().zip(&graphed.params) {
            let diff = (a - b).abs().max().double_value(&[]);
            assert!(diff <= 0.5 * lr, "{name}: the graph's weights differ from the eager ones by {diff} (lr {lr})");
        }
    }

    #[test]
    fn the_l1_loss_drives_the_updates_and_lowers_the_l1_error() {
        let video = bwm_model::vb::with_seed(5, || Tensor::rand([3, 5, 16, 16], (Kind::Float, Device::Cpu))) * 2.0 - 1.0;
        let x = video.unsqueeze(0);
        let data = FrameSets { train: vec![video.shallow_clone()], holdout: vec![video] };
        let settings = |steps, recon_loss| VaeTrainSettings { steps, lr: 1e-2, recon_loss, ..tiny_settings(5) };
        let l1_error = |vae: &WanVae| (vae.decode(&vae.encode(&x).unwrap()).unwrap() - &x).abs().mean(Kind::Float).double_value(&[]);
        let mse_1 = train_vae(&data, &settings(1, ReconLoss::Mse), &mut |_| {}).unwrap();
        let l1_1 = train_vae(&data, &settings(1, ReconLoss::L1), &mut |_| {}).unwrap();
        let moments = |t: &TrainedVae| t.vae.encode_moments(&x).unwrap();
        assert!(!moments(&mse_1).equal(&moments(&l1_1)), "the same first step under both losses");
        let l1_30 = train_vae(&data, &settings(30, ReconLoss::L1), &mut |_| {}).unwrap();
        let (before, after) = (l1_error(&l1_1.vae), l1_error(&l1_30.vae));
        assert!(after < 0.9 * before, "30 L1 steps: mean absolute error {before:.4} -> {after:.4}");
        assert_eq!("l1".parse::<ReconLoss>(), Ok(ReconLoss::L1));
        assert_eq!("mse".parse::<ReconLoss>(), Ok(ReconLoss::Mse));
        assert!("lpips".parse::<ReconLoss>().unwrap_err().contains("known: mse, l1"));
    }

    /// The motion loss was removed (issue 69): its name is refused, saying so and why.
    #[test]
    fn the_removed_motion_loss_is_refused_by_name_with_the_reason() {
        let e = "motion".parse::<ReconLoss>().unwrap_err();
        assert!(e.contains("was removed") && e.contains("run 34") && e.contains("docs/fidelity.md"), "{e}");
    }

    #[test]
    fn the_saved_vae_records_its_clip_length_and_prepare_can_warn_of_longer_clips() {
        let (vae, store) = WanVae::random(&VaeConfig::with_width(4, 4), Kind::Float, Device::Cpu, 0).unwrap();
        let report = VaeTrainReport { train_psnr: 1.0, holdout_psnr: 1.0, seconds: 0.0, steps: 1, clip_frames: 9, seed: 0, candidates: vec![(0, 1.0)], candidates_step: 1 };
        let dir = bwm_testdir::TestDir::new("vae-clip-frames");
        let path = dir.join("vae.safetensors");
        save_trained_vae(&TrainedVae { vae, params: store.named_parameters(), report }, &path).unwrap();
        let trained = WanVae::load_any(&path, Kind::Float, Device::Cpu).unwrap().trained_clip_frames;
        assert_eq!(trained, Some(9));
        assert_eq!(bwm_model::vae::clip_length_warning(trained, 9), None);
        assert_eq!(bwm_model::vae::clip_length_warning(trained, 5), None);
        let w = bwm_model::vae::clip_length_warning(trained, 33).unwrap();
        assert!(w.contains("trained on 9-frame clips") && w.contains("--clip-frames 33"), "{w}");
        assert_eq!(bwm_model::vae::clip_length_warning(None, 33), None, "the published VAE records no clip length");
    }

    #[test]
    fn held_out_videos_shorter_than_a_clip_are_refused_before_training() {
        let video = |frames: i64| Tensor::zeros([3, frames, 16, 16], (Kind::Float, Device::Cpu));
        let data = FrameSets { train: vec![video(33)], holdout: vec![video(12)] };
        let s = tiny_settings(33);
        let mut lines = Vec::new();
        let err = train_vae(&data, &s, &mut |l| lines.push(l.to_string())).err().expect("a 12-frame hold-out cannot hold a 33-frame clip");
        assert!(err.to_string().contains("at most 12 frames") && err.to_string().contains("--holdout-tail"), "{err}");
        assert!(lines.is_empty(), "no training step ran: {lines:?}");
    }
}
