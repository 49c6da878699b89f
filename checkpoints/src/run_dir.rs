//! A run's checkpoint directory: `step-00000100/` folders that appear only when complete (written
//! under a temporary name, fsynced, then renamed), a `latest` file naming the newest, and pruning
//! to the last K. A crash mid-write leaves a `.tmp-*` folder that is ignored and removed later,
//! and so is a staging folder (`staging_path`) where ranks put their optimizer shards of a step
//! before it is written.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// The file written last inside a checkpoint; a step folder without it is not a checkpoint.
pub const STATE_FILE: &str = "state.json";
const LATEST: &str = "latest";

pub struct CheckpointRoot {
    pub root: PathBuf,
}

/// A complete checkpoint folder and its step.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StepDir {
    pub step: u64,
    pub path: PathBuf,
}

const STAGING_SUFFIX: &str = ".optimizer-shards";

fn step_name(step: u64) -> String {
    format!("step-{step:08}")
}

fn parse_step(name: &str) -> Option<u64> {
    name.strip_prefix("step-")?.parse().ok()
}

fn sync_dir(path: &Path) -> Result<()> {
    fs::File::open(path).and_then(|f| f.sync_all()).with_context(|| format!("syncing {}", path.display()))
}

impl CheckpointRoot {
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }

    /// Where the checkpoint of `step` lives (whether or not it exists).
    pub fn step_path(&self, step: u64) -> PathBuf {
        self.root.join(step_name(step))
    }

    /// The folder where the data-parallel ranks gather their optimizer shards of `step` before it
    /// is saved; `save(step, ..)` leaves it alone and removes those of other steps (a crash's).
    pub fn staging_path(&self, step: u64) -> PathBuf {
        self.root.join(format!(".{}{STAGING_SUFFIX}", step_name(step)))
    }

    /// Writes checkpoint `step`: `write` fills a fresh temporary folder (and must write
    /// `state.json` last); then every file is fsynced, the folder renamed into place, `latest`
    /// updated and all but the newest `keep_last` checkpoints removed.
    pub fn save(&self, step: u64, keep_last: usize, write: impl FnOnce(&Path) -> Result<()>) -> Result<StepDir> {
        fs::create_dir_all(&self.root).with_context(|| format!("creating {}", self.root.display()))?;
        self.remove_stale_temporaries(step)?;
        let name = step_name(step);
        let tmp = self.root.join(format!(".{name}.tmp-{}", std::process::id()));
        if tmp.exists() {
            fs::remove_dir_all(&tmp).with_context(|| format!("removing {}", tmp.display()))?;
        }
        fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
        let written = write(&tmp).and_then(|()| {
            if tmp.join(STATE_FILE).is_file() {
                Ok(())
            } else {
                Err(anyhow::anyhow!("checkpoint writer left no {STATE_FILE} in {}", tmp.display()))
            }
        });
        if let Err(e) = written {
            fs::remove_dir_all(&tmp).ok();
            return Err(e);
        }
        for entry in fs::read_dir(&tmp)? {
            let path = entry?.path();
            if path.is_file() {
                fs::File::open(&path).and_then(|f| f.sync_all()).with_context(|| format!("syncing {}", path.display()))?;
            }
        }
        sync_dir(&tmp)?;
        let dest = self.step_path(step);
        if dest.exists() {
            // Re-saving a step (a resumed run reaching it again): move the old one aside first so
            // that `dest` is never missing a complete checkpoint for longer than one rename.
            let old = self.root.join(format!(".{name}.old-{}", std::process::id()));
            fs::rename(&dest, &old)?;
            fs::rename(&tmp, &dest)?;
            fs::remove_dir_all(&old).ok();
        } else {
            fs::rename(&tmp, &dest).with_context(|| format!("renaming {} to {}", tmp.display(), dest.display()))?;
        }
        sync_dir(&self.root)?;
        let latest_tmp = self.root.join(format!(".{LATEST}.tmp-{}", std::process::id()));
        fs::write(&latest_tmp, format!("{name}\n"))?;
        fs::File::open(&latest_tmp)?.sync_all()?;
        fs::rename(&latest_tmp, self.root.join(LATEST))?;
        sync_dir(&self.root)?;
        self.prune(keep_last)?;
        Ok(StepDir { step, path: dest })
    }

    /// Every complete checkpoint, oldest first.
    pub fn list(&self) -> Result<Vec<StepDir>> {
        if !self.root.is_dir() {
            return Ok(Vec::new());
        }
        let mut out = Vec::new();
        for entry in fs::read_dir(&self.root).with_context(|| format!("listing {}", self.root.display()))? {
            let entry = entry?;
            let name = entry.file_name();
            let Some(step) = name.to_str().and_then(parse_step) else { continue };
            if entry.path().join(STATE_FILE).is_file() {
                out.push(StepDir { step, path: entry.path() });
            }
        }
        out.sort_by_key(|d| d.step);
        Ok(out)
    }

    /// The newest complete checkpoint: the one `latest` names when it is complete, else the
    /// highest complete step folder.
    pub fn latest(&self) -> Result<Option<StepDir>> {
        if let Ok(text) = fs::read_to_string(self.root.join(LATEST)) {
            let name = text.trim();
            if let Some(step) = parse_step(name) {
                let path = self.root.join(name);
                let newest = self.list()?.last().map(|d| d.step).unwrap_or(0);
                if path.join(STATE_FILE).is_file() && step >= newest {
                    return Ok(Some(StepDir { step, path }));
                }
            }
        }
        Ok(self.list()?.pop())
    }

    fn prune(&self, keep_last: usize) -> Result<()> {
        let all = self.list()?;
        let excess = all.len().saturating_sub(keep_last.max(1));
        for old in &all[..excess] {
            fs::remove_dir_all(&old.path).with_context(|| format!("removing old checkpoint {}", old.path.display()))?;
        }
        Ok(())
    }

    /// What writers that died left (any `.step-*.tmp-*`, `.step-*.old-*` or `.latest.tmp-*` not
    /// of this process), and staging folders of steps other than `step`.
    fn remove_stale_temporaries(&self, step: u64) -> Result<()> {
        let pid = std::process::id();
        let staging = self.staging_path(step);
        for entry in fs::read_dir(&self.root)? {
            let entry = entry?;
            let name = entry.file_name().to_string_lossy().to_string();
            let dead_writer = |kind: &str| name.contains(kind) && !name.ends_with(&format!("{kind}{pid}"));
            let stale_temporary = dead_writer(".tmp-") || dead_writer(".old-");
            let stale_staging = name.ends_with(STAGING_SUFFIX) && entry.path() != staging;
            if name.starts_with(".step-") && (stale_temporary || stale_staging) {
                fs::remove_dir_all(entry.path()).ok();
            } else if name.starts_with(&format!(".{LATEST}.tmp-")) && dead_writer(".tmp-") {
                fs::remove_file(entry.path()).ok();
            }
        }
        Ok(())
    }
}

