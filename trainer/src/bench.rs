//! `bwm bench-train`: time the real training step (objective, recomputation, AdamW with fp32
//! masters) of a run config on random weights and a synthetic one-clip latent cache of the
//! config's clip size; prints step time, throughput, MFU and device memory, and with a breakdown
//! where the step's time goes ([`breakdown`]). With [`DistillBench`], the step of step
//! distillation instead, against a frozen teacher of random weights.

pub mod breakdown;

use std::path::PathBuf;

use anyhow::{Context, Result};
use bwm_data::latent_cache::{CacheIndex, CacheWriter, ClipEntry};
use bwm_model::BwmModel;
use tch::{Device, Kind, Tensor};

use crate::config::DistillSection;
use crate::distill::Distillation;
use crate::{Resume, RunConfig, Trainer};

/// The step of step distillation (`[distill]`, [`crate::distill`]) timed instead of flow
/// matching: a student of `student_steps` learning from a frozen teacher of the same model that
/// takes `teacher_substeps` Euler steps per student step. The teacher has random weights of its
/// own (the time and memory are those of any teacher; the weights file is not needed), and the
/// actions are never dropped, as distillation requires.
#[derive(Clone, Copy, Debug)]
pub struct DistillBench {
    pub student_steps: usize,
    pub teacher_substeps: usize,
}

/// What [`run`] times: a run config (with `--set` overrides) at a clip size.
#[derive(Clone, Debug)]
pub struct BenchTrainOptions {
    pub config: PathBuf,
    /// `KEY=VALUE` overrides of the config, as `bwm train --set` takes them.
    pub overrides: Vec<String>,
    /// Pixel frames per clip: x0 + history + future.
    pub history: usize,
    pub future: usize,
    pub height: i64,
    pub width: i64,
    pub steps: u64,
    /// After the steps, time one DiT block and its parts and print the step's breakdown.
    pub breakdown: bool,
    /// Record the steps after the first with libtorch's profiler into this Chrome trace and print
    /// where their GPU time went.
    pub profile: Option<PathBuf>,
    /// Scratch folder for the synthetic cache and the run's logs (a rank's own `rank-N` below it
    /// when `RANK` is set).
    pub out: PathBuf,
    /// Time the step of step distillation instead of the flow-matching step.
    pub distill: Option<DistillBench>,
}

