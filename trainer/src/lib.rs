//! Training: the BWM objective, AdamW with fp32 master weights, per-block recomputation, the
//! run loop with checkpoints, metrics, TensorBoard and validation.

pub mod bench;
pub mod config;
pub mod dist;
pub mod distill;
pub mod flops;
pub mod fused_adamw;
pub mod grad_engine;
pub mod light_decoder_train;
/// Keyed random draws live with the model (the rollout sampler uses them too).
pub use bwm_model::keyed_rng;
pub mod metrics;
pub mod objective;
pub mod optim;
pub mod recompute;
pub mod report;
pub mod run_log;
pub mod step_graph;
pub mod tensorboard;
pub mod trainer;
pub mod vae_frames;
pub mod vae_train;
pub mod validation;

pub use config::RunConfig;
pub use trainer::{Resume, Trainer};
