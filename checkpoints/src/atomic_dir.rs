//! Folders that appear whole: written under a hidden temporary folder beside the destination
//! (`.<name>.tmp-<pid>`), fsynced, then renamed into place, so that an interrupted export or
//! conversion leaves only that temporary folder (removed by the next write once its process is
//! gone), never a half-written model repository.

use std::path::{Path, PathBuf};

use anyhow::{ensure, Context, Result};

/// Removes `.{name}.tmp-<pid>` folders beside `out` whose writer process is gone.
fn remove_stale_temporaries(parent: &Path, name: &str) {
    let prefix = format!(".{name}.tmp-");
    let Ok(entries) = std::fs::read_dir(parent) else { return };
    for e in entries.flatten() {
        let n = e.file_name().to_string_lossy().to_string();
        if let Some(pid) = n.strip_prefix(&prefix) {
            let alive = pid.parse::<u32>().is_ok_and(|p| p == std::process::id() || Path::new(&format!("/proc/{p}")).exists());
            if !alive {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
}

fn sync_tree(dir: &Path) -> Result<()> {
    for e in std::fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))? {
        let p = e?.path();
        if p.is_dir() {
            sync_tree(&p)?;
        } else {
            std::fs::File::open(&p).and_then(|f| f.sync_all()).with_context(|| format!("syncing {}", p.display()))?;
        }
    }
    std::fs::File::open(dir).and_then(|f| f.sync_all()).with_context(|| format!("syncing {}", dir.display()))
}

/// Fills a fresh temporary folder beside `out` with `fill`, fsyncs it and renames it to `out`.
/// `out` may not exist as a non-empty folder unless `overwrite`; on failure nothing is left.
pub fn write_dir_atomically<T>(out: &Path, overwrite: bool, fill: impl FnOnce(&Path) -> Result<T>) -> Result<T> {
    let name = out
        .file_name()
        .and_then(|n| n.to_str())
        .with_context(|| format!("{}: the output must name a folder", out.display()))?
        .to_string();
    if out.exists() {
        ensure!(out.is_dir(), "{} exists and is not a folder", out.display());
        let empty = std::fs::read_dir(out).with_context(|| format!("listing {}", out.display()))?.next().is_none();
        ensure!(empty || overwrite, "{} exists and is not empty; pass --overwrite to replace it", out.display());
    }
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).with_context(|| format!("creating {}", parent.display()))?;
    remove_stale_temporaries(&parent, &name);
    let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).with_context(|| format!("removing {}", tmp.display()))?;
    }
    std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    let result = fill(&tmp).and_then(|v| sync_tree(&tmp).map(|_| v));
    let value = match result {
        Ok(v) => v,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
    };
    if out.exists() {
        let old = parent.join(format!(".{name}.old-{}", std::process::id()));
        std::fs::rename(out, &old).with_context(|| format!("moving the old {} aside", out.display()))?;
        if let Err(e) = std::fs::rename(&tmp, out) {
            let _ = std::fs::rename(&old, out);
            return Err(e).with_context(|| format!("renaming {} to {}", tmp.display(), out.display()));
        }
        std::fs::remove_dir_all(&old).with_context(|| format!("removing the replaced {}", old.display()))?;
    } else {
        std::fs::rename(&tmp, out).with_context(|| format!("renaming {} to {}", tmp.display(), out.display()))?;
    }
    std::fs::File::open(&parent).and_then(|f| f.sync_all()).ok();
    Ok(value)
}
