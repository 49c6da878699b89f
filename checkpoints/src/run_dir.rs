//! A run's checkpoint directory: `step-00000100/` folders that appear only when complete (written
//! under a temporary name, fsynced, then renamed), a `latest` file naming the newest, and pruning
//! to the last K. A crash mid-write leaves a `.tmp-PID` folder that is ignored and removed later
//! (once process PID is gone), and so is a staging folder (`staging_path`) where ranks put their
//! optimizer shards of a step before it is written. Re-saving a step moves the previous copy
//! aside first (`.old-PID`); a crash before its replacement is in place leaves it there, and the
//! next start (`recover`) or save puts it back.
//!
//! One process writes a run folder: `RunLock` (`train.lock`, held by rank 0 of the job for the
//! whole run) makes a second `bwm train` on a live run fail at once. The staging folders carry no
//! pid: every rank writes there, and only ranks of the job whose rank 0 holds the lock get that far.

use std::fs;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

/// The file written last inside a checkpoint; a step folder without it is not a checkpoint.
pub const STATE_FILE: &str = "state.json";
const LATEST: &str = "latest";
/// The lock file of a run folder (`RunLock`).
pub const LOCK_FILE: &str = "train.lock";

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
        self.clean_up(Some(&self.staging_path(step)))?;
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
            // Re-saving a step (a resumed run reaching it again): the old copy is moved aside
            // first; a crash before the new one is in place leaves it as `.old-PID`, which
            // `recover` puts back, so a complete `step-N` survives a crash at any point. It is
            // removed only once both renames are durable.
            let old = self.root.join(format!(".{name}.old-{}", std::process::id()));
            fs::rename(&dest, &old).with_context(|| format!("moving {} aside", dest.display()))?;
            fs::rename(&tmp, &dest).with_context(|| format!("renaming {} to {}", tmp.display(), dest.display()))?;
            sync_dir(&self.root)?;
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

    /// Repairs what a crash left, before the run's checkpoints are looked at: a re-saved step's
    /// previous copy that was moved aside (`.step-N.old-PID`) becomes `step-N` again when there
    /// is no complete `step-N`, and the temporaries of writers that are gone are removed, with
    /// every optimizer-shard staging folder. For the process that holds the run's `RunLock`.
    pub fn recover(&self) -> Result<()> {
        if !self.root.is_dir() {
            return Ok(());
        }
        self.clean_up(None)
    }

    /// `recover`'s work, keeping the staging folder `keep` (the step being saved).
    fn clean_up(&self, keep: Option<&Path>) -> Result<()> {
        let entries: Vec<(String, PathBuf)> = fs::read_dir(&self.root)
            .with_context(|| format!("listing {}", self.root.display()))?
            .map(|e| e.map(|e| (e.file_name().to_string_lossy().into_owned(), e.path())))
            .collect::<std::io::Result<_>>()?;
        // Moved-aside checkpoints first, so that a complete `step-N` is there before the
        // temporaries are judged.
        for (name, path) in &entries {
            let Some((step, ".old-", pid)) = temporary(name) else { continue };
            if !writer_is_gone(pid) {
                continue;
            }
            let dest = self.root.join(step);
            if dest.join(STATE_FILE).is_file() || !path.join(STATE_FILE).is_file() {
                fs::remove_dir_all(path).ok();
                continue;
            }
            if dest.exists() {
                fs::remove_dir_all(&dest).with_context(|| format!("removing the incomplete {}", dest.display()))?;
            }
            fs::rename(path, &dest).with_context(|| format!("putting {} back as {}", path.display(), dest.display()))?;
            sync_dir(&self.root)?;
            eprintln!("checkpoints: {} was moved aside by a save that did not finish; put back", dest.display());
        }
        for (name, path) in &entries {
            match temporary(name) {
                Some((_, ".tmp-", pid)) if writer_is_gone(pid) && path.exists() => {
                    let _ = if path.is_dir() { fs::remove_dir_all(path) } else { fs::remove_file(path) };
                }
                _ if name.starts_with(".step-") && name.ends_with(STAGING_SUFFIX) && Some(path.as_path()) != keep => {
                    fs::remove_dir_all(path).ok();
                }
                _ => {}
            }
        }
        Ok(())
    }
}

