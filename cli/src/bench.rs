//! `bwm info`, `bwm bench-forward` and `bwm bench-vae`.

use std::time::Instant;

use anyhow::{ensure, Result};
use bwm_model::{frame_timesteps, BwmModel, ModelConfig, ParamStore};
use clap::Args;
use tch::{Device, Kind, Tensor};

use bwm_trainer::devices::{parse_device, parse_kind};

#[derive(Args)]
pub struct InfoArgs {
    /// Model preset: wan22_ti2v_5b or tiny.
    #[arg(long, default_value = "wan22_ti2v_5b")]
    preset: String,
}

pub fn info(args: InfoArgs) -> Result<()> {
    let cfg = ModelConfig::preset(&args.preset)?;
    let store = ParamStore::shapes_only(Kind::BFloat16);
    BwmModel::build(&store, &cfg)?;
    let params = store.named_parameters();
    let count = |pred: &dyn Fn(&str) -> bool| -> (usize, i64) {
        let sel: Vec<_> = params.iter().filter(|(n, _)| pred(n)).collect();
        (sel.len(), sel.iter().map(|(_, t)| t.size().iter().product::<i64>()).sum())
    };
    let (dt, dp) = count(&|n| !n.starts_with("action_encoder."));
    let (at, ap) = count(&|n| n.starts_with("action_encoder."));
    println!("preset {}: {:?}", args.preset, cfg.dit);
    println!("DiT:            {dt:>4} tensors  {dp:>14} parameters");
    println!("action encoder: {at:>4} tensors  {ap:>14} parameters");
    println!("total:          {:>4} tensors  {:>14} parameters ({:.2} GB in bf16)", dt + at, dp + ap, (dp + ap) as f64 * 2e-9);
    Ok(())
}

/// Where and at what clip size a benchmark runs.
#[derive(Args)]
pub struct BenchRun {
    #[arg(long, default_value = "cuda")]
    device: String,
    #[arg(long, default_value = "bf16")]
    dtype: String,
    /// Pixel frames of the clip (1 + H + K); must be 1+4k.
    #[arg(long, default_value_t = 81)]
    frames: i64,
    #[arg(long, default_value_t = 480)]
    height: i64,
    #[arg(long, default_value_t = 640)]
    width: i64,
}

impl BenchRun {
    fn device_and_kind(&self) -> Result<(Device, Kind)> {
        Ok((parse_device(&self.device)?, parse_kind(&self.dtype)?))
    }
}

#[derive(Args)]
pub struct BenchForwardArgs {
    #[arg(long, default_value = "wan22_ti2v_5b")]
    preset: String,
    #[command(flatten)]
    run: BenchRun,
    /// Condition latents (x0 + history) that get timestep 0.
    #[arg(long, default_value_t = 3)]
    condition_latents: i64,
    #[arg(long, default_value_t = 1)]
    batch: i64,
    #[arg(long, default_value_t = 2)]
    warmup: usize,
    #[arg(long, default_value_t = 5)]
    iters: usize,
}

