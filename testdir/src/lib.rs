//! Temporary folders of the tests. A test process writes under one folder of its own,
//! `<temp dir>/bwm-tests-<pid>-<random>`, removed when the process exits; each test takes a
//! [`TestDir`] inside it, removed with its contents when dropped, so also when the test fails.
//! `make test` points TMPDIR at a folder of the run, which it removes at the end.
//!
//! Also what the crates' tests share beyond folders: the optional dependencies and where they are
//! found (`optional`: the virtualenv's Python and the other optional dependencies; `files`: the
//! reference files, from the repository, the golden cache or `BWM_SHARED`), and the fixture
//! datasets of `scripts/make_fixtures.py` (`make_fixtures`).

pub mod files;
pub mod optional;
pub use files::{demo_data, golden_dir, golden_generator, reference_path, repo_root};
pub use optional::{need, python, python_with, reference, Dep};

use std::ffi::OsStr;
use std::ops::Deref;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

static ROOT: OnceLock<PathBuf> = OnceLock::new();

extern "C" fn remove_root() {
    if let Some(dir) = ROOT.get() {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// This process's folder, created on first use and removed when the process exits.
pub fn root() -> &'static Path {
    ROOT.get_or_init(|| {
        let dir = tempfile::Builder::new()
            .prefix(&format!("bwm-tests-{}-", std::process::id()))
            .tempdir()
            .unwrap_or_else(|e| panic!("creating a folder in {}: {e}", std::env::temp_dir().display()))
            .keep();
        // Statics are never dropped, and the test harness ends the process with `exit`.
        // SAFETY: registers a plain function with no preconditions.
        let registered = unsafe { libc::atexit(remove_root) };
        assert_eq!(registered, 0, "atexit failed");
        dir
    })
}

/// A folder under [`root`] that lasts until the process exits, for what the tests of one binary
/// share (fixtures written once).
pub fn shared_dir(name: &str) -> PathBuf {
    let dir = root().join(name);
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("creating {}: {e}", dir.display()));
    dir
}

/// A fresh folder for one test, removed when dropped ([`TestDir::new`]).
pub fn tmp_dir(name: &str) -> TestDir {
    TestDir::new(name)
}

/// Writes the fixture datasets (LeRobot v2.1/v3.0, RoboTwin HDF5, written with the formats' own
/// tools) into `dir` by running `scripts/make_fixtures.py` with `python`; panics with the script's
/// error output when it fails.
pub fn make_fixtures(python: &Path, dir: &Path) {
    let script = repo_root().join("scripts/make_fixtures.py");
    let out = std::process::Command::new(python)
        .arg(&script)
        .arg(dir)
        .output()
        .unwrap_or_else(|e| panic!("starting {}: {e}", python.display()));
    assert!(out.status.success(), "make_fixtures.py failed:
{}", String::from_utf8_lossy(&out.stderr));
}

/// A fresh empty folder under [`root`], removed with its contents when dropped. Derefs to its
/// path.
pub struct TestDir(tempfile::TempDir);

impl TestDir {
    /// The folder's name starts with `name`.
    pub fn new(name: &str) -> TestDir {
        let dir = tempfile::Builder::new()
            .prefix(&format!("{name}-"))
            .tempdir_in(root())
            .unwrap_or_else(|e| panic!("creating a folder in {}: {e}", root().display()));
        TestDir(dir)
    }

    pub fn path(&self) -> &Path {
        self.0.path()
    }
}

impl Deref for TestDir {
    type Target = Path;

    fn deref(&self) -> &Path {
        self.0.path()
    }
}

impl AsRef<Path> for TestDir {
    fn as_ref(&self) -> &Path {
        self.0.path()
    }
}

impl AsRef<OsStr> for TestDir {
    fn as_ref(&self) -> &OsStr {
        self.0.path().as_os_str()
    }
}

impl std::fmt::Debug for TestDir {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.path().fmt(f)
    }
}
