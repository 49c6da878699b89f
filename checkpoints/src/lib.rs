//! Checkpoint files: safetensors written tensor by tensor, checkpoint directories that appear
//! atomically (temporary directory, fsync, rename, `latest` pointer, keep-last-K), and the
//! training state that lets a run resume exactly. Interchange with the layouts people publish:
//! key maps (Wan-native / diffusers / BWM release), export to a Hugging Face model repository,
//! pushing it to the Hub, conversions, and loading any layout from a folder or a Hub repo id.

pub mod atomic_dir;
pub mod contract;
pub mod convert;
pub mod export;
pub mod hub;
pub mod keymap;
pub mod lora_export;
pub mod model_card;
pub mod open;
pub mod optimizer_shards;
pub mod repo;
pub mod run_dir;
pub mod run_info;
pub mod sampler;
pub mod sources;
pub mod tensor_file;

pub use export::{export, ExportDtype, ExportOptions, ExportReport};
pub use keymap::DitLayout;
pub use open::{load_model, open_any, OpenedWeights};
pub use run_dir::{CheckpointRoot, StepDir};
pub use tensor_file::{read_tensors, write_tensors, write_tensors_replacing};
