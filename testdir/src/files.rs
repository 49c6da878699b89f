//! Where the tests find the reference's files: the golden cases of the parity tests and the
//! bundled episodes. Every test looks them up through [`reference_path`], so that one variable
//! swaps them all.
//!
//! Paths are named as in the layout of a reference folder: `golden/<file>` and
//! `data/bwm-demo/...`. They resolve to:
//! - `$BWM_SHARED/<rel>` when `BWM_SHARED` is set: a folder with `golden/` and `data/` that an
//!   outside check supplies (other golden cases, other data); CI sets it to `../shared` when that
//!   folder sits beside the clone;
//! - otherwise `golden/<file>` is the golden cache of the project's virtualenv,
//!   `<venv>/bwm-golden/<key>/<file>` ([`golden_dir`]), which `scripts/setup.sh --tests` fills by
//!   running `scripts/golden.py` (the reference implementation, DiffSynth-Studio 2.0.11 on the
//!   pinned torch) and `<key>` is the start of that script's SHA-256, so that a changed generator
//!   never meets the files of an older one;
//! - and any other path is the repository's own copy: `data/bwm-demo` is committed there.

use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

/// The repository's root (this crate sits one level below it).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("bwm-testdir sits inside the repository").to_path_buf()
}

/// `BWM_SHARED`, when set and not empty.
pub fn shared_override() -> Option<PathBuf> {
    std::env::var_os("BWM_SHARED").filter(|v| !v.is_empty()).map(PathBuf::from)
}

/// The generator of the golden files, `scripts/golden.py`.
pub fn golden_generator() -> PathBuf {
    repo_root().join("scripts/golden.py")
}

/// The cache key of the golden files: the first 16 hex digits of the SHA-256 of
/// `scripts/golden.py` (as `sha256sum scripts/golden.py | cut -c1-16` in scripts/setup.sh).
pub fn golden_key() -> String {
    let path = golden_generator();
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    let digest = Sha256::digest(&bytes);
    digest.iter().take(8).map(|b| format!("{b:02x}")).collect()
}

/// The project's virtualenv: `VIRTUAL_ENV`, else `BWM_VENV`, else the repository's `.venv` (as
/// [`crate::python`] finds its Python); the first that has `bin/python`, else `None`.
pub fn venv() -> Option<PathBuf> {
    let from_env = ["VIRTUAL_ENV", "BWM_VENV"].iter().filter_map(std::env::var_os).map(PathBuf::from);
    from_env.chain(std::iter::once(repo_root().join(".venv"))).find(|v| v.join("bin/python").is_file())
}

/// The folder of the golden files when no `BWM_SHARED` is set: `<venv>/bwm-golden/<key>`
/// ([`golden_key`]). `None` without a virtualenv.
pub fn golden_dir() -> Option<PathBuf> {
    Some(venv()?.join("bwm-golden").join(golden_key()))
}

/// The one lookup of the reference's files (module documentation): `rel` under `BWM_SHARED` when
/// set, else the golden cache for `golden/...`, else the repository's copy. Whether the path
/// exists is the caller's question ([`crate::reference`] asks it).
pub fn reference_path(rel: &str) -> PathBuf {
    if let Some(shared) = shared_override() {
        return shared.join(rel);
    }
    let rel_path = Path::new(rel);
    if let Ok(rest) = rel_path.strip_prefix("golden") {
        return match golden_dir() {
            Some(dir) => dir.join(rest),
            None => repo_root().join(".venv/bwm-golden").join(golden_key()).join(rest),
        };
    }
    repo_root().join(rel_path)
}

/// Why `path` (the answer of [`reference_path`] for `rel`) is missing, in words that say what
/// makes it.
pub fn missing_reason(rel: &str, path: &Path) -> String {
    if let Some(shared) = shared_override() {
        return format!("{} does not exist (BWM_SHARED={} names the folder of the golden files and data)", path.display(), shared.display());
    }
    if Path::new(rel).starts_with("golden") {
        return format!(
            "{} does not exist: the golden files are computed by `scripts/setup.sh --tests` (scripts/golden.py, with the \
             reference packages) into the virtualenv's bwm-golden/<key of the generator>; or set BWM_SHARED to a folder with golden/",
            path.display()
        );
    }
    format!("{} does not exist (committed in the repository; or set BWM_SHARED to a folder with {rel})", path.display())
}

/// The bundled episodes (`data/bwm-demo`, through [`reference_path`]).
pub fn demo_data() -> PathBuf {
    reference_path("data/bwm-demo")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_key_is_the_start_of_the_generators_sha256() {
        let key = golden_key();
        assert_eq!(key.len(), 16);
        assert!(key.bytes().all(|b| b.is_ascii_hexdigit()), "{key}");
        let out = std::process::Command::new("sha256sum").arg(golden_generator()).output();
        if let Ok(out) = out {
            if out.status.success() {
                assert_eq!(&String::from_utf8_lossy(&out.stdout)[..16], key, "the same key as scripts/setup.sh");
            }
        }
    }

    #[test]
    fn lookups_go_to_the_repository_or_the_golden_cache_unless_bwm_shared_is_set() {
        // Tests of this binary run in parallel: read the variable once, never set it here.
        match shared_override() {
            Some(s) => assert_eq!(reference_path("golden/x.json"), s.join("golden/x.json")),
            None => {
                assert_eq!(reference_path("data/bwm-demo"), repo_root().join("data/bwm-demo"));
                assert!(reference_path("data/bwm-demo").join("demo.jsonl").is_file());
                let g = reference_path("golden/dit_public.json");
                assert!(g.ends_with(format!("bwm-golden/{}/dit_public.json", golden_key())), "{}", g.display());
            }
        }
    }
}
