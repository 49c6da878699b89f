//! The output folder the ranks share: each rank's lock and progress file, a folder brought to a
//! state the plan can continue (or refused), and `index.json`, written once every shard is
//! finished by the process that finds it so (or by `bwm prepare --merge`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use bwm_data::latent_cache::{read_index, shard_file_name, write_atomically, write_index, CacheIndex, ClipEntry, IndexExtras, CACHE_VERSION, INDEX_FILE};
use serde::{Deserialize, Serialize};

pub(crate) const LOCK_FILE: &str = ".index.json.lock";

/// One process's record of its finished shards.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RankProgress {
    pub(crate) plan_hash: String,
    pub(crate) rank: usize,
    pub(crate) world: usize,
    pub(crate) shards: usize,
    /// The cache's index without clips, and its extras: what `--merge` needs.
    pub(crate) index: CacheIndex,
    pub(crate) extras: IndexExtras,
    pub(crate) finished: BTreeMap<usize, FinishedShard>,
    pub(crate) done: bool,
}

#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct FinishedShard {
    pub(crate) clips: Vec<ClipEntry>,
    pub(crate) skipped: Vec<ShardSkip>,
}

/// Planned clips that could not be read or enhanced, and why.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ShardSkip {
    pub(crate) episode: i64,
    pub(crate) clips: usize,
    pub(crate) reason: String,
}

/// This rank's claim on the output folder, held while the process runs: a second `bwm prepare`
/// of the same rank into the same folder is refused instead of encoding the same shards twice.
pub const LOCK_PREFIX: &str = ".lock.rank-";

pub(crate) fn lock_rank(out: &Path, rank: usize, world: usize) -> Result<std::fs::File> {
    let path = out.join(format!("{LOCK_PREFIX}{rank}-of-{world}"));
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .with_context(|| format!("creating {}", path.display()))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => bail!(
            "{} is being written by another `bwm prepare` (rank {rank} of {world}, lock {}); wait for it to finish or choose another --out",
            out.display(),
            path.display()
        ),
        Err(std::fs::TryLockError::Error(e)) => Err(e).with_context(|| format!("locking {}", path.display())),
    }
}

pub(crate) fn progress_name(rank: usize, world: usize) -> String {
    format!("progress.rank-{rank}-of-{world}.json")
}

/// Brings the folder to a state this plan can continue: returns true when index.json already
/// holds this plan's complete cache. A cache of another plan is an error unless `overwrite`;
/// then its files are removed (by their owners, so that concurrent processes never touch the
/// same file: each rank its own progress file and stale temporary files, rank 0 the rest).
pub(crate) fn prepare_folder(out: &Path, hash: &str, record: &serde_json::Value, overwrite: bool, rank: usize, world: usize, shards: usize) -> Result<bool> {
    let differs = |stored: Option<&serde_json::Value>, what: &str| -> anyhow::Error {
        let fields = match stored.and_then(|s| s.as_object()) {
            Some(old) => {
                let new = record.as_object().cloned().unwrap_or_default();
                let mut keys: BTreeSet<&String> = old.keys().collect();
                keys.extend(new.keys());
                let names: Vec<&str> = keys.into_iter().filter(|k| old.get(*k) != new.get(*k)).map(|k| k.as_str()).collect();
                format!(" (differs in: {})", names.join(", "))
            }
            None => String::new(),
        };
        anyhow::anyhow!(
            "{} holds {what} prepared with other arguments{fields}; rerun with the same arguments to continue it, or pass --overwrite to replace it",
            out.display()
        )
    };
    let index_path = out.join(INDEX_FILE);
    if index_path.is_file() {
        let extras = read_index(&index_path).map(|(_, e)| e).unwrap_or_default();
        if extras.plan_hash.as_deref() == Some(hash) {
            return Ok(true);
        }
        if !overwrite {
            return Err(differs(extras.plan.as_ref(), "a cache"));
        }
        remove_if_present(&index_path)?;
    }
    for (path, p) in progress_files(out)? {
        let stored = p.as_ref().ok();
        if stored.is_some_and(|p| p.plan_hash == hash) {
            continue;
        }
        if !overwrite {
            return Err(differs(stored.and_then(|p| p.extras.plan.as_ref()), "a partial cache"));
        }
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let current_world = (0..world).any(|r| name == progress_name(r, world));
        if name == progress_name(rank, world) || (!current_world && rank == 0) {
            remove_if_present(&path)?;
        }
    }
    for entry in std::fs::read_dir(out).with_context(|| format!("listing {}", out.display()))? {
        let name = entry?.file_name().to_string_lossy().into_owned();
        let shard_of = |n: &str| n.strip_prefix("shard-").and_then(|n| n.get(..5)).and_then(|n| n.parse::<usize>().ok());
        let stale = if let Some(tmp) = name.strip_prefix('.').filter(|n| n.ends_with(".tmp")) {
            // A temporary file of a process that died, removed by the rank that would write it.
            shard_of(tmp).map_or(tmp.starts_with(&format!("{}.", progress_name(rank, world))), |s| s % world == rank)
        } else {
            overwrite && rank == 0 && (shard_of(&name).is_some_and(|s| s >= shards) || (name.starts_with("clip-") && name.ends_with(".safetensors")))
        };
        if stale {
            remove_if_present(&out.join(&name))?;
        }
    }
    Ok(false)
}

