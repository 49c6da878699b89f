//! `bwm`: the one command of the BWM trainer.

mod bench;
mod bench_train;
mod convert;
mod demo;
mod evaluate;
mod export;
mod fidelity;
mod prepare;
mod reconstruct;
mod reference;
mod rollout;
mod sampler;
mod serve;
mod stats;
mod train;
mod train_light_decoder;
mod train_vae;
mod world_model;

use anyhow::Result;
use bwm_launcher::{launch, submit};
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "bwm",
    version,
    about = "Boundless World Model: post-train Wan2.2-TI2V-5B into an action-conditioned robot simulator"
)]
pub(crate) struct Cli {
    /// Attention kernels for every scaled-dot-product attention of this run: libtorch's own choice
    /// (auto; cuDNN on Hopper with bf16) or one family forced (flash, efficient, cudnn, math), with
    /// the math path for the attentions a forced family cannot take. The bench commands print the
    /// kernel the DiT's attention gets.
    #[arg(long, global = true, default_value = "auto", env = "BWM_SDP_BACKEND")]
    sdp_backend: bwm_sdp::SdpBackend,
    /// Let cuDNN time its convolution algorithms for each new shape and keep the fastest (the VAE's
    /// 3D convolutions; fixed shapes, as rollouts have, pay the timing once). The kernels chosen
    /// may differ between runs, so bit-exact repeats and resumes need it off.
    #[arg(long, global = true, env = "BWM_CUDNN_BENCHMARK")]
    cudnn_benchmark: bool,
    /// Threads of libtorch's CPU operator pool. Default: OMP_NUM_THREADS when set; else 1 on a
    /// machine with a CUDA device, where the CPU only feeds the GPU and a pool of one spinning
    /// thread per core beside the launching thread slows launch-bound steps (docs/performance.md,
    /// "CPU threads beside the GPU"); else libtorch's own choice (one per core).
    #[arg(long, global = true, env = "BWM_CPU_THREADS", value_parser = clap::value_parser!(i32).range(1..))]
    cpu_threads: Option<i32>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// One sampling pass of the tiny model (random weights) on a bundled clip's actions, printed step by step.
    Demo(demo::DemoArgs),
    /// Per-dimension action statistics of a dataset's training split, as a stat.json.
    Stats(stats::StatsArgs),
    /// Cut a dataset into action-aligned clips and encode them into a latent cache for training.
    Prepare(prepare::PrepareArgs),
    /// Data engine: roll the world model out from each episode's first frame with recorded, file or
    /// perturbed actions, and write the result as a LeRobot v2.1 dataset.
    Rollout(rollout::RolloutArgs),
    /// Show or record the sampler (steps, solver) a checkpoint's fidelity was measured at, which
    /// rollout, fidelity, evaluate, serve and bench-rollout then use by default.
    Sampler(sampler::SamplerArgs),
    /// Score the world model on held-out episodes: whole-episode rollouts driven by their own and
    /// by another episode's actions, PSNR/SSIM per frame and at horizons, against copy-last-frame.
    Fidelity(fidelity::FidelityArgs),
    /// Evaluate policies served over openpi's websocket protocol in closed loop with the world
    /// model: success judge, per-task success rates, agreement with reference rates.
    Evaluate(evaluate::EvaluateArgs),
    /// Serve the world model over HTTP, one chunk per request (POST /v1/chunk, GET /health).
    Serve(serve::ServeArgs),
    /// Start one process per GPU (or N CPU processes) with torchrun's variables and supervise
    /// them: `bwm launch --nproc-per-node 2 -- train --config ...`.
    Launch(launch::LaunchArgs),
    /// Write a Slurm batch script that runs `bwm launch` on every node (checkpoint, requeue and
    /// resume before the time limit) and submit it: `bwm submit --nodes 2 --gpus-per-node 8 -- train ...`.
    Submit(submit::SubmitArgs),
    /// Post-train the model on a prepared latent cache (`--config configs/tiny.toml`).
    Train(train::TrainArgs),
    /// Fit a small Wan2.2-architecture VAE to a dataset's frames (real pixels for CPU runs).
    TrainVae(train_vae::TrainVaeArgs),
    /// Fit a light decoder (a few per-frame convolutions) to a trained VAE's decoder, for the
    /// world-model commands' --light-decoder.
    TrainLightDecoder(train_light_decoder::TrainLightDecoderArgs),
    /// Round-trip a dataset's frames through a trained VAE: what a world model decoding with it
    /// can show at best (u8 safetensors per episode, and the PSNR).
    Reconstruct(reconstruct::ReconstructArgs),
    /// Print a model preset's module tree summary: tensors and parameters (nothing is allocated).
    Info(bench::InfoArgs),
    /// Time the DiT forward on random weights of a preset at a given clip size.
    BenchForward(bench::BenchForwardArgs),
    /// Time the real training step of a run config on random weights and a synthetic clip.
    BenchTrain(bench_train::BenchTrainArgs),
    /// Time the Wan2.2 VAE encode/decode on random weights, then a long streaming decode.
    BenchVae(bench::BenchVaeArgs),
    /// Time whole rollout chunks (condition encode, sampler, decode) of the world model.
    BenchRollout(bench::BenchRolloutArgs),
    /// Export a training checkpoint as a Hugging Face model repo folder (config, shards, action
    /// encoder, action stats, model card); --push uploads it.
    Export(export::ExportArgs),
    /// Upload a finished export folder to a Hugging Face model repo (what `export --push` does
    /// after exporting; retries a failed push without exporting again).
    Push(export::PushArgs),
    /// Convert DiT weights between the wan, diffusers and bwm-release layouts, or a VAE .pth to safetensors.
    Convert(convert::ConvertArgs),
    /// Print the CLI reference (docs/cli.md) or the run-config reference (docs/config.md), both
    /// generated from the code; --check FILE compares instead.
    Reference(reference::ReferenceArgs),
}

