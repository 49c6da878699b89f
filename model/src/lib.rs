//! The BWM model: the Wan2.2-TI2V-5B DiT with the BWM action interface, the flow-matching
//! schedule, and weight loading by checkpoint name. No data, distribution or logging here.

pub mod action;
pub mod bwm;
pub mod config;
pub mod convert;
pub mod device;
pub mod dit;
pub mod fp8;
pub mod hand_map;
pub mod keyed_rng;
pub mod light_decoder;
pub mod lora;
pub mod nn;
pub mod pth;
pub mod rollout;
pub mod rope;
pub mod sampler;
pub mod schedule;
pub mod vae;
pub mod vb;
pub mod weight_file;
pub mod weights;

pub use bwm::{frame_timesteps, BwmModel, Layout};
pub use config::{ActionConfig, DitConfig, ModelConfig, Residual};
pub use schedule::FlowSchedule;
pub use vb::{ParamStore, Vb};
pub use weights::{SafetensorsSource, WeightSource, WeightsError};
