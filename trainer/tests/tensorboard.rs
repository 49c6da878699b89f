//! Event files written by `bwm_trainer::tensorboard::EventWriter`, read back by TensorBoard's own
//! `EventAccumulator` (the project virtualenv's `tensorboard` package, driven by Python below).

use std::path::{Path, PathBuf};
use std::process::Command;

use bwm_trainer::tensorboard::EventWriter;
use serde_json::Value;

/// The project virtualenv's Python with TensorBoard (`bwm_testdir::python_with`: without it the
/// test fails where BWM_REQUIRE names python, and is logged as skipped elsewhere).
fn python() -> Option<PathBuf> {
    bwm_testdir::python_with(bwm_testdir::Dep::Python, &["tensorboard"])
}

/// Loads `log_dir` with TensorBoard's EventAccumulator and also re-checks every record's
/// TFRecord framing and masked CRC-32C with TensorBoard's pure-Python implementation.
const READER: &str = r#"
import glob, json, os, struct, sys
from tensorboard.backend.event_processing import event_accumulator as ea
from tensorboard.compat.tensorflow_stub.pywrap_tensorflow import masked_crc32c

log_dir = sys.argv[1]
files = sorted(glob.glob(os.path.join(log_dir, "events.out.tfevents.*")))
records = 0
for path in files:
    data = open(path, "rb").read()
    off = 0
    while off < len(data):
        header = data[off:off + 8]
        (n,) = struct.unpack("<Q", header)
        (hcrc,) = struct.unpack("<I", data[off + 8:off + 12])
        assert hcrc == masked_crc32c(header), "header crc"
        body = data[off + 12:off + 12 + n]
        (bcrc,) = struct.unpack("<I", data[off + 12 + n:off + 16 + n])
        assert bcrc == masked_crc32c(body), "data crc"
        off += 16 + n
        records += 1
    assert off == len(data), "trailing bytes"

guidance = {k: 0 for k in (ea.SCALARS, ea.IMAGES, ea.TENSORS, ea.HISTOGRAMS, ea.COMPRESSED_HISTOGRAMS, ea.AUDIO)}
acc = ea.EventAccumulator(log_dir, size_guidance=guidance)
acc.Reload()
tags = acc.Tags()
print(json.dumps({
    "files": [os.path.basename(f) for f in files],
    "records": records,
    "file_version": acc.file_version,
    "scalars": {t: [[e.step, e.value] for e in acc.Scalars(t)] for t in tags["scalars"]},
    "images": {t: [[e.step, e.width, e.height, e.encoded_image_string.hex()] for e in acc.Images(t)]
               for t in tags["images"]},
}))
"#;

fn read_back(py: &Path, log_dir: &Path) -> Value {
    let out = Command::new(py).arg("-c").arg(READER).arg(log_dir).output().unwrap();
    assert!(out.status.success(), "python reader failed:\n{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

fn tmp_dir(tag: &str) -> bwm_testdir::TestDir {
    bwm_testdir::TestDir::new(&format!("tb-{tag}"))
}

fn loss(step: u64) -> f64 {
    1.0 / (step as f64 + 0.3)
}

fn lr(step: u64) -> f64 {
    1e-4 * step as f64 + 1e-7
}

fn test_image() -> image::RgbImage {
    image::RgbImage::from_fn(7, 5, |x, y| image::Rgb([(x * 30) as u8, (y * 50) as u8, ((x + y) * 9) as u8]))
}

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap()).collect()
}

fn assert_scalars(got: &Value, tag: &str, f: fn(u64) -> f64) {
    let points = got["scalars"][tag].as_array().unwrap_or_else(|| panic!("no scalar tag {tag}: {got}"));
    let steps: Vec<u64> = points.iter().map(|p| p[0].as_u64().unwrap()).collect();
    assert_eq!(steps, [1, 2, 3, 4, 5], "{tag}");
    for p in points {
        let (step, value) = (p[0].as_u64().unwrap(), p[1].as_f64().unwrap());
        let want = f(step);
        assert!(((value - want) / want).abs() < 1e-6, "{tag} step {step}: {value} vs {want}");
    }
}

