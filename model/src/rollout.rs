//! Autoregressive rollout (the lightweight inference module): from the episode's first frame x0,
//! optional history frames and a sequence of normalized actions, generate the video chunk by
//! chunk. Each chunk is conditioned on a freshly encoded clip [x0, h1..hH] of the last H frames
//! actually shown (generated latents are never reused directly), with the actions that were
//! actually applied to those frames; slots before the episode start hold x0 and action a0.
//! Pixel frames are [3, F, H, W] f32 in [-1, 1]; actions are [rows, d_a], normalized.

use std::cell::RefCell;
use std::collections::VecDeque;
use std::rc::Rc;
use std::time::Instant;

use anyhow::{ensure, Context, Result};
use tch::{Device, Kind, Tensor};

use crate::bwm::BwmModel;
use crate::keyed_rng::{self, Purpose};
use crate::light_decoder::LightDecoder;
use crate::sampler::{sample_chunk, Denoiser, Eager};
use crate::schedule::{FlowSchedule, Solver, DEFAULT_SHIFT, NUM_TRAIN_TIMESTEPS};
use crate::vae::WanVae;

/// The history-noise level the BWM release trains and samples with (`FlowSchedule::history_sigma`).
pub fn default_history_sigma() -> f64 {
    history_sigma_for_shift(DEFAULT_SHIFT)
}

/// The history-noise level a run trains with when it does not set one: the training grid's sigma
/// 50 steps from clean, which moves with the grid's shift.
pub fn history_sigma_for_shift(shift: f64) -> f64 {
    FlowSchedule::training(NUM_TRAIN_TIMESTEPS, shift).history_sigma()
}

#[derive(Debug, Clone, PartialEq)]
pub struct RolloutSpec {
    /// H: history pixel frames in each chunk's condition (a multiple of 4, may be 0).
    pub history: usize,
    /// K: pixel frames generated per chunk (a positive multiple of 4).
    pub future: usize,
    /// Sampler steps per chunk.
    pub steps: usize,
    pub shift: f64,
    /// How the sampler steps (Euler: the reference's).
    pub solver: Solver,
    /// Noise level of the history latents in the prefix (drawn once per chunk); None: clean.
    pub history_sigma: Option<f64>,
    /// Classifier-free guidance by the actions (`sample_chunk`); 1: off.
    pub guidance: f64,
    pub seed: u64,
}

impl RolloutSpec {
    /// BWM defaults: 50 steps, shift 5, history noise 0.2083.
    pub fn new(history: usize, future: usize) -> Self {
        Self { history, future, steps: 50, shift: DEFAULT_SHIFT, solver: Solver::Euler, history_sigma: Some(default_history_sigma()), guidance: 1.0, seed: 0 }
    }

    pub fn validate(&self) -> Result<()> {
        ensure!(self.future > 0 && self.future % 4 == 0, "rollout future {} must be a positive multiple of 4", self.future);
        ensure!(self.history % 4 == 0, "rollout history {} must be a multiple of 4", self.history);
        ensure!(self.steps > 0, "rollout needs at least one sampler step");
        ensure!(self.shift > 0.0, "sampler shift {} must be positive", self.shift);
        crate::sampler::validate_guidance(self.guidance)?;
        if let Some(s) = self.history_sigma {
            ensure!((0.0..=1.0).contains(&s), "history sigma {s} must lie in [0, 1]");
        }
        Ok(())
    }

    /// Latent frames of the condition prefix: x0, then H/4 history latents.
    pub fn condition_latents(&self) -> usize {
        1 + self.history / 4
    }
}

/// One generated chunk and the actions that produced it, row by row.
pub struct Chunk {
    /// 0 for the first chunk of the rollout.
    pub index: usize,
    /// [3, n, H, W] f32 in [-1, 1] on the CPU; n = the number of actions asked for.
    pub frames: Tensor,
    /// [n, d_a] f32 on the CPU.
    pub actions: Tensor,
    /// Seconds in the encode of the condition clip, the sampler (DiT) and the decode (with the
    /// copy to the host); NaN for a chunk begun with [`Rollout::begin_chunks`], whose phases were
    /// queued without waiting for them.
    pub encode_seconds: f64,
    pub dit_seconds: f64,
    pub decode_seconds: f64,
}

