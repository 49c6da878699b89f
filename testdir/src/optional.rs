//! Optional dependencies of the tests, decided in one place.
//!
//! Some tests need what a plain `cargo test` may not have: the project's Python with the reference
//! packages, Slurm, FFmpeg, the pinned reference implementation, CUDA, NCCL. Such a test asks
//! [`need`] (or [`python_with`]) before it starts. When the dependency is there, the test runs.
//! When it is missing:
//! - if `BWM_REQUIRE` names it (a comma-separated list of [`Dep`] names, or `all`), the test fails
//!   with the reason: CI sets `BWM_REQUIRE=all` once, so nothing is skipped there;
//! - otherwise the test prints one line starting with [`SKIP_MARK`] on stderr and returns early.
//!   The harness captures a passing test's output, so the line also goes to the file
//!   `BWM_SKIP_LOG` names, where `scripts/test.sh` counts it as skipped, never as passed.

use std::fmt;
use std::path::{Path, PathBuf};
use std::process::Command;

/// What a skipped test's line starts with (on stderr and in `BWM_SKIP_LOG`).
pub const SKIP_MARK: &str = "bwm-test: SKIPPED";

/// An optional dependency of a test.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dep {
    /// The project's virtualenv Python with the packages a test imports.
    Python,
    /// Slurm's daemons and client commands (the test cluster of `tests/slurm.rs`).
    Slurm,
    /// The ffmpeg command line and FFmpeg's libraries.
    Ffmpeg,
    /// The pinned reference implementation (DiffSynth, diffusers) and its files.
    Reference,
    /// A CUDA device visible to libtorch.
    Cuda,
    /// NCCL over at least two CUDA devices.
    Nccl,
}

impl Dep {
    /// Every dependency, in the order of their names.
    pub const ALL: [Dep; 6] = [Dep::Python, Dep::Slurm, Dep::Ffmpeg, Dep::Reference, Dep::Cuda, Dep::Nccl];

    /// The name `BWM_REQUIRE` uses.
    pub fn name(self) -> &'static str {
        match self {
            Dep::Python => "python",
            Dep::Slurm => "slurm",
            Dep::Ffmpeg => "ffmpeg",
            Dep::Reference => "reference",
            Dep::Cuda => "cuda",
            Dep::Nccl => "nccl",
        }
    }
}

