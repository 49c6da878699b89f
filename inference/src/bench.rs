//! Benchmarks of the inference path on random weights (`bwm info`, `bwm bench-forward`,
//! `bwm bench-vae`) and of whole rollout chunks of a loaded world model (`bwm bench-rollout`).
//! Each prints its measurements; the figures in docs/performance.md come from them.

use std::time::Instant;

use anyhow::{ensure, Result};
use bwm_model::rollout::{Rollout, RolloutSpec};
use bwm_model::{frame_timesteps, BwmModel, ModelConfig, ParamStore};
use bwm_model::device::synchronize as sync;
use tch::{Device, Kind, Tensor};

use crate::fallible::{alloc_error, guarded, probe};
use crate::WorldModel;

/// Prints a model preset's tensor and parameter counts (DiT, action encoder); nothing is allocated.
pub fn info(preset: &str) -> Result<()> {
    let cfg = ModelConfig::preset(&preset)?;
    let store = ParamStore::shapes_only(Kind::BFloat16);
    BwmModel::build(&store, &cfg)?;
    let params = store.named_parameters();
    let count = |pred: &dyn Fn(&str) -> bool| -> (usize, i64) {
        let sel: Vec<_> = params.iter().filter(|(n, _)| pred(n)).collect();
        (sel.len(), sel.iter().map(|(_, t)| t.size().iter().product::<i64>()).sum())
    };
    let (dt, dp) = count(&|n| !n.starts_with("action_encoder."));
    let (at, ap) = count(&|n| n.starts_with("action_encoder."));
    println!("preset {}: {:?}", preset, cfg.dit);
    println!("DiT:            {dt:>4} tensors  {dp:>14} parameters");
    println!("action encoder: {at:>4} tensors  {ap:>14} parameters");
    println!("total:          {:>4} tensors  {:>14} parameters ({:.2} GB in bf16)", dt + at, dp + ap, (dp + ap) as f64 * 2e-9);
    Ok(())
}

/// Where and at what clip size a benchmark runs.
#[derive(Clone, Debug)]
pub struct BenchShape {
    pub device: Device,
    pub kind: Kind,
    /// Pixel frames of the clip (1 + H + K); must be 1+4k.
    pub frames: i64,
    pub height: i64,
    pub width: i64,
}

/// The `--dtype` name of `kind`.
fn kind_name(kind: Kind) -> String {
    match kind {
        Kind::BFloat16 => "bf16".into(),
        Kind::Float => "f32".into(),
        other => format!("{other:?}"),
    }
}

/// [`forward`]: the DiT forward of a preset on random weights.
#[derive(Clone, Debug)]
pub struct ForwardOptions {
    pub preset: String,
    pub shape: BenchShape,
    /// Condition latents (x0 + history) that get timestep 0.
    pub condition_latents: i64,
    pub batch: i64,
    pub warmup: usize,
    pub iters: usize,
}

/// Times the DiT forward and prints mean and min seconds and the achieved TFLOP/s.
pub fn forward(args: &ForwardOptions) -> Result<()> {
    let (device, kind) = (args.shape.device, args.shape.kind);
    let cfg = ModelConfig::preset(&args.preset)?;
    ensure!(args.shape.frames > 0 && args.shape.frames % 4 == 1, "--frames {} must be 1+4k", args.shape.frames);
    ensure!(
        args.shape.height > 0 && args.shape.width > 0 && args.shape.height % 32 == 0 && args.shape.width % 32 == 0,
        "--height and --width must be positive multiples of 32"
    );
    ensure!(args.batch >= 1, "--batch must be at least 1");
    ensure!(args.iters >= 1, "--iters must be at least 1");
    let latent_frames = (args.shape.frames - 1) / 4 + 1;
    let (lh, lw) = (args.shape.height / 16, args.shape.width / 16);
    let tokens = latent_frames * (lh / 2) * (lw / 2);
    // The clip's latents are the first allocation its size decides: a size no memory holds is
    // named here, before the weights are built.
    let clip = format!("a {}x{}x{} clip", args.shape.frames, args.shape.height, args.shape.width);
    let shape = [args.batch, cfg.dit.in_dim, latent_frames, lh, lw];
    let latents_of = format!("bench-forward: the latents of {clip}");
    probe(&latents_of, &shape, Kind::Float, device)?;
    let t0 = Instant::now();
    let model = BwmModel::random(&cfg, kind, device, 0)?;
    sync(device);
    eprintln!("built {} random weights ({} parameters) in {:.1}s", args.preset, model.store.num_parameters(), t0.elapsed().as_secs_f64());

    let latents = Tensor::f_randn(shape, (Kind::Float, device)).map_err(|e| alloc_error(&latents_of, &shape, Kind::Float, device, e))?;
    let action_shape = [args.batch, args.shape.frames, cfg.action.action_dim];
    let actions = Tensor::f_rand(action_shape, (Kind::Float, device))
        .map_err(|e| alloc_error(&format!("bench-forward: the actions of {clip}"), &action_shape, Kind::Float, device, e))?
        * 2.0
        - 1.0;
    let t = frame_timesteps(&Tensor::full([args.batch], 700.0, (Kind::Float, device)), latent_frames, args.condition_latents);
    let mut times = Vec::new();
    for i in 0..args.warmup + args.iters {
        let start = Instant::now();
        let v = guarded(
            || format!("bench-forward: the DiT forward of {clip} (latents {shape:?}, {tokens} tokens per sample)"),
            || tch::no_grad(|| model.forward(&latents, &t, &actions)),
        )?;
        sync(device);
        let dt = start.elapsed().as_secs_f64();
        ensure!(v.isfinite().all().int64_value(&[]) == 1, "non-finite output");
        if i >= args.warmup {
            times.push(dt);
        }
    }
    let mean = times.iter().sum::<f64>() / times.len() as f64;
    let min = times.iter().cloned().fold(f64::INFINITY, f64::min);
    // Spec section 9.2: 295.70 MFLOP per token per block for the linears (with 512 context rows),
    // 4*N^2*D for self-attention; here the context is the action tokens, so count it exactly.
    let d = cfg.dit.dim as f64;
    let n = (tokens * args.batch) as f64;
    let lc = args.shape.frames as f64;
    let per_block = n * (2.0 * 4.0 * d * d + 2.0 * 2.0 * d * d + 2.0 * 2.0 * d * cfg.dit.ffn_dim as f64 + 4.0 * lc * d)
        + 2.0 * 2.0 * lc * d * d * args.batch as f64
        + 4.0 * (tokens as f64).powi(2) * d * args.batch as f64;
    let flops = per_block * cfg.dit.num_layers as f64;
    println!(
        "bench-forward preset={} device={:?} dtype={} clip={}x{}x{} latents=[{},{},{},{},{}] tokens={} : mean {:.4}s min {:.4}s over {} iters, {:.1} TFLOP/s (model FLOPs {:.2} TFLOP)",
        args.preset, device, kind_name(kind), args.shape.frames, args.shape.height, args.shape.width,
        args.batch, cfg.dit.in_dim, latent_frames, lh, lw, tokens, mean, min, times.len(), flops / mean / 1e12, flops / 1e12
    );
    Ok(())
}