/// A batch's chunk queued on the device by [`Rollout::begin_chunks`], not yet read back.
pub struct PendingChunks {
    /// [B, 3, K, H, W] f32 in [-1, 1], where the model runs.
    frames: Tensor,
    /// Each rollout's actions [n, d_a] (CPU).
    applied: Vec<Tensor>,
    encode_seconds: f64,
    dit_seconds: f64,
    decode_seconds: f64,
}

pub struct Rollout<'m> {
    model: &'m BwmModel,
    vae: &'m WanVae,
    spec: RolloutSpec,
    schedule: FlowSchedule,
    x0: Tensor,
    a0: Tensor,
    /// The last H frames shown ([3, H, W] each, CPU) with the action applied to each.
    history: VecDeque<(Tensor, Tensor)>,
    chunks: usize,
    /// Synchronizes the device before reading a timer (CUDA work is asynchronous).
    sync: Box<dyn Fn()>,
    /// Runs the sampler's forward passes; None: eagerly.
    denoiser: Option<SharedDenoiser<'m>>,
    /// Decodes the generated latents instead of the VAE's decoder (the VAE still encodes).
    light_decoder: Option<&'m LightDecoder>,
}

/// A denoiser that several rollouts (and their batches) share.
pub type SharedDenoiser<'m> = Rc<RefCell<dyn Denoiser + 'm>>;

impl<'m> Rollout<'m> {
    /// Starts a rollout at the episode's first frame `x0` `[3, H, W]` with its action `a0` `[d_a]`.
    pub fn new(model: &'m BwmModel, vae: &'m WanVae, spec: RolloutSpec, x0: &Tensor, a0: &Tensor) -> Result<Self> {
        spec.validate()?;
        let d = model.cfg.action.action_dim;
        let xs = x0.size();
        ensure!(xs.len() == 3 && xs[0] == 3, "x0 must be [3, H, W], got {xs:?}");
        ensure!(a0.size() == [d], "a0 must hold {d} action values, got shape {:?}", a0.size());
        ensure!(
            xs[1] % 32 == 0 && xs[2] % 32 == 0,
            "frames are {}x{} (HxW); rollouts need multiples of 32 (DiT patch x VAE stride)",
            xs[1],
            xs[2]
        );
        let device = model.store.device();
        let sync: Box<dyn Fn()> = match device {
            Device::Cuda(i) => Box::new(move || tch::Cuda::synchronize(i as i64)),
            _ => Box::new(|| {}),
        };
        Ok(Self {
            model,
            vae,
            schedule: FlowSchedule::inference(spec.steps, spec.shift).with_solver(spec.solver),
            spec,
            x0: x0.to_device(Device::Cpu).to_kind(Kind::Float),
            a0: a0.to_device(Device::Cpu).to_kind(Kind::Float),
            history: VecDeque::new(),
            chunks: 0,
            sync,
            denoiser: None,
            light_decoder: None,
        })
    }

    /// This rollout with the sampler's forward passes run by `denoiser` (a batch of rollouts
    /// advanced together must share one).
    pub fn with_denoiser(mut self, denoiser: SharedDenoiser<'m>) -> Self {
        self.denoiser = Some(denoiser);
        self
    }

    /// This rollout with its chunks decoded by `decoder` instead of the VAE's decoder (a batch of
    /// rollouts advanced together must share one). It must read the VAE's latents
    /// ([`LightDecoder::check_vae`]).
    pub fn with_light_decoder(mut self, decoder: &'m LightDecoder) -> Result<Self> {
        decoder.check_vae(&self.vae.cfg)?;
        self.light_decoder = Some(decoder);
        Ok(self)
    }

