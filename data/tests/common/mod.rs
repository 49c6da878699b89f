//! Helpers shared by the integration tests: the bundled data, the project virtualenv's python,
//! and the fixture datasets `scripts/make_fixtures.py` writes.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use bwm_testdir::Dep;
use image::RgbImage;

pub fn demo_root() -> PathBuf {
    bwm_testdir::demo_data()
}

/// Runs a python snippet with `py` and arguments; returns its stdout, panics with its stderr on
/// failure.
pub fn run_python(py: &Path, script: &str, args: &[&str]) -> String {
    let out = Command::new(py).arg("-c").arg(script).args(args).output().expect("starting python");
    assert!(out.status.success(), "python failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).expect("python printed non-UTF-8")
}

/// The fixture datasets, written once per test binary into a folder that lasts until it exits.
/// They are written with the formats' own tools (the virtualenv's pyarrow, h5py, OpenCV and the
/// ffmpeg CLI); without those: `None`, after the test failed where BWM_REQUIRE names the missing
/// one (CI) or was logged as skipped elsewhere (`bwm_testdir::need`).
pub fn fixtures() -> Option<&'static Path> {
    let py = bwm_testdir::python_with(Dep::Python, &["cv2", "h5py", "numpy", "pyarrow"])?;
    let ffmpeg = Command::new("ffmpeg").arg("-version").output();
    let missing = match ffmpeg {
        Ok(out) if out.status.success() => None,
        Ok(out) => Some(format!("`ffmpeg -version` failed: {}", String::from_utf8_lossy(&out.stderr).trim())),
        Err(e) => Some(format!("no ffmpeg command ({e}); scripts/setup.sh --tests installs it")),
    };
    if !bwm_testdir::need(Dep::Ffmpeg, missing) {
        return None;
    }
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    Some(DIR.get_or_init(|| {
        let dir = bwm_testdir::shared_dir("data-fixtures");
        bwm_testdir::make_fixtures(&py, &dir);
        dir
    }))
}

#[allow(unused_imports)]
pub use bwm_testdir::tmp_dir;

/// Mean colour of a small square around (x, y).
pub fn mean_rgb(img: &RgbImage, x: u32, y: u32) -> [f64; 3] {
    let mut sum = [0.0; 3];
    let mut n = 0.0;
    for yy in y.saturating_sub(2)..(y + 3).min(img.height()) {
        for xx in x.saturating_sub(2)..(x + 3).min(img.width()) {
            let p = img.get_pixel(xx, yy);
            for c in 0..3 {
                sum[c] += p[c] as f64;
            }
            n += 1.0;
        }
    }
    sum.map(|s| s / n)
}

/// Panics unless the colour at (x, y) is within `tol` of `want` in every channel.
pub fn assert_color(img: &RgbImage, x: u32, y: u32, want: [u8; 3], tol: f64, what: &str) {
    let got = mean_rgb(img, x, y);
    assert!(
        got.iter().zip(want).all(|(g, w)| (g - w as f64).abs() <= tol),
        "{what}: pixel ({x}, {y}) is {got:?}, expected {want:?} (within {tol})"
    );
}