pub fn forward(args: BenchForwardArgs) -> Result<()> {
    let (device, kind) = args.run.device_and_kind()?;
    let cfg = ModelConfig::preset(&args.preset)?;
    ensure!(args.run.frames % 4 == 1, "--frames {} must be 1+4k", args.run.frames);
    ensure!(args.run.height % 32 == 0 && args.run.width % 32 == 0, "--height and --width must be multiples of 32");
    let latent_frames = (args.run.frames - 1) / 4 + 1;
    let (lh, lw) = (args.run.height / 16, args.run.width / 16);
    let tokens = latent_frames * (lh / 2) * (lw / 2);
    let t0 = Instant::now();
    let model = BwmModel::random(&cfg, kind, device, 0)?;
    sync(device);
    eprintln!("built {} random weights ({} parameters) in {:.1}s", args.preset, model.store.num_parameters(), t0.elapsed().as_secs_f64());

    let latents = Tensor::randn([args.batch, cfg.dit.in_dim, latent_frames, lh, lw], (Kind::Float, device));
    let actions = Tensor::rand([args.batch, args.run.frames, cfg.action.action_dim], (Kind::Float, device)) * 2.0 - 1.0;
    let t = frame_timesteps(&Tensor::full([args.batch], 700.0, (Kind::Float, device)), latent_frames, args.condition_latents);
    let mut times = Vec::new();
    for i in 0..args.warmup + args.iters {
        let start = Instant::now();
        let v = tch::no_grad(|| model.forward(&latents, &t, &actions))?;
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
    let lc = args.run.frames as f64;
    let per_block = n * (2.0 * 4.0 * d * d + 2.0 * 2.0 * d * d + 2.0 * 2.0 * d * cfg.dit.ffn_dim as f64 + 4.0 * lc * d)
        + 2.0 * 2.0 * lc * d * d * args.batch as f64
        + 4.0 * (tokens as f64).powi(2) * d * args.batch as f64;
    let flops = per_block * cfg.dit.num_layers as f64;
    println!(
        "bench-forward preset={} device={:?} dtype={} clip={}x{}x{} latents=[{},{},{},{},{}] tokens={} : mean {:.4}s min {:.4}s over {} iters, {:.1} TFLOP/s (model FLOPs {:.2} TFLOP)",
        args.preset, device, args.run.dtype, args.run.frames, args.run.height, args.run.width,
        args.batch, cfg.dit.in_dim, latent_frames, lh, lw, tokens, mean, min, times.len(), flops / mean / 1e12, flops / 1e12
    );
    Ok(())
}

fn sync(device: Device) {
    if let Device::Cuda(i) = device {
        tch::Cuda::synchronize(i as i64);
    }
}

#[derive(Args)]
pub struct BenchVaeArgs {
    #[command(flatten)]
    run: BenchRun,
    #[arg(long, default_value_t = 3)]
    iters: usize,
    /// Then stream-decode this many seconds of video (0 to skip), moving frames to the host.
    #[arg(long, default_value_t = 30.0)]
    stream_seconds: f64,
    #[arg(long, default_value_t = 24.0)]
    fps: f64,
}

pub fn vae(args: BenchVaeArgs) -> Result<()> {
    use bwm_model::vae::{VaeConfig, WanVae};
    let (device, kind) = args.run.device_and_kind()?;
    let (vae, _store) = WanVae::random(&VaeConfig::wan22(), kind, device, 0)?;
    let video = Tensor::rand([1, 3, args.run.frames, args.run.height, args.run.width], (Kind::Float, device)) * 2.0 - 1.0;
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
        ensure!(x.size()[2] == args.run.frames, "decoded {} frames", x.size()[2]);
        println!(
            "bench-vae iter {i}: encode {}x{}x{} {:?} -> {:?} in {te:.3}s; decode in {td:.3}s",
            args.run.frames, args.run.height, args.run.width, args.run.dtype, z.size()
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
            produced as f64 / args.fps, args.fps, args.run.height, args.run.width, start.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

#[derive(Args)]
pub struct BenchRolloutArgs {
    #[command(flatten)]
    wm: crate::world_model::WorldModelArgs,
    /// Frame size of the rollout.
    #[arg(long, default_value_t = 480)]
    height: i64,
    #[arg(long, default_value_t = 640)]
    width: i64,
    /// Chunks to generate (the first includes one-time CUDA start-up costs).
    #[arg(long, default_value_t = 2)]
    chunks: usize,
}

/// Times whole rollout chunks (condition encode, the sampler's DiT steps, decode) on a random x0
/// and random actions.
pub fn rollout(args: BenchRolloutArgs) -> Result<()> {
    let wm = args.wm.load()?;
    let d = wm.action_dim() as i64;
    tch::manual_seed(0);
    let x0 = Tensor::rand([3, args.height, args.width], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
    let a0 = Tensor::zeros([d], (Kind::Float, Device::Cpu));
    let mut rollout = wm.rollout(&x0, &a0)?;
    let spec = rollout.spec().clone();
    println!(
        "bench-rollout: {:?} {:?}, {}x{}, x0 + {} history frames, {} frames per chunk, {} Euler steps",
        wm.device,
        wm.model.store.kind(),
        args.width,
        args.height,
        spec.history,
        spec.future,
        spec.steps
    );
    for i in 0..args.chunks {
        let actions = Tensor::rand([spec.future as i64, d], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
        let start = Instant::now();
        let c = rollout.next_chunk(&actions)?;
        let total = start.elapsed().as_secs_f64();
        println!(
            "chunk {i}: {total:.2} s = encode {:.2} s + DiT {:.2} s ({:.3} s/step) + decode {:.2} s; {} frames; device memory {}",
            c.encode_seconds,
            c.dit_seconds,
            c.dit_seconds / spec.steps as f64,
            c.decode_seconds,
            c.frames.size()[1],
            bwm_trainer::device_memory::used_mib(wm.device).map_or("n/a".to_string(), |m| format!("{m:.0} MiB used"))
        );
    }
    Ok(())
}