    /// Frames already seen after x0 ([3, T, H, W]) with their actions ([T, d_a]); the last H are
    /// kept as the first chunk's history.
    pub fn with_history(mut self, frames: &Tensor, actions: &Tensor) -> Result<Self> {
        let (fs, as_) = (frames.size(), actions.size());
        ensure!(
            fs.len() == 4 && fs[0] == 3 && fs[2..] == self.x0.size()[1..],
            "history frames must be [3, T, {}, {}], got {fs:?}",
            self.x0.size()[1],
            self.x0.size()[2]
        );
        ensure!(
            as_.len() == 2 && as_[0] == fs[1] && as_[1] == self.a0.size()[0],
            "history actions must be [{}, {}] (one per history frame), got {as_:?}",
            fs[1],
            self.a0.size()[0]
        );
        for t in 0..fs[1] {
            self.push(frames.select(1, t), actions.get(t));
        }
        Ok(self)
    }

    pub fn spec(&self) -> &RolloutSpec {
        &self.spec
    }

    fn push(&mut self, frame: Tensor, action: Tensor) {
        self.history.push_back((frame.to_device(Device::Cpu).to_kind(Kind::Float), action.to_device(Device::Cpu).to_kind(Kind::Float)));
        while self.history.len() > self.spec.history {
            self.history.pop_front();
        }
    }

    /// The condition clip [3, 1+H, H, W] and its actions [1+H, d_a]: x0, then the last H frames,
    /// padded with x0 (action a0) where fewer have been shown.
    pub fn condition(&self) -> (Tensor, Tensor) {
        let pad = self.spec.history - self.history.len();
        let mut frames: Vec<Tensor> = (0..=pad).map(|_| self.x0.shallow_clone()).collect();
        let mut actions: Vec<Tensor> = (0..=pad).map(|_| self.a0.shallow_clone()).collect();
        for (f, a) in &self.history {
            frames.push(f.shallow_clone());
            actions.push(a.shallow_clone());
        }
        (Tensor::stack(&frames, 1), Tensor::stack(&actions, 0))
    }

    /// Generates the next chunk for `actions` [n, d_a], 1 <= n <= K. A window shorter than K is
    /// padded with its last action and the output trimmed to n frames.
    pub fn next_chunk(&mut self, actions: &Tensor) -> Result<Chunk> {
        self.next_chunk_traced(actions, &mut |_, _, _| {})
    }

    /// As `next_chunk`, showing each sampler step's model input and velocity to `on_step`.
    pub fn next_chunk_traced(&mut self, actions: &Tensor, on_step: &mut dyn FnMut(usize, &Tensor, &Tensor)) -> Result<Chunk> {
        let mut chunks = Self::next_chunks_traced(&mut [self], std::slice::from_ref(actions), on_step)?;
        Ok(chunks.remove(0))
    }