/// Whether `dir` is a training checkpoint folder (`state.json` + `model.safetensors`).
pub fn is_training_checkpoint(dir: &Path) -> bool {
    dir.is_dir() && dir.join(STATE_FILE).is_file()
}

#[cfg(test)]
mod tests {
    use super::*;
    use anyhow::bail;

    /// A checkpoint root that does not exist yet, inside a folder removed on drop.
    fn tmp(name: &str) -> (bwm_testdir::TestDir, CheckpointRoot) {
        let dir = bwm_testdir::TestDir::new(name);
        let root = CheckpointRoot::new(dir.join("checkpoints"));
        (dir, root)
    }

    #[test]
    fn saves_points_latest_and_keeps_the_last_k() {
        let (_dir, root) = tmp("keep");
        for step in [10, 20, 30] {
            root.save(step, 2, |d| Ok(fs::write(d.join(STATE_FILE), format!("{step}"))?)).unwrap();
        }
        let steps: Vec<u64> = root.list().unwrap().iter().map(|d| d.step).collect();
        assert_eq!(steps, vec![20, 30]);
        assert_eq!(root.latest().unwrap().unwrap().step, 30);
    }

    #[test]
    fn a_failed_write_leaves_the_previous_checkpoint_latest() {
        let (_dir, root) = tmp("fail");
        root.save(1, 3, |d| Ok(fs::write(d.join(STATE_FILE), "1")?)).unwrap();
        let err = root.save(2, 3, |d| {
            fs::write(d.join("model.safetensors"), "partial")?;
            bail!("disk full")
        });
        assert!(err.is_err());
        assert_eq!(root.latest().unwrap().unwrap().step, 1);
        assert!(root.save(3, 3, |_| Ok(())).unwrap_err().to_string().contains(STATE_FILE));
        assert_eq!(root.latest().unwrap().unwrap().step, 1);
    }