#[test]
fn tensorboard_reads_scalars_and_images() {
    let Some(py) = python() else { return };
    let dir = tmp_dir("rw");
    let log_dir = dir.join("runs/a"); // created by `create`
    let img = test_image();
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png).unwrap();

    let mut w = EventWriter::create(&log_dir).unwrap();
    let name = w.path().file_name().unwrap().to_str().unwrap().to_string();
    assert!(name.starts_with("events.out.tfevents."), "{name}");
    assert!(name.contains(&format!(".{}.", std::process::id())), "{name}");
    for step in 1..=5 {
        w.scalar("train/loss", loss(step), step).unwrap();
        w.scalar("train/lr", lr(step), step).unwrap();
    }
    w.image_rgb("samples/frame0", &img, 5).unwrap();
    w.image_png("samples/png", &png, 7, 5, 3).unwrap();
    assert!(w.image_png("samples/bad", &png, 5, 7, 3).is_err(), "size mismatch must be refused");
    assert!(w.image_png("samples/bad", b"not a png", 7, 5, 3).is_err(), "non-PNG must be refused");
    w.flush().unwrap();

    // Read while the writer is still open: flush() must have made everything visible.
    let got = read_back(&py, &log_dir);
    assert_eq!(got["files"].as_array().unwrap().len(), 1, "{got}");
    assert_eq!(got["records"].as_u64(), Some(1 + 10 + 2), "{got}");
    assert_eq!(got["file_version"].as_f64(), Some(2.0), "{got}");
    assert_eq!(got["scalars"].as_object().unwrap().len(), 2, "{got}");
    assert_scalars(&got, "train/loss", loss);
    assert_scalars(&got, "train/lr", lr);

    let images = got["images"].as_object().unwrap();
    assert_eq!(images.len(), 2, "{got}");
    for (tag, step) in [("samples/frame0", 5), ("samples/png", 3)] {
        let events = images[tag].as_array().unwrap();
        assert_eq!(events.len(), 1, "{tag}");
        let e = &events[0];
        assert_eq!(e[0].as_u64(), Some(step), "{tag}");
        assert_eq!((e[1].as_u64(), e[2].as_u64()), (Some(7), Some(5)), "{tag} width, height");
        let decoded = image::load_from_memory_with_format(&unhex(e[3].as_str().unwrap()), image::ImageFormat::Png)
            .unwrap()
            .to_rgb8();
        assert_eq!(decoded, img, "{tag} pixels");
    }
    drop(w);
}

#[test]
fn drop_flushes_and_writers_get_distinct_files() {
    let Some(py) = python() else { return };
    let dir = tmp_dir("drop");
    let mut a = EventWriter::create(&dir).unwrap();
    let mut b = EventWriter::create(&dir).unwrap();
    assert_ne!(a.path(), b.path());
    for step in 1..=5 {
        a.scalar("train/loss", loss(step), step).unwrap();
    }
    for step in 1..=5 {
        b.scalar("train/lr", lr(step), step).unwrap();
    }
    b.sync().unwrap();
    drop(a);
    drop(b);
    let got = read_back(&py, &dir);
    assert_eq!(got["files"].as_array().unwrap().len(), 2, "{got}");
    assert_scalars(&got, "train/loss", loss);
    assert_scalars(&got, "train/lr", lr);
}

#[test]
fn log_dir_that_is_a_file_is_an_error() {
    let dir = tmp_dir("file");
    let file = dir.join("not_a_dir");
    std::fs::write(&file, b"x").unwrap();
    let err = EventWriter::create(&file).err().expect("a regular file as log dir must fail");
    assert!(format!("{err:#}").contains("not_a_dir"), "{err:#}");
    assert!(EventWriter::create(&file.join("sub")).is_err());
}
