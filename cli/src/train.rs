//! `bwm train`: post-train the BWM model on a prepared latent cache.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::{Context, Result};
use bwm_trainer::{Resume, RunConfig, Trainer};
use clap::Args;

#[derive(Args)]
pub struct TrainArgs {
    /// Run config (TOML), e.g. configs/tiny.toml.
    #[arg(long)]
    config: PathBuf,
    /// Override a config value: --set optim.lr=2e-5 (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
    /// `auto`: continue from the newest complete checkpoint of the run (fresh when there is none);
    /// a checkpoint folder: continue from it (an error when it is missing or does not match);
    /// `no`: start fresh (an error when the run already has checkpoints).
    #[arg(long, default_value = "no")]
    resume: Resume,
}

pub fn run(args: TrainArgs) -> Result<()> {
    // SIGTERM (Slurm's preemption and time-limit warning, `bwm launch` stopping its ranks) and
    // SIGINT stop the run after the current optimizer step, with a checkpoint of that step.
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(sig, stop.clone())
            .context("installing the SIGTERM/SIGINT handler")?;
    }
    let cfg = RunConfig::load(&args.config, &args.overrides)?;
    let mut trainer = Trainer::new(cfg, args.resume)?;
    trainer.check_validation_vae()?;
    let c = &trainer.cfg;
    println!(
        "run {}: {} on {:?}, {} of {} parameters trained, {} training clips ({} held-out clips for validation), {} steps of {} samples (micro-batch {} x accumulation {}), recompute {}",
        c.run.name,
        c.model.preset,
        trainer.device,
        trainer.opt.num_trainable(),
        trainer.model.store.num_parameters(),
        trainer.train_clips,
        trainer.cache.len() - trainer.train_clips,
        c.train.steps,
        c.samples_per_step(),
        c.train.micro_batch,
        c.train.grad_accum,
        if c.train.recompute { "on" } else { "off" }
    );
    println!("outputs in {}", trainer.out_dir.display());
    if let Some(dir) = trainer.run_until(&stop)? {
        println!(
            "stopped by signal at step {}; checkpoint {}",
            trainer.state.step,
            dir.display()
        );
        return Ok(());
    }
    println!(
        "done: step {} (checkpoints in {})",
        trainer.state.step,
        trainer.checkpoints.root.display()
    );
    // The curve is a report of a run that is done and saved: one that cannot be drawn is a
    // warning, not a failed run (which `bwm launch` or Slurm would restart, to no avail).
    let plot = trainer.out_path("loss.svg");
    let title = format!("{}: training loss", trainer.cfg.run.name);
    let drawn = bwm_trainer::run_log::read_run_losses(&trainer.out_path(""))
        .and_then(|losses| bwm_metrics::plot::loss_plot(&losses, &title, &plot));
    match drawn {
        Ok(()) => println!("loss curve: {}", plot.display()),
        Err(e) => eprintln!("warning: no loss curve: {e:#}"),
    }
    if let Some(vae) = trainer.cfg.validation.vae.clone() {
        let video = trainer.out_path("rollout.mp4");
        let r = bwm_trainer::report::rollout_video(&trainer, &vae, &video)?;
        let shown = if r.recorded.is_some() { "recorded left, the VAE's reconstruction middle, model right" } else { "the VAE's reconstruction left, model right" };
        println!("rollout of the held-out clip that moves most ({shown}): {}", r.path.display());
        let line = |what: &str, s: bwm_trainer::report::Scores| {
            let (verdict, margin) = if s.model_psnr >= s.copy_last_psnr { ("AHEAD of", s.model_psnr - s.copy_last_psnr) } else { ("BEHIND", s.copy_last_psnr - s.model_psnr) };
            println!(
                "  against {what}: model PSNR {:.2} dB, holding the last given frame {:.2} dB: the model is {verdict} that baseline by {margin:.2} dB",
                s.model_psnr, s.copy_last_psnr
            );
        };
        println!("{} held-out clips, {} predicted frames each:", r.clips, r.future_frames);
        line("the VAE's reconstruction of the true frames (what the model learns to predict)", r.decoded);
        if let (Some(s), Some(ceiling)) = (r.recorded, r.vae_ceiling_psnr) {
            line("the recorded frames", s);
            println!("  (the VAE's reconstruction itself scores {ceiling:.2} dB against the recorded frames: no model decoding with it can do better there)");
        }
    }
    Ok(())
}
