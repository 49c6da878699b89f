//! Robot datasets in, action-aligned clips out. This crate knows files and formats; it knows
//! nothing of the model.

pub mod bwm_layout;
pub mod stats;

pub use bwm_layout::{ActionSpec, BwmDataset, Episode};
pub use stats::ActionStats;