pub(crate) fn remove_if_present(path: &Path) -> Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e).with_context(|| format!("removing {}", path.display())),
        _ => Ok(()),
    }
}

/// Every progress file of the folder, parsed (or why not).
pub(crate) fn progress_files(out: &Path) -> Result<Vec<(PathBuf, Result<RankProgress>)>> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(out).with_context(|| format!("listing {}", out.display()))? {
        let path = entry?.path();
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        if name.starts_with("progress.rank-") && name.ends_with(".json") {
            let parsed = std::fs::read_to_string(&path)
                .map_err(anyhow::Error::from)
                .and_then(|t| Ok(serde_json::from_str::<RankProgress>(&t)?))
                .with_context(|| format!("reading {}", path.display()));
            files.push((path, parsed));
        }
    }
    files.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(files)
}

/// This rank's progress (fresh when it has none of this plan), and the shards other progress
/// files of this plan record as finished.
pub(crate) fn load_progress(out: &Path, hash: &str, rank: usize, world: usize) -> Result<(RankProgress, BTreeMap<usize, FinishedShard>)> {
    let mine = out.join(progress_name(rank, world));
    let mut own = None;
    let mut elsewhere = BTreeMap::new();
    for (path, p) in progress_files(out)? {
        let Ok(p) = p else { continue };
        if p.plan_hash != hash {
            continue;
        }
        if path == mine {
            own = Some(p);
        } else {
            elsewhere.extend(p.finished);
        }
    }
    let fresh = || RankProgress {
        plan_hash: hash.to_string(),
        rank,
        world,
        shards: 0,
        index: CacheIndex {
            version: CACHE_VERSION,
            latent_shape: vec![],
            action_dim: 0,
            pixel_frames: 0,
            history_frames: 0,
            future_frames: 0,
            resolution: [0, 0],
            fps: 0.0,
            vae: String::new(),
            has_frames: false,
            has_latents: true,
            clips: vec![],
        },
        extras: IndexExtras::default(),
        finished: BTreeMap::new(),
        done: false,
    };
    Ok((own.unwrap_or_else(fresh), elsewhere))
}

pub(crate) fn write_progress(out: &Path, p: &RankProgress) -> Result<()> {
    write_atomically(out, &progress_name(p.rank, p.world), serde_json::to_string(p)?.as_bytes())
}

pub(crate) enum Merged {
    Written(CacheIndex),
    Exists(CacheIndex),
    Missing(Vec<usize>),
    Busy(PathBuf),
}

