//! The BWM world model as a library, for programs that embed the simulator (a policy-learning
//! loop, an RL environment, a server of their own) without the `bwm` command line.
//!
//! Open a model with [`WorldModelOptions::load`], start a [`Rollout`] from an episode's first
//! frame and action with [`WorldModel::rollout`], then call [`Rollout::next_chunk`] with each
//! chunk's actions to get its frames; [`server::serve`] puts the same model behind HTTP
//! (`docs/serve.md`). Above the model sit the data engine ([`rollout::run`]: generated episodes
//! as a LeRobot dataset), the fidelity report ([`fidelity::run`]: whole-episode rollouts scored
//! against the real frames) and the policy evaluator ([`evaluate::run`]: policies served over
//! openpi's websocket protocol in closed loop, judged, with per-task success rates); each is what
//! the `bwm` subcommand of the same name runs; [`lanes`] splits their episodes in flight into lanes
//! that take turns on CUDA streams of their own; [`fallible`] turns libtorch's failures (an
//! allocation a user's sizes make impossible) into errors naming the size. [`bench`](mod@bench) times the DiT, the VAE and whole rollout
//! chunks; [`demo`] is `bwm demo`. `examples/step.rs` steps a tiny random model twice and writes
//! the frames:
//!
//! ```no_run
//! use bwm_inference::{WorldModelOptions, tch::{Kind, Tensor}};
//! let wm = WorldModelOptions { random_weights: Some("tiny".into()), future: Some(4), sample_steps: Some(2), ..Default::default() }.load()?;
//! let x0 = Tensor::zeros([3, 32, 32], (Kind::Float, wm.device));
//! let a0 = Tensor::zeros([wm.action_dim() as i64], (Kind::Float, wm.device));
//! let mut rollout = wm.rollout(&x0, &a0)?;
//! let chunk = rollout.next_chunk(&Tensor::zeros([4, wm.action_dim() as i64], (Kind::Float, wm.device)))?;
//! println!("{:?}", chunk.frames.size()); // [3, 4, 32, 32], in [-1, 1]
//! # anyhow::Ok(())
//! ```

pub mod bench;
pub mod demo;
pub mod evaluate;
pub mod fallible;
pub mod fidelity;
pub mod graphed;
pub mod lanes;
pub mod msgpack_numpy;
pub mod rollout;
pub mod server;
pub mod world_model;

pub use bwm_model::rollout::{Chunk, Rollout, RolloutSpec};
pub use tch;
pub use world_model::{tensor_rows, WorldModel, WorldModelOptions};