/// [`vae`]: the full-width Wan2.2 VAE on random weights.
#[derive(Clone, Debug)]
pub struct VaeBenchOptions {
    pub shape: BenchShape,
    pub iters: usize,
    /// Then stream-decode this many seconds of video (0 to skip), moving frames to the host.
    pub stream_seconds: f64,
    pub fps: f64,
}

/// Times encode and decode of a clip, then a long streaming decode.
pub fn vae(args: &VaeBenchOptions) -> Result<()> {
    use bwm_model::vae::{VaeConfig, WanVae};
    let (device, kind) = (args.shape.device, args.shape.kind);
    let (vae, _store) = WanVae::random(&VaeConfig::wan22(), kind, device, 0)?;
    let video = Tensor::rand([1, 3, args.shape.frames, args.shape.height, args.shape.width], (Kind::Float, device)) * 2.0 - 1.0;
    let time = |f: &mut dyn FnMut() -> Result<Tensor>| -> Result<(f64, Tensor)> {
        let start = Instant::now();
        let out = tch::no_grad(|| f())?;
        sync(device);
        Ok((start.elapsed().as_secs_f64(), out))
    };
    let mut latents = None;
    for i in 0..args.iters {
        let (te, z) = time(&mut || vae.encode(&video))?;
        let (td, x) = time(&mut || vae.decode(&z))?;
        ensure!(x.size()[2] == args.shape.frames, "decoded {} frames", x.size()[2]);
        println!(
            "bench-vae iter {i}: encode {}x{}x{} {} -> {:?} in {te:.3}s; decode in {td:.3}s",
            args.shape.frames, args.shape.height, args.shape.width, kind_name(kind), z.size()
        );
        latents = Some(z);
    }
    if args.stream_seconds > 0.0 {
        let z = latents.expect("at least one iteration");
        let frames = (args.stream_seconds * args.fps).ceil() as i64;
        let chunks = (frames - 1 + 3) / 4 + 1;
        let mut stream = vae.decoder_stream();
        let start = Instant::now();
        let mut produced = 0;
        for i in 0..chunks {
            let latent = z.narrow(2, i % z.size()[2], 1);
            let out = tch::no_grad(|| stream.next(&latent))?.to_device(Device::Cpu);
            produced += out.size()[2];
            if i == 0 || (i + 1) % 20 == 0 || i + 1 == chunks {
                sync(device);
                println!(
                    "stream-decode chunk {}/{chunks} at {:.2}s: {produced} frames so far, feature cache {:.1} MiB",
                    i + 1,
                    start.elapsed().as_secs_f64(),
                    stream.cache_bytes() as f64 / (1 << 20) as f64
                );
            }
        }
        println!(
            "stream-decode: {produced} frames ({:.1} s at {} fps) of {}x{} in {:.2}s",
            produced as f64 / args.fps, args.fps, args.shape.height, args.shape.width, start.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

/// Times `chunks` whole rollout chunks (condition encode, the sampler's DiT steps, decode) of
/// `batch` rollouts advanced together (as the evaluator's episodes in flight) of `wm` at `width` x
/// `height` on random x0s and random actions; the first includes one-time CUDA start-up costs.
/// With `streams` > 1 the rollouts are split into that many lanes taking turns, each on a CUDA
/// stream of its own (`crate::lanes`), and each chunk's line gives when the last lane finished it
/// and the frames per second since the chunk before (the phases overlap, so they are not timed
/// apart).
pub fn rollout(wm: &WorldModel, height: i64, width: i64, chunks: usize, batch: usize, streams: usize) -> Result<()> {
    ensure!(batch >= 1, "--batch must be at least 1");
    crate::lanes::check(batch, streams).map_err(|e| e.context("--batch and --streams"))?;
    wm.check_frame_size(&format!("--height {height} --width {width}"), height, width, batch)?;
    let lanes = wm.lanes(streams)?;
    let d = wm.action_dim() as i64;
    tch::manual_seed(0);
    let a0 = Tensor::zeros([d], (Kind::Float, Device::Cpu));
    let frame = [3, height, width];
    let mut rollouts = (0..batch)
        .map(|i| {
            let x0 = Tensor::f_rand(frame, (Kind::Float, Device::Cpu)).map_err(|e| alloc_error("bench-rollout: x0", &frame, Kind::Float, Device::Cpu, e))? * 2.0 - 1.0;
            wm.rollout_with(RolloutSpec { seed: wm.spec.seed.wrapping_add(i as u64), ..wm.spec.clone() }, &x0, &a0)
        })
        .collect::<Result<Vec<_>>>()?;
    let chunk_of = || format!("bench-rollout: a chunk of {batch} rollout(s) of {height}x{width} (HxW) frames");
    let spec = wm.spec.clone();
    let dit = &wm.model.cfg.dit;
    let kernel = bwm_sdp::kernel_for_shape(dit.num_heads, dit.head_dim(), 1024, wm.model.store.kind(), wm.device)?;
    println!(
        "bench-rollout: {:?} {:?}, {}x{}, {batch} rollout(s) at once in {streams} stream(s), x0 + {} history frames, {} frames per chunk, {} {} steps, attention backend {} ({kernel}), libtorch CPU threads {}, {}, sampler forward {}, decoded by {}",
        wm.device,
        wm.model.store.kind(),
        width,
        height,
        spec.history,
        spec.future,
        spec.steps,
        spec.solver,
        bwm_sdp::backend(),
        tch::get_num_threads(),
        wm.fp8.map_or("block linears in the weights' dtype".to_string(), |s| format!("block linears in FP8 ({s} scaling)")),
        if wm.graphed.is_some() { "replayed from a CUDA graph (warm-up and capture in the first chunk)" } else { "eager" },
        if wm.light_decoder.is_some() { "the light decoder" } else { "the VAE's decoder" }
    );
    let memory = || bwm_model::device::memory::used_mib(wm.device).map_or("n/a".to_string(), |m| format!("{m:.0} MiB used"));
    let frames_per_chunk = (batch * spec.future) as f64;
    if streams == 1 {
        for i in 0..chunks {
            let actions: Vec<Tensor> = (0..batch).map(|_| Tensor::rand([spec.future as i64, d], (Kind::Float, Device::Cpu)) * 2.0 - 1.0).collect();
            let start = Instant::now();
            let c = guarded(chunk_of, || Rollout::next_chunks(&mut rollouts.iter_mut().collect::<Vec<_>>(), &actions))?.remove(0);
            let total = start.elapsed().as_secs_f64();
            println!(
                "chunk {i}: {total:.2} s = encode {:.2} s + DiT {:.2} s ({:.3} s/step) + decode {:.2} s; {} frames; {:.1} generated frames/s; device memory {}",
                c.encode_seconds,
                c.dit_seconds,
                c.dit_seconds / spec.steps as f64,
                c.decode_seconds,
                c.frames.size()[1],
                frames_per_chunk / total,
                memory()
            );
        }
        return Ok(());
    }
    let actions: Vec<Tensor> = (0..batch).map(|_| Tensor::rand([(chunks * spec.future) as i64, d], (Kind::Float, Device::Cpu)) * 2.0 - 1.0).collect();
    let mut done = vec![0usize; chunks];
    let start = Instant::now();
    let mut last = 0.0;
    let mut rollouts: Vec<_> = rollouts.iter_mut().collect();
    guarded(chunk_of, || crate::lanes::run_together(&lanes, &mut rollouts, &actions, &mut |_, chunk| {
        done[chunk.index] += 1;
        if done[chunk.index] == batch {
            let at = start.elapsed().as_secs_f64();
            let since = if chunk.index == 0 { "the start".to_string() } else { format!("chunk {}'s", chunk.index - 1) };
            println!(
                "chunk {}: all {batch} rollouts' frames at {at:.2} s, {:.2} s after {since}; {:.1} generated frames/s; device memory {}",
                chunk.index,
                at - last,
                frames_per_chunk / (at - last),
                memory()
            );
            last = at;
        }
        Ok(())
    }))
}
