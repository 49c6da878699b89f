//! How generated video is scored and charted: PSNR and SSIM of frames against the truth (`image`)
//! and line charts as SVG (`plot`: the training loss curve, the fidelity report's curves).
//!
//! The trainer (validation, the rollout video, the VAE's held-out PSNR) and inference (`bwm
//! fidelity`, `bwm rollout`) both score frames and draw curves. The model is no place for them (it
//! neither reads pixels back nor draws), and the trainer is not one either: a program embedding
//! the world model would link the optimizer, NCCL and the training loop for them. So they live in
//! a crate of their own below both, which needs only tch and plotters.

pub mod image;
pub mod plot;