/// `.step-N.tmp-PID`, `.step-N.old-PID` or `.latest.tmp-PID`: (`step-N` or `latest`, the kind, PID).
fn temporary(name: &str) -> Option<(&str, &'static str, u32)> {
    let rest = name.strip_prefix('.')?;
    [".tmp-", ".old-"].into_iter().find_map(|kind| {
        let (base, pid) = rest.rsplit_once(kind)?;
        (parse_step(base).is_some() || (base == LATEST && kind == ".tmp-")).then_some((base, kind, pid.parse().ok()?))
    })
}

/// Whether the process that named a temporary after `pid` is gone: no process `pid` runs on this
/// host. This process's own pid counts as gone: what carries it before it writes is a dead
/// predecessor's that had the same pid (a restarted container). Across hosts the run lock is what
/// keeps two writers apart; a pid that happens to be alive here only leaves its folder in place.
fn writer_is_gone(pid: u32) -> bool {
    if pid == std::process::id() {
        return true;
    }
    let Ok(pid) = libc::pid_t::try_from(pid) else { return true };
    if pid <= 0 {
        return true;
    }
    // SAFETY: signal 0 sends nothing; it only asks whether the process exists.
    let alive = unsafe { libc::kill(pid, 0) } == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM);
    !alive
}

/// One writer per run folder: an exclusive OS advisory lock (`flock`) on `<run>/train.lock`, which
/// the kernel releases when the holder exits however it exits, so a `kill -9` leaves no stale lock
/// to clear by hand. The file records the holder (pid, host) only for the message a second writer
/// gets; the holder empties it when it lets go, so a record found on taking the lock names a
/// holder that was killed. Held by rank 0 of a job for the whole run (see the trainer).
pub struct RunLock {
    file: fs::File,
    path: PathBuf,
    /// The holder a crash left recorded (`pid P on host H`), when this lock took over from one.
    pub previous: Option<String>,
}

impl RunLock {
    /// Takes the lock of the run folder `run` (created when missing), or fails at once naming the
    /// process that holds it.
    pub fn acquire(run: &Path) -> Result<Self> {
        fs::create_dir_all(run).with_context(|| format!("creating {}", run.display()))?;
        let path = run.join(LOCK_FILE);
        let file = fs::OpenOptions::new().read(true).write(true).create(true).truncate(false).open(&path).with_context(|| format!("opening {}", path.display()))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(fs::TryLockError::WouldBlock) => {
                // The holder writes its record just after locking: give it a moment.
                let mut holder = read_holder(&file);
                for _ in 0..20 {
                    if holder.is_some() {
                        break;
                    }
                    std::thread::sleep(std::time::Duration::from_millis(50));
                    holder = read_holder(&file);
                }
                let holder = holder.unwrap_or_else(|| "a process that has not recorded itself yet".into());
                bail!(
                    "{} is in use: another `bwm train` ({holder}) holds {}; wait for it to end or stop it, or pick another run.out_dir",
                    run.display(),
                    path.display()
                );
            }
            Err(fs::TryLockError::Error(e)) => return Err(e).with_context(|| format!("locking {}", path.display())),
        }
        let previous = read_holder(&file);
        let me = format!("pid {} on host {}", std::process::id(), hostname());
        let record = (|| -> std::io::Result<()> {
            file.set_len(0)?;
            file.write_all_at(format!("{me}\n").as_bytes(), 0)?;
            file.sync_data()
        })();
        record.with_context(|| format!("writing {}", path.display()))?;
        if let Some(p) = &previous {
            eprintln!("{}: taking over from {p}, which ended without letting go (killed?)", run.display());
        }
        Ok(Self { file, path, previous })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        // An empty record says the holder let go; the kernel drops the lock with the file.
        let _ = self.file.set_len(0);
    }
}

/// The holder recorded in a lock file, when there is one.
fn read_holder(file: &fs::File) -> Option<String> {
    let mut buf = vec![0u8; 4096];
    let n = file.read_at(&mut buf, 0).ok()?;
    let text = String::from_utf8_lossy(&buf[..n]).trim().to_string();
    (!text.is_empty()).then_some(text)
}

