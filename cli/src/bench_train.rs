//! `bwm bench-train`: time the real training step (objective, recomputation, AdamW with fp32
//! masters) of a run config on random weights and a synthetic one-clip latent cache of the
//! config's clip size; prints step time, throughput, MFU and device memory, and with
//! `--breakdown` where the step's time goes (`bench_breakdown`).

use std::path::PathBuf;

use anyhow::Result;
use bwm_data::latent_cache::{CacheIndex, CacheWriter, ClipEntry};
use bwm_trainer::{Resume, RunConfig, Trainer};
use clap::Args;
use tch::{Device, Kind, Tensor};

#[derive(Args)]
pub struct BenchTrainArgs {
    #[arg(long, default_value = "configs/bwm-wan22-ti2v-5b.toml")]
    config: PathBuf,
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
    /// Pixel frames per clip: x0 + history + future.
    #[arg(long, default_value_t = 8)]
    history: usize,
    #[arg(long, default_value_t = 72)]
    future: usize,
    #[arg(long, default_value_t = 480)]
    height: i64,
    #[arg(long, default_value_t = 640)]
    width: i64,
    #[arg(long, default_value_t = 3)]
    steps: u64,
    /// After the steps, time one DiT block and its parts and print the step's breakdown
    /// (attention, linear layers, norms/elementwise, the rest; collectives).
    #[arg(long)]
    breakdown: bool,
    /// Scratch folder for the synthetic cache and the run's logs.
    #[arg(long, default_value = "runs/bench-train")]
    out: PathBuf,
}

pub fn run(mut a: BenchTrainArgs) -> Result<()> {
    // Ranks of a data-parallel benchmark (`bwm launch -- bench-train`) each get their own folder.
    if let Ok(rank) = std::env::var("RANK") {
        a.out = a.out.join(format!("rank-{rank}"));
    }
    let cache_dir = a.out.join("cache");
    let pixel_frames = 1 + a.history + a.future;
    let latent_shape = bwm_model::vae::VaeConfig::wan22().latent_shape(pixel_frames as i64, a.height, a.width);
    let index = CacheIndex::new(latent_shape.clone(), 14, a.history, a.future, [a.width as u32, a.height as u32], 30.0, "synthetic (bench-train)");
    let mut w = CacheWriter::create(&cache_dir, index)?;
    for episode in 0..2 {
        let latents = Tensor::randn(latent_shape.as_slice(), (Kind::Float, Device::Cpu));
        let actions = Tensor::rand([pixel_frames as i64, 14], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
        w.add(ClipEntry { file: String::new(), episode, frames: (0..pixel_frames).collect(), task: "bench".into() }, &latents, &actions, None)?;
    }
    w.finish()?;
    let mut overrides = vec![
        format!("data.latent_cache=\"{}\"", cache_dir.display()),
        "data.holdout_episodes=0".into(),
        "model.init={from=\"random\"}".into(),
        format!("run.out_dir=\"{}\"", a.out.join("run").display()),
        format!("train.steps={}", a.steps),
        "log.tensorboard=false".into(),
    ];
    overrides.extend(a.overrides.iter().cloned());
    let cfg = RunConfig::load(&a.config, &overrides)?;
    let out = cfg.out_dir();
    if out.exists() {
        std::fs::remove_dir_all(&out)?;
    }
    let mut t = Trainer::new(cfg, Resume::No)?;
    println!(
        "bench-train: {} ({} parameters, {} trained) on {:?}, {:?}, clip {}x{} with {} frames -> latents {:?}, micro-batch {} x accumulation {}, recompute {}",
        t.cfg.model.preset,
        t.model.store.num_parameters(),
        t.opt.num_trainable(),
        t.device,
        t.cfg.model.dtype,
        a.width,
        a.height,
        pixel_frames,
        latent_shape,
        t.cfg.train.micro_batch,
        t.cfg.train.grad_accum,
        t.cfg.train.recompute
    );
    let mut timed = Vec::new();
    for _ in 0..a.steps {
        let m = t.train_step()?;
        println!("{}", m.summary_line(a.steps));
        timed.push((m.seconds, m.collective_s));
    }
    if a.breakdown {
        // The first step includes warm-up (allocator, autotuning); the median of the others.
        let mut later: Vec<(f64, f64)> = timed.iter().skip(1).copied().collect();
        if later.is_empty() {
            later = timed;
        }
        later.sort_by(|x, y| x.0.total_cmp(&y.0));
        let (seconds, collectives) = later[later.len() / 2];
        for line in crate::bench_breakdown::breakdown(&t, seconds, collectives)? {
            println!("{line}");
        }
    }
    Ok(())
}