/// Writes the synthetic cache under `out`, trains `steps` steps on it from random weights and
/// prints each step's line, then the breakdown when asked.
pub fn run(a: &BenchTrainOptions) -> Result<()> {
    // Ranks of a data-parallel benchmark (`bwm launch -- bench-train`) each get their own folder.
    let out_root = match std::env::var("RANK") {
        Ok(rank) => a.out.join(format!("rank-{rank}")),
        Err(_) => a.out.clone(),
    };
    let cache_dir = out_root.join("cache");
    let pixel_frames = 1 + a.history + a.future;
    let latent_shape = bwm_model::vae::VaeConfig::wan22().latent_shape(pixel_frames as i64, a.height, a.width);
    let mut overrides = vec![
        format!("data.latent_cache=\"{}\"", cache_dir.display()),
        "data.holdout_episodes=0".into(),
        "model.init={from=\"random\"}".into(),
        format!("run.out_dir=\"{}\"", out_root.join("run").display()),
        format!("train.steps={}", a.steps),
        "log.tensorboard=false".into(),
    ];
    overrides.extend(a.overrides.iter().cloned());
    if let Some(d) = a.distill {
        DistillSection::check_steps(d.student_steps, d.teacher_substeps)?;
        overrides.push("objective.action_dropout=0.0".into());
    }
    let cfg = RunConfig::load(&a.config, &overrides)?;
    // The synthetic actions have the config's action width, so any run config can be timed.
    let action_dim = cfg.model.action.action_dim;
    let index = CacheIndex::new(latent_shape.clone(), action_dim, a.history, a.future, [a.width as u32, a.height as u32], 30.0, "synthetic (bench-train)");
    let mut w = CacheWriter::create(&cache_dir, index)?;
    for episode in 0..2 {
        let latents = Tensor::randn(latent_shape.as_slice(), (Kind::Float, Device::Cpu));
        let actions = Tensor::rand([pixel_frames as i64, action_dim], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
        w.add(ClipEntry { file: String::new(), episode, frames: (0..pixel_frames).collect(), task: "bench".into() }, &latents, &actions, None)?;
    }
    w.finish()?;
    let out = cfg.out_dir();
    if out.exists() {
        std::fs::remove_dir_all(&out)?;
    }
    let mut t = Trainer::new(cfg, Resume::No)?;
    if let Some(d) = a.distill {
        let teacher = BwmModel::random(&t.model.cfg, t.model.store.kind(), t.device, t.cfg.run.seed as i64 + 1)
            .context("building the distillation's teacher (random weights)")?;
        t.distill = Some(Distillation::with_teacher(teacher, d.student_steps, d.teacher_substeps, t.cfg.objective.shift, t.cfg.run.seed));
        println!(
            "bench-train: step distillation, a student of {} step(s) from a frozen teacher of random weights taking {} Euler steps ({} per student step); FLOP/s and MFU count the student's forward and backward only",
            d.student_steps,
            d.student_steps * d.teacher_substeps,
            d.teacher_substeps
        );
    }
    let dit = &t.model.cfg.dit;
    let kernel = bwm_sdp::kernel_for_shape(dit.num_heads, dit.head_dim(), 1024, t.model.store.kind(), t.device)?;
    println!(
        "bench-train: {} ({} parameters, {} trained) on {:?}, {:?}, clip {}x{} with {} frames -> latents {:?}, micro-batch {} x accumulation {}, recompute {}, attention backend {} ({kernel}), libtorch CPU threads {}",
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
        t.cfg.train.recompute,
        bwm_sdp::backend(),
        tch::get_num_threads()
    );
    let mut timed = Vec::new();
    // The first step holds the warm-up (allocator, autotuning); a one-step run profiles it anyway.
    let profile_from = a.steps.min(2);
    let mut profiler = None;
    for step in 1..=a.steps {
        if step == profile_from && a.profile.is_some() {
            bwm_model::device::synchronize(t.device);
            profiler = Some(bwm_profiler::Profiler::start(t.device.is_cuda())?);
        }
        let m = t.train_step()?;
        println!("{}", m.summary_line(a.steps));
        timed.push((m.seconds, m.collective_s));
    }
    if let (Some(p), Some(path)) = (profiler, &a.profile) {
        bwm_model::device::synchronize(t.device);
        p.finish(path)?;
        let steps = (a.steps + 1 - profile_from) as f64;
        for line in profile_lines(&bwm_profiler::gpu_summary(path)?, steps) {
            println!("{line}");
        }
        println!("  trace (Chrome JSON, for chrome://tracing or Perfetto): {}", path.display());
    }
    if a.breakdown {
        // The first step includes warm-up (allocator, autotuning); the median of the others.
        let mut later: Vec<(f64, f64)> = timed.iter().skip(1).copied().collect();
        if later.is_empty() {
            later = timed;
        }
        later.sort_by(|x, y| x.0.total_cmp(&y.0));
        let (seconds, collectives) = later[later.len() / 2];
        for line in breakdown::breakdown(&t, seconds, collectives)? {
            println!("{line}");
        }
    }
    Ok(())
}

/// What a profile of `steps` steps says per step: the span, the GPU's busy and idle time, and
/// the kernels with the most GPU time.
fn profile_lines(s: &bwm_profiler::GpuSummary, steps: f64) -> Vec<String> {
    let ms = |us: f64| us / 1e3 / steps;
    let mut lines = vec![format!(
        "profile of {steps} step(s), per step: {:.1} ms traced, GPU busy {:.1} ms ({:.1}%), idle {:.1} ms",
        ms(s.span_us),
        ms(s.busy_us),
        100.0 * s.busy_us / s.span_us.max(f64::MIN_POSITIVE),
        ms(s.span_us - s.busy_us)
    )];
    for (name, calls, us) in s.kernels.iter().take(25) {
        let short: String = name.chars().take(110).collect();
        lines.push(format!("  {:8.2} ms  {:6.1} calls  {short}", ms(*us), *calls as f64 / steps));
    }
    lines
}