/// This host's name (Linux: the kernel's).
fn hostname() -> String {
    fs::read_to_string("/proc/sys/kernel/hostname")
        .or_else(|_| fs::read_to_string("/etc/hostname"))
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "localhost".to_string())
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

    /// Held by the tests that start a process and by the lock's test: a child forked while the
    /// lock file is open holds a copy of its descriptor, and with it the lock, until it execs, so
    /// on a loaded machine a start beside the lock's test could hold the lock it just let go.
    static SPAWNING: std::sync::Mutex<()> = std::sync::Mutex::new(());

    impl Drop for Live {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }

    #[test]
    fn only_the_temporaries_of_writers_that_are_gone_are_removed() {
        let (_dir, root) = tmp("live");
        let _spawning = SPAWNING.lock().unwrap_or_else(|e| e.into_inner());
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
    fn recover_puts_a_moved_aside_checkpoint_back_before_the_latest_is_looked_for() {
        let (_dir, root) = tmp("recover");
        assert!(root.recover().is_ok(), "no checkpoint folder yet");
        for step in [1, 2] {
            root.save(step, 3, |d| Ok(fs::write(d.join(STATE_FILE), format!("{step}"))?)).unwrap();
        }
        // Killed re-saving step 2 between its two renames, a staging folder left behind.
        fs::rename(root.step_path(2), root.root.join(".step-00000002.old-0")).unwrap();
        fs::create_dir_all(root.root.join(".step-00000002.tmp-0")).unwrap();
        fs::create_dir_all(root.staging_path(2)).unwrap();
        assert_eq!(root.latest().unwrap().unwrap().step, 1);
        root.recover().unwrap();
        assert_eq!(root.latest().unwrap().unwrap().step, 2);
        assert_eq!(names(&root), ["latest", "step-00000001", "step-00000002"]);
        // A moved-aside copy is dropped when a complete step folder is there.
        fs::create_dir_all(root.root.join(".step-00000001.old-0")).unwrap();
        fs::write(root.root.join(".step-00000001.old-0").join(STATE_FILE), "old").unwrap();
        root.recover().unwrap();
        assert_eq!(fs::read_to_string(root.step_path(1).join(STATE_FILE)).unwrap(), "1");
        assert_eq!(names(&root), ["latest", "step-00000001", "step-00000002"]);
    }

    #[test]
    fn a_run_folder_has_one_holder_and_a_killed_holders_record_is_taken_over() {
        let dir = bwm_testdir::TestDir::new("lock");
        let _spawning = SPAWNING.lock().unwrap_or_else(|e| e.into_inner());
        let run = dir.join("run");
        let lock = RunLock::acquire(&run).unwrap();
        assert_eq!(lock.previous, None);
        let me = format!("pid {} on host {}", std::process::id(), hostname());
        let e = format!("{:#}", RunLock::acquire(&run).err().expect("a second holder"));
        assert!(e.contains(&me) && e.contains(LOCK_FILE), "{e}");
        // Let go: the record is emptied and the next holder takes over from nobody.
        drop(lock);
        assert_eq!(fs::read_to_string(run.join(LOCK_FILE)).unwrap(), "");
        let lock = RunLock::acquire(&run).unwrap();
        assert_eq!((lock.previous.as_deref(), lock.path()), (None, run.join(LOCK_FILE).as_path()));
        drop(lock);
        // A holder killed with SIGKILL: the kernel released its lock, its record stayed.
        fs::write(run.join(LOCK_FILE), "pid 4242 on host elsewhere\n").unwrap();
        let lock = RunLock::acquire(&run).unwrap();
        assert_eq!(lock.previous.as_deref(), Some("pid 4242 on host elsewhere"));
        assert_eq!(fs::read_to_string(run.join(LOCK_FILE)).unwrap().trim(), me);
    }

    #[test]
    fn missing_root_has_no_latest() {
        assert!(tmp("none").1.latest().unwrap().is_none());
    }
}