    #[test]
    fn saving_a_step_keeps_its_staging_folder_and_removes_other_steps() {
        let (_dir, root) = tmp("staging");
        let (current, crashed) = (root.staging_path(3), root.staging_path(7));
        for d in [&current, &crashed] {
            fs::create_dir_all(d).unwrap();
        }
        root.save(3, 3, |d| {
            assert!(current.is_dir(), "the step's own staging folder is in use while it is written");
            Ok(fs::write(d.join(STATE_FILE), "3")?)
        })
        .unwrap();
        assert!(current.is_dir() && !crashed.exists());
    }

    /// Names of the entries of the checkpoint root, sorted.
    fn names(root: &CheckpointRoot) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(&root.root).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        names.sort();
        names
    }

    #[test]
    fn a_crash_between_the_renames_of_a_re_save_keeps_the_checkpoint() {
        let (_dir, root) = tmp("dead");
        root.save(1, 3, |d| Ok(fs::write(d.join(STATE_FILE), "1")?)).unwrap();
        // Killed between moving a re-saved step aside and renaming its replacement, and before
        // `latest` was renamed: the step folder is missing, latest falls back to what is complete.
        let dead = u32::MAX;
        fs::rename(root.step_path(1), root.root.join(format!(".step-00000001.old-{dead}"))).unwrap();
        fs::create_dir_all(root.root.join(format!(".step-00000001.tmp-{dead}"))).unwrap();
        fs::create_dir_all(root.root.join(format!(".step-00000002.tmp-{dead}"))).unwrap();
        fs::write(root.root.join(format!(".latest.tmp-{dead}")), "step-00000002\n").unwrap();
        assert!(root.latest().unwrap().is_none());
        // The next save puts the moved-aside checkpoint back and removes the rest.
        root.save(2, 3, |d| Ok(fs::write(d.join(STATE_FILE), "2")?)).unwrap();
        assert_eq!(names(&root), ["latest", "step-00000001", "step-00000002"]);
        assert_eq!(fs::read_to_string(root.step_path(1).join(STATE_FILE)).unwrap(), "1");
    }

    /// A process that runs until dropped.
    struct Live(std::process::Child);

    impl Drop for Live {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }

    #[test]
    fn only_the_temporaries_of_writers_that_are_gone_are_removed() {
        let (_dir, root) = tmp("live");
        let mut live = Live(std::process::Command::new("sleep").arg("600").spawn().unwrap());
        let pid = live.0.id();
        fs::create_dir_all(&root.root).unwrap();
        let theirs = [format!(".step-00000005.tmp-{pid}"), format!(".step-00000004.old-{pid}"), format!(".latest.tmp-{pid}")];
        for name in &theirs[..2] {
            fs::create_dir_all(root.root.join(name)).unwrap();
        }
        fs::write(root.root.join(&theirs[2]), "step-00000005\n").unwrap();
        fs::create_dir_all(root.step_path(4)).unwrap();
        fs::write(root.step_path(4).join(STATE_FILE), "4").unwrap();
        root.save(1, 3, |d| Ok(fs::write(d.join(STATE_FILE), "1")?)).unwrap();
        for name in &theirs {
            assert!(root.root.join(name).exists(), "{name} of a live writer was removed: {:?}", names(&root));
        }
        let _ = live.0.kill();
        live.0.wait().unwrap();
        root.save(2, 3, |d| Ok(fs::write(d.join(STATE_FILE), "2")?)).unwrap();
        assert_eq!(names(&root), ["latest", "step-00000001", "step-00000002", "step-00000004"]);
    }

    #[test]
    fn missing_root_has_no_latest() {
        assert!(tmp("none").1.latest().unwrap().is_none());
    }
}
