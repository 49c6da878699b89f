//! The latent cache from a dataset (what `bwm prepare` runs): cut a dataset's episodes (any format `open_dataset` detects) into action-aligned
//! clips, encode them with the VAE, and write the latent cache the trainer reads (layout in
//! `bwm_data::latent_cache`): shards of `--clips-per-shard` clips, each written whole, so an
//! interrupted run leaves only complete shards, and a rerun with the same arguments skips them.
//!
//! Ranks (`--rank R --world W`, default RANK and WORLD_SIZE) encode the shards s with s % W == R
//! into one folder. A process writes only its own files: its shards (temporary name, then rename)
//! and its progress file `progress.rank-R-of-W.json`, rewritten after each shard. The process that
//! finds every shard done writes `index.json` (a single writer, through an exclusive lock file),
//! or `bwm prepare --merge` does.
//!
//! The modules, in the order of a run: `options` (the command's flags), `plan` (what the cache
//! will hold, and the hash that decides whether a rerun continues it), `folder` (the output folder
//! the ranks share: locks, progress files, the index), `read` (the clips read and resized on a
//! thread of their own), `encode` (batches encoded by the VAE and written in shards), `run` (one
//! `bwm prepare` from start to end).

mod encode;
mod folder;
mod options;
mod plan;
mod read;
mod run;

pub use folder::LOCK_PREFIX;
pub use options::PrepareOptions;
pub use run::run;