impl fmt::Display for Dep {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Whether `BWM_REQUIRE` (a value as the environment would hold it) requires `dep`. An unknown
/// name is an error, so that a typo cannot turn a requirement into a skip.
pub fn required_by(value: Option<&str>, dep: Dep) -> Result<bool, String> {
    let Some(value) = value else { return Ok(false) };
    let mut hit = false;
    for name in value.split(',').map(str::trim).filter(|n| !n.is_empty()) {
        if name == "all" {
            hit = true;
            continue;
        }
        let known = Dep::ALL.iter().find(|d| d.name() == name);
        let known = known.ok_or_else(|| {
            let names: Vec<&str> = Dep::ALL.iter().map(|d| d.name()).collect();
            format!("BWM_REQUIRE names {name:?}, which is none of all, {}", names.join(", "))
        })?;
        hit |= *known == dep;
    }
    Ok(hit)
}

/// Whether this process's `BWM_REQUIRE` requires `dep` (panics on an unknown name).
pub fn required(dep: Dep) -> bool {
    let value = std::env::var("BWM_REQUIRE").ok();
    required_by(value.as_deref(), dep).unwrap_or_else(|e| panic!("{e}"))
}

/// `true` when the test can go on: `missing` is `None`. Otherwise (the reason `dep` is missing)
/// the test fails if `dep` is required, else a skip line is printed and `false` returned.
pub fn need(dep: Dep, missing: Option<String>) -> bool {
    let Some(why) = missing else { return true };
    let log = std::env::var_os("BWM_SKIP_LOG").map(PathBuf::from);
    let test = std::thread::current().name().unwrap_or("?").to_string();
    if let Err(e) = skip(dep, &test, &why, required(dep), log.as_deref()) {
        panic!("{e}");
    }
    false
}

/// The skip of `test` for want of `dep`: an error when `required`, else its line on stderr and
/// appended to `log`.
fn skip(dep: Dep, test: &str, why: &str, required: bool, log: Option<&Path>) -> Result<(), String> {
    if required {
        return Err(format!("{dep} is required (BWM_REQUIRE) but missing: {why}"));
    }
    let line = format!("{SKIP_MARK} {test}: {dep} missing: {why} (BWM_REQUIRE={dep} makes this a failure)");
    eprintln!("{line}");
    if let Some(log) = log {
        use std::io::Write;
        // One write of the whole line, in append mode: lines of parallel tests do not interleave.
        let mut f = std::fs::OpenOptions::new().create(true).append(true).open(log).map_err(|e| format!("opening {}: {e}", log.display()))?;
        f.write_all(format!("{line}\n").as_bytes()).map_err(|e| format!("recording the skip in {}: {e}", log.display()))?;
    }
    Ok(())
}

/// The project's virtualenv Python: `VIRTUAL_ENV`, else `BWM_VENV` (both set by
/// `scripts/env.sh`), else the repository's `.venv`. `None` when none of them has `bin/python`.
pub fn python() -> Option<PathBuf> {
    crate::files::venv().map(|v| v.join("bin/python"))
}

/// Why the virtualenv's Python cannot import `modules`, or its path when it can. The answer is
/// kept for the rest of the process (importing torch takes seconds; a test binary asks often).
pub fn find_python_with(modules: &[&str]) -> Result<PathBuf, String> {
    use std::collections::HashMap;
    use std::sync::Mutex;
    static ANSWERS: Mutex<Option<HashMap<Vec<String>, Result<PathBuf, String>>>> = Mutex::new(None);
    let key: Vec<String> = modules.iter().map(|m| m.to_string()).collect();
    if let Some(known) = ANSWERS.lock().unwrap_or_else(|e| e.into_inner()).get_or_insert_with(HashMap::new).get(&key) {
        return known.clone();
    }
    let answer = try_import(modules);
    ANSWERS.lock().unwrap_or_else(|e| e.into_inner()).get_or_insert_with(HashMap::new).insert(key, answer.clone());
    answer
}

fn try_import(modules: &[&str]) -> Result<PathBuf, String> {
    let py = python().ok_or_else(|| "no virtualenv python (VIRTUAL_ENV, BWM_VENV or .venv; source scripts/env.sh)".to_string())?;
    let import = format!("import {}", modules.join(", "));
    let out = Command::new(&py).args(["-c", &import]).output().map_err(|e| format!("running {}: {e}", py.display()))?;
    if out.status.success() {
        return Ok(py);
    }
    let err = String::from_utf8_lossy(&out.stderr);
    let last = err.lines().last().unwrap_or("").to_string();
    Err(format!("`{import}` fails in {}: {last} (scripts/setup.sh --tests installs the packages)", py.display()))
}

/// The virtualenv's Python when it imports `modules`; else as [`need`] with `dep`: a failure when
/// required, a skip line and `None` when not.
pub fn python_with(dep: Dep, modules: &[&str]) -> Option<PathBuf> {
    match find_python_with(modules) {
        Ok(py) => Some(py),
        Err(why) => {
            need(dep, Some(why));
            None
        }
    }
}

/// The reference's file `rel` (`golden/<file>`, `data/bwm-demo/...`) where
/// [`crate::files::reference_path`] finds it (`BWM_SHARED`, the golden cache or the repository),
/// when it exists; else as [`need`] with [`Dep::Reference`]: a failure when required, a skip line
/// and `None` when not.
pub fn reference(rel: &str) -> Option<PathBuf> {
    let path = crate::files::reference_path(rel);
    let missing = (!path.exists()).then(|| crate::files::missing_reason(rel, &path));
    need(Dep::Reference, missing).then_some(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requirement_lists_name_dependencies_or_all() {
        assert_eq!(required_by(None, Dep::Slurm), Ok(false));
        assert_eq!(required_by(Some(""), Dep::Slurm), Ok(false));
        assert_eq!(required_by(Some("all"), Dep::Cuda), Ok(true));
        assert_eq!(required_by(Some("python, slurm"), Dep::Slurm), Ok(true));
        assert_eq!(required_by(Some("python,slurm"), Dep::Cuda), Ok(false));
        let e = required_by(Some("pyhton"), Dep::Python).unwrap_err();
        assert!(e.contains("\"pyhton\"") && e.contains("python"), "{e}");
    }

    #[test]
    fn a_missing_dependency_fails_when_required_and_is_logged_as_skipped_when_not() {
        assert!(need(Dep::Reference, None));
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("skipped.log");
        let e = skip(Dep::Slurm, "t1", "no sbatch", true, Some(&log)).unwrap_err();
        assert!(e.contains("slurm is required") && e.contains("no sbatch"), "{e}");
        assert!(!log.exists(), "a required dependency is not logged as skipped");
        skip(Dep::Slurm, "t1", "no sbatch", false, Some(&log)).unwrap();
        skip(Dep::Cuda, "t2", "no device", false, Some(&log)).unwrap();
        let text = std::fs::read_to_string(&log).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 2, "{text}");
        assert!(lines[0].starts_with(SKIP_MARK) && lines[0].contains("t1: slurm missing: no sbatch"), "{text}");
        assert!(lines[1].contains("t2: cuda missing"), "{text}");
    }
}