/// Writes index.json when every shard of plan `hash` is finished (by any progress file); only
/// the process that creates the lock file writes it (`force`: regardless of the lock).
pub(crate) fn merge(out: &Path, hash: &str, force: bool) -> Result<Merged> {
    let index_path = out.join(INDEX_FILE);
    if let Ok((index, extras)) = read_index(&index_path) {
        if extras.plan_hash.as_deref() == Some(hash) {
            return Ok(Merged::Exists(index));
        }
    }
    let progress: Vec<RankProgress> = progress_files(out)?.into_iter().filter_map(|(_, p)| p.ok()).filter(|p| p.plan_hash == hash).collect();
    let Some(first) = progress.iter().find(|p| p.shards > 0) else { bail!("{}: no progress file of this plan", out.display()) };
    let mut finished: BTreeMap<usize, &FinishedShard> = BTreeMap::new();
    for p in &progress {
        finished.extend(p.finished.iter().map(|(&s, f)| (s, f)));
    }
    let missing: Vec<usize> = (0..first.shards)
        .filter(|s| !finished.get(s).is_some_and(|f| f.clips.is_empty() || out.join(shard_file_name(*s)).is_file()))
        .collect();
    if !missing.is_empty() {
        return Ok(Merged::Missing(missing));
    }
    let lock = out.join(LOCK_FILE);
    match std::fs::OpenOptions::new().write(true).create_new(true).open(&lock) {
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && !force => return Ok(Merged::Busy(lock)),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
        Err(e) => return Err(e).with_context(|| format!("creating {}", lock.display())),
    }
    let written = (|| -> Result<CacheIndex> {
        let mut index = first.index.clone();
        index.clips = finished.values().flat_map(|f| f.clips.iter().cloned()).collect();
        ensure!(!index.clips.is_empty(), "every planned clip was skipped; see the reasons above");
        write_index(out, INDEX_FILE, &index, &first.extras)?;
        Ok(index)
    })();
    remove_if_present(&lock)?;
    written.map(Merged::Written)
}

/// `bwm prepare --merge`: index.json from the progress files of the one plan in the folder.
pub(crate) fn merge_command(out: &Path) -> Result<()> {
    let files = progress_files(out)?;
    let hashes: BTreeSet<String> = files.iter().filter_map(|(_, p)| p.as_ref().ok()).map(|p| p.plan_hash.clone()).collect();
    let hash = match hashes.len() {
        0 => bail!("{}: no progress files of `bwm prepare` to merge", out.display()),
        1 => hashes.into_iter().next().unwrap_or_default(),
        n => bail!("{}: progress files of {n} different plans; rerun `bwm prepare` with --overwrite", out.display()),
    };
    let all: BTreeMap<usize, FinishedShard> =
        files.into_iter().filter_map(|(_, p)| p.ok()).filter(|p| p.plan_hash == hash).flat_map(|p| p.finished).collect();
    report_skips(&all);
    match merge(out, &hash, true)? {
        Merged::Written(index) | Merged::Exists(index) => {
            println!("prepare --merge: wrote {} ({} clips)", out.join(INDEX_FILE).display(), index.clips.len());
            Ok(())
        }
        Merged::Missing(m) => bail!(
            "{}: {} shards are not finished yet (e.g. {}); run (or rerun) the ranks that own them",
            out.display(),
            m.len(),
            m.iter().take(8).map(|s| shard_file_name(*s)).collect::<Vec<_>>().join(", ")
        ),
        Merged::Busy(lock) => bail!("{} is held", lock.display()),
    }
}

pub(crate) fn report_skips(finished: &BTreeMap<usize, FinishedShard>) {
    let mut by_episode: BTreeMap<i64, (usize, String)> = BTreeMap::new();
    for s in finished.values().flat_map(|f| &f.skipped) {
        let e = by_episode.entry(s.episode).or_insert((0, s.reason.clone()));
        e.0 += s.clips;
    }
    for (episode, (clips, reason)) in by_episode {
        println!("  skipped {clips} {} of episode {episode}: {reason}", if clips == 1 { "clip" } else { "clips" });
    }
}
