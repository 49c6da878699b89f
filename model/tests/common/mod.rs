//! Helpers shared by the model's integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

use tch::{Kind, Tensor};

/// The golden files the reference computed (`scripts/golden.py`, run by `scripts/setup.sh --tests`
/// into the virtualenv's cache), or `$BWM_SHARED/golden` when BWM_SHARED is set
/// (`bwm_testdir::reference_path`). Without them: `None`, after the test failed where
/// BWM_REQUIRE names reference (CI) or was logged as skipped elsewhere (`bwm_testdir::need`).
pub fn golden_dir() -> Option<PathBuf> {
    bwm_testdir::reference("golden")
}

/// ||a - b|| / ||b||
pub fn rel_err(a: &Tensor, b: &Tensor) -> f64 {
    let a = a.to_kind(Kind::Double);
    let b = b.to_kind(Kind::Double);
    assert_eq!(a.size(), b.size(), "shape mismatch");
    let num = (&a - &b).norm().double_value(&[]);
    let den = b.norm().double_value(&[]);
    num / den.max(1e-30)
}

#[allow(unused_imports)]
pub use bwm_testdir::tmp_dir;

/// tch draws random numbers from one global generator and the tests of a binary run on parallel
/// threads: a test that seeds the generator and relies on what it draws holds this lock.
pub fn torch_rng() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}
