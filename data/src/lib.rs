//! Robot datasets in, action-aligned clips out. This crate knows files and formats; it knows
//! nothing of the model.

pub mod actions;
pub mod bwm_layout;
pub mod clips;
pub mod defect;
pub mod frames;
#[cfg(test)]
mod fsync_log;
pub mod latent_cache;
pub mod lerobot;
pub mod lerobot_writer;
pub mod open;
pub mod prefetch;
pub mod robotwin;
pub mod source;
pub mod stats;
pub mod table;
pub mod video;

pub use actions::{ActionSpec, QuatOrder, QuatToEuler};
pub use bwm_layout::{BwmDataset, BwmSource, Episode};
pub use clips::{plan_clips, read_clip_frames, ClipPlan, ClipSpec, ClipWindow, EpisodeClips, EpisodeFrames, SkipReport, Skipped};
pub use defect::{classify, Defect, DefectKind};
pub use frames::ResizeMode;
pub use latent_cache::{CacheIndex, CacheWriter, ClipEntry, IndexExtras, LatentCache, ShardClip};
pub use prefetch::{prefetch_clips, Prefetcher};
pub use lerobot::{LeRobotDataset, LeRobotVersion};
pub use robotwin::{RoboTwinDataset, RoboTwinLayout};
pub use open::open_dataset;
pub use source::{CameraLayout, CameraSelection, EpisodeInfo, EpisodeSource};
pub use stats::{compute_stats, split_episodes, write_stat_json, ActionStats, EpisodeSplit, SplitSpec, StatsResult, ValidationSize};
pub use video::{Mp4Encoder, StreamInfo, VideoInfo};