    /// The next chunk of several rollouts at once, `actions[i]` driving `rollouts[i]`: one batched
    /// encode, sampler and decode instead of one of each per rollout. Each rollout draws its own
    /// keyed noise, so it generates what `next_chunk` alone would (up to the rounding of batched
    /// kernels). The rollouts must share the model, the VAE, the frame size and every setting but
    /// the seed; each chunk reports the batch's seconds.
    pub fn next_chunks(rollouts: &mut [&mut Rollout<'m>], actions: &[Tensor]) -> Result<Vec<Chunk>> {
        Self::next_chunks_traced(rollouts, actions, &mut |_, _, _| {})
    }

    fn next_chunks_traced(rollouts: &mut [&mut Rollout<'m>], actions: &[Tensor], on_step: &mut dyn FnMut(usize, &Tensor, &Tensor)) -> Result<Vec<Chunk>> {
        let shared: Vec<&Rollout<'m>> = rollouts.iter().map(|r| &**r).collect();
        let pending = Self::begin_traced(&shared, actions, true, on_step)?;
        Self::finish_chunks(rollouts, pending)
    }

    /// The first half of [`Rollout::next_chunks`]: queues the batch's encode, sampler and decode
    /// on the device and returns without waiting for them (on CUDA, on the current stream); the
    /// host reads nothing back but the condition clip's finiteness check. [`Rollout::finish_chunks`]
    /// with the same rollouts, not advanced in between, reads the frames. Meanwhile the host is
    /// free for other work, such as another batch's policies or another stream's chunk. The
    /// chunks' phase seconds are NaN: the phases are not timed apart.
    pub fn begin_chunks(rollouts: &[&Rollout<'m>], actions: &[Tensor]) -> Result<PendingChunks> {
        Self::begin_traced(rollouts, actions, false, &mut |_, _, _| {})
    }

    fn begin_traced(rollouts: &[&Rollout<'m>], actions: &[Tensor], timed: bool, on_step: &mut dyn FnMut(usize, &Tensor, &Tensor)) -> Result<PendingChunks> {
        ensure!(!rollouts.is_empty(), "no rollouts to advance");
        ensure!(rollouts.len() == actions.len(), "{} rollouts but {} action windows", rollouts.len(), actions.len());
        let first = rollouts[0];
        let (model, vae) = (first.model, first.vae);
        for (i, r) in rollouts.iter().enumerate().skip(1) {
            ensure!(
                std::ptr::eq(r.model, model) && std::ptr::eq(r.vae, vae),
                "rollout {i} runs another model or VAE than rollout 0; a batch shares both"
            );
            ensure!(
                RolloutSpec { seed: first.spec.seed, ..r.spec.clone() } == first.spec,
                "rollout {i}'s settings ({:?}) differ from rollout 0's ({:?}) in more than the seed",
                r.spec,
                first.spec
            );
            ensure!(r.x0.size() == first.x0.size(), "rollout {i}'s frames are {:?}, rollout 0's {:?}", r.x0.size(), first.x0.size());
            let same_denoiser = match (&r.denoiser, &first.denoiser) {
                (Some(a), Some(b)) => Rc::ptr_eq(a, b),
                (None, None) => true,
                _ => false,
            };
            ensure!(same_denoiser, "rollout {i} runs its sampler through another denoiser than rollout 0; a batch shares one");
            let same_decoder = match (r.light_decoder, first.light_decoder) {
                (Some(a), Some(b)) => std::ptr::eq(a, b),
                (None, None) => true,
                _ => false,
            };
            ensure!(same_decoder, "rollout {i} decodes with another decoder than rollout 0; a batch shares one");
        }
        let (k, d) = (first.spec.future as i64, first.a0.size()[0]);
        let p = first.spec.condition_latents() as i64;
        let history_sigma = first.spec.history_sigma;
        let mut applied = Vec::with_capacity(actions.len());
        let mut future_actions = Vec::with_capacity(actions.len());
        for (i, a) in actions.iter().enumerate() {
            let s = a.size();
            let at = if actions.len() > 1 { format!(" (rollout {i})") } else { String::new() };
            ensure!(
                s.len() == 2 && s[1] == d && s[0] >= 1 && s[0] <= k,
                "chunk actions{at} must be [n, {d}] with 1 <= n <= {k}, got {s:?}"
            );
            let a = a.to_device(Device::Cpu).to_kind(Kind::Float);
            ensure!(bool::try_from(a.isfinite().all())?, "chunk actions{at} hold NaN or infinite values");
            let n = s[0];
            future_actions.push(if n < k { Tensor::cat(&[a.shallow_clone(), a.get(n - 1).unsqueeze(0).expand([k - n, d], false)], 0) } else { a.shallow_clone() });
            applied.push(a);
        }
        let conditions: Vec<(Tensor, Tensor)> = rollouts.iter().map(|r| r.condition()).collect();
        let device = model.store.device();
        let kind = model.store.kind();
        let sync = || {
            if timed {
                (first.sync)()
            }
        };
        let seconds_since = |start: Instant| if timed { start.elapsed().as_secs_f64() } else { f64::NAN };

        // Every upload before the first kernel: a copy from pageable host memory waits for the
        // work queued on its stream, which would hold the host until the encode ended.
        let start = Instant::now();
        let cond_frames = Tensor::stack(&conditions.iter().map(|c| c.0.shallow_clone()).collect::<Vec<_>>(), 0).to_device(device);
        let (cs, lh, lw) = {
            let f = cond_frames.size();
            let l = vae.cfg.latent_shape(f[2], f[3], f[4]);
            (l[0], l[2], l[3])
        };
        let one = |r: &Rollout, purpose: Purpose, frames: i64| keyed_rng::normal(&[1, cs, frames, lh, lw], r.spec.seed, r.chunks as u64, purpose);
        let history_noise = match history_sigma {
            Some(sh) if p > 1 => Some((sh, Tensor::cat(&rollouts.iter().map(|r| one(r, Purpose::RolloutHistoryNoise, p - 1)).collect::<Vec<_>>(), 0).to_device(device))),
            _ => None,
        };
        let noise = Tensor::cat(&rollouts.iter().map(|r| one(r, Purpose::RolloutNoise, p + k / 4)).collect::<Vec<_>>(), 0).to_device(device);
        let all_actions = Tensor::stack(
            &conditions.iter().zip(&future_actions).map(|(c, f)| Tensor::cat(&[c.1.shallow_clone(), f.shallow_clone()], 0)).collect::<Vec<_>>(),
            0,
        )
        .to_device(device);
        let clean = tch::no_grad(|| vae.encode(&cond_frames))
            .context("encoding the condition clip [x0, history]")?
            .to_kind(Kind::Float);
        ensure!(
            clean.size() == [rollouts.len() as i64, cs, p, lh, lw],
            "the VAE encoded the condition clip to {:?}; expected [{}, {cs}, {p}, {lh}, {lw}]",
            clean.size(),
            rollouts.len()
        );
        sync();
        let encode_seconds = seconds_since(start);

        let prefix = match history_noise {
            Some((sh, eps)) => Tensor::cat(&[clean.narrow(2, 0, 1), FlowSchedule::add_noise(&clean.narrow(2, 1, p - 1), &eps, sh)], 2),
            None => clean,
        };
        let start = Instant::now();
        let mut eager = Eager;
        let mut shared = first.denoiser.as_ref().map(|d| d.borrow_mut());
        let denoiser: &mut dyn Denoiser = match shared.as_deref_mut() {
            Some(d) => d,
            None => &mut eager,
        };
        let latents = tch::no_grad(|| {
            sample_chunk(denoiser, model, &prefix.to_kind(kind), &noise.to_kind(kind), &all_actions, &first.schedule, first.spec.guidance, on_step)
        })?;
        drop(shared);
        sync();
        let dit_seconds = seconds_since(start);

        // The causal decoder runs through the prefix latents for its cache; their pixels are dropped.
        // Widened, joined and clamped where they were decoded: on the host these passes over
        // every pixel ran on libtorch's CPU pool (0.4 s of a 5B chunk's decode with one thread,
        // docs/performance.md at abaed68, "CPU threads beside the GPU").
        let start = Instant::now();
        let frames = tch::no_grad(|| -> Result<Tensor> {
            let mut pixels = match first.light_decoder {
                Some(light) => {
                    // Every latent at once; the prefix's frames (1 + 4 (p - 1)) are dropped.
                    let all = light.decode(&latents)?;
                    let prefix = 1 + vae.cfg.temporal_stride() * (p - 1);
                    all.narrow(2, prefix, all.size()[2] - prefix)
                }
                None => {
                    let mut stream = vae.decoder_stream();
                    let mut future = Vec::new();
                    for i in 0..latents.size()[2] {
                        let px = stream.next(&latents.narrow(2, i, 1))?;
                        if i >= p {
                            future.push(px);
                        }
                    }
                    Tensor::cat(&future, 2)
                }
            }
            .to_kind(Kind::Float);
            let _ = pixels.clamp_(-1.0, 1.0);
            Ok(pixels)
        })
        .context("decoding the generated chunk")?;
        sync();
        let decode_seconds = seconds_since(start);
        Ok(PendingChunks { frames, applied, encode_seconds, dit_seconds, decode_seconds })
    }

    /// The second half of [`Rollout::next_chunks`]: waits for the chunk [`Rollout::begin_chunks`]
    /// queued for these rollouts (on CUDA, for the current stream: the stream it was queued on),
    /// moves its frames to the host and advances each rollout by it.
    pub fn finish_chunks(rollouts: &mut [&mut Rollout<'m>], pending: PendingChunks) -> Result<Vec<Chunk>> {
        let PendingChunks { frames, applied, encode_seconds, dit_seconds, decode_seconds } = pending;
        ensure!(
            rollouts.len() == applied.len(),
            "a chunk begun for {} rollouts is finished for {}",
            applied.len(),
            rollouts.len()
        );
        let start = Instant::now();
        let frames = frames.to_device(Device::Cpu);
        // The copy to the host belongs to the decode's time where that was timed.
        let decode_seconds = decode_seconds + start.elapsed().as_secs_f64();
        let mut chunks = Vec::with_capacity(rollouts.len());
        for (b, (r, actions)) in rollouts.iter_mut().zip(applied).enumerate() {
            let n = actions.size()[0];
            let frames = frames.get(b as i64).narrow(1, 0, n);
            for t in 0..n {
                r.push(frames.select(1, t), actions.get(t));
            }
            r.chunks += 1;
            chunks.push(Chunk { index: r.chunks - 1, frames, actions, encode_seconds, dit_seconds, decode_seconds });
        }
        Ok(chunks)
    }

    /// Rolls out a whole action sequence [T, d_a] in chunks of K (the last one shorter), handing
    /// each chunk to `on_chunk` as soon as it exists so callers can stream it out.
    pub fn run(&mut self, actions: &Tensor, on_chunk: &mut dyn FnMut(Chunk) -> Result<()>) -> Result<()> {
        Self::run_together(&mut [self], std::slice::from_ref(actions), &mut |_, chunk| on_chunk(chunk))
    }

    /// The next chunk's rows of a whole action sequence [T, d_a] of which the first `applied` have
    /// been applied: at most K of them, None when none are left.
    pub fn next_window(&self, actions: &Tensor, applied: i64) -> Option<Tensor> {
        let left = actions.size()[0] - applied;
        (left > 0).then(|| actions.narrow(0, applied, left.min(self.spec.future as i64)))
    }

    /// `run` for several rollouts, `actions[i]` driving `rollouts[i]`: each round advances those
    /// with actions left by one chunk as one batch (`next_chunks`) and hands the chunks over as
    /// `on_chunk(i, chunk)`.
    pub fn run_together(rollouts: &mut [&mut Rollout<'m>], actions: &[Tensor], on_chunk: &mut dyn FnMut(usize, Chunk) -> Result<()>) -> Result<()> {
        ensure!(rollouts.len() == actions.len(), "{} rollouts but {} action sequences", rollouts.len(), actions.len());
        let mut applied = vec![0i64; actions.len()];
        loop {
            let (mut batch, mut windows, mut indices) = (Vec::new(), Vec::new(), Vec::new());
            for (i, (r, a)) in rollouts.iter_mut().zip(actions).enumerate() {
                if let Some(window) = r.next_window(a, applied[i]) {
                    windows.push(window);
                    indices.push(i);
                    batch.push(&mut **r);
                }
            }
            if batch.is_empty() {
                return Ok(());
            }
            for (i, chunk) in indices.into_iter().zip(Self::next_chunks(&mut batch, &windows)?) {
                applied[i] += chunk.actions.size()[0];
                on_chunk(i, chunk)?;
            }
        }
    }
}