fn main() {
    let cli = Cli::parse();
    bwm_sdp::set_backend(cli.sdp_backend);
    tch::Cuda::cudnn_set_benchmark(cli.cudnn_benchmark);
    match cli.cpu_threads {
        Some(n) => tch::set_num_threads(n),
        None if std::env::var_os("OMP_NUM_THREADS").is_none() && tch::Cuda::is_available() => tch::set_num_threads(1),
        None => {}
    }
    if cli.cudnn_benchmark {
        eprintln!("bwm: cuDNN convolution autotuning on (--cudnn-benchmark)");
    }
    let result: Result<()> = match cli.command {
        Command::Demo(a) => demo::run(a),
        Command::Stats(a) => stats::run(a),
        Command::Prepare(a) => prepare::run(a),
        Command::Rollout(a) => rollout::run(a),
        Command::Sampler(a) => sampler::run(a),
        Command::Fidelity(a) => fidelity::run(a),
        Command::Evaluate(a) => evaluate::run(a),
        Command::Serve(a) => serve::run(a),
        Command::Launch(a) => launch::run(a),
        Command::Submit(a) => submit::run(a),
        Command::Train(a) => train::run(a),
        Command::TrainVae(a) => train_vae::run(a),
        Command::TrainLightDecoder(a) => train_light_decoder::run(a),
        Command::Reconstruct(a) => reconstruct::run(a),
        Command::Info(a) => bench::info(a),
        Command::BenchForward(a) => bench::forward(a),
        Command::BenchVae(a) => bench::vae(a),
        Command::BenchRollout(a) => bench::rollout(a),
        Command::BenchTrain(a) => bench_train::run(a),
        Command::Export(a) => export::run(a),
        Command::Push(a) => export::run_push(a),
        Command::Convert(a) => convert::run(a),
        Command::Reference(a) => reference::run(a),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
