//! `bwm prepare` end to end on CPU with a small random VAE: the bundled dataset's cache
//! round-trips (cached latents decode like the VAE's own encode of the dataset's frames, cached
//! actions are the normalized rows of exactly those frames), an interrupted run leaves only
//! complete shards and its rerun gives the uninterrupted result, two ranks give the one-process
//! result, another plan is refused without --overwrite; LeRobot and RoboTwin fixtures (written by
//! scripts/make_fixtures.py) prepare, with defects skipped and counted, upscaling refused unless
//! allowed, and an x0 enhancement command applied; raw clips (`--raw`) train like their encoded
//! cache, the trainer encoding them with `data.vae`.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use bwm_data::frames::{fit, frames_to_tensor};
use bwm_data::latent_cache::LatentCache;
use bwm_data::{open_dataset, CameraSelection};
use bwm_data::{ActionSpec, ActionStats, ResizeMode};
use bwm_model::vae::WanVae;
use common::{assert_close, bwm, demo_data, final_weights, python, shared_dir, temp_dir, write_random_vae};
use tch::{Device, Kind, Tensor};




/// A small random VAE, written once per test binary.
fn vae_file() -> &'static Path {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        let path = shared_dir("vae").join("vae.safetensors");
        write_random_vae(&path, 5);
        path
    })
}

/// The fixture datasets of scripts/make_fixtures.py, written once per test binary.
fn fixtures() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = shared_dir("fixtures");
        bwm_testdir::make_fixtures(Path::new(&python()), &dir);
        dir
    })
}

fn prepare_cmd(args: &[&str]) -> Command {
    let mut c = Command::new(bwm());
    c.arg("prepare").args(["--vae", vae_file().to_str().unwrap(), "--device", "cpu"]).args(args).env_remove("RANK").env_remove("WORLD_SIZE");
    c
}

fn show(out: &Output) -> (String, String) {
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned());
    println!("{stdout}{stderr}");
    (stdout, stderr)
}

fn prepare(args: &[&str]) -> String {
    let out = prepare_cmd(args).output().unwrap();
    let (stdout, stderr) = show(&out);
    assert!(out.status.success(), "bwm prepare {args:?} failed: {stderr}");
    stdout
}

fn prepare_err(args: &[&str]) -> String {
    let out = prepare_cmd(args).output().unwrap();
    let (_, stderr) = show(&out);
    assert!(!out.status.success(), "bwm prepare {args:?} should have failed");
    stderr
}

/// The folder's files, without the ranks' lock files (`.lock.rank-R-of-W`, kept between runs).
fn names(dir: &Path) -> Vec<String> {
    let mut n: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !n.starts_with(".lock.rank-"))
        .collect();
    n.sort();
    n
}

/// Same clips (episode, frames, shard) and bit-identical cached tensors.
fn assert_same_cache(a: &Path, b: &Path) {
    let (ca, cb) = (LatentCache::open(a).unwrap(), LatentCache::open(b).unwrap());
    assert_eq!(ca.index, cb.index, "{} vs {}", a.display(), b.display());
    assert_eq!(ca.extras.plan_hash, cb.extras.plan_hash);
    for i in 0..ca.len() {
        let (x, y) = (ca.load(i, Device::Cpu).unwrap(), cb.load(i, Device::Cpu).unwrap());
        assert!(x.latents.equal(&y.latents), "clip {i}: latents differ between {} and {}", a.display(), b.display());
        assert!(x.actions.equal(&y.actions), "clip {i}: actions differ");
        assert_eq!(x.frames.is_some(), y.frames.is_some());
        if let (Some(f), Some(g)) = (&x.frames, &y.frames) {
            assert!(f.equal(g), "clip {i}: frames differ");
        }
    }
}

fn max_abs(t: &Tensor) -> f64 {
    t.abs().max().double_value(&[])
}

#[test]
fn demo_cache_round_trips_resumes_after_interruption_and_splits_across_ranks() {
    let dir = temp_dir("prepare-demo");
    let data = demo_data();
    let common = [
        "--data", data.to_str().unwrap(), "--resolution", "64x32", "--history", "4", "--future", "4", "--clips-per-shard", "4", "--keep-frames",
    ];
    let stride = |s: &'static str| -> [&'static str; 2] { ["--stride", s] };
    let run = |out: &Path, extra: &[&str]| prepare(&[&common[..], &["--out", out.to_str().unwrap()], &stride("32"), extra].concat());

    // Uninterrupted: 143, 150 and 143 frames give 5 windows each (future starts 1, 33, ..., 129).
    let full = dir.join("full");
    let stdout = run(&full, &[]);
    assert!(stdout.contains("clips/s"), "{stdout}");
    assert!(stdout.contains("3 episodes: 3 used (15 clips), 0 skipped"), "{stdout}");
    assert!(stdout.contains("warning: this VAE was trained on 5-frame clips and these clips have 9 frames"), "{stdout}");
    let cache = LatentCache::open(&full).unwrap();
    assert_eq!(cache.len(), 15);
    assert_eq!(cache.index.latent_shape, [48, 3, 2, 4]);
    assert_eq!(cache.extras.source_resolution, [[640, 480]]);
    assert_eq!(cache.extras.clips_per_shard, Some(4));
    assert_eq!(names(&full).iter().filter(|n| n.starts_with("shard-")).count(), 4);

    // Round trip of one clip against the dataset, read independently of `bwm prepare`.
    let i = 6;
    let entry = cache.index.clips[i].clone();
    let clip = cache.load(i, Device::Cpu).unwrap();
    let source = open_dataset(&data).unwrap();
    let e = source.episodes().iter().position(|info| info.index == entry.episode).unwrap();
    let last = *entry.frames.iter().max().unwrap();
    let episode_frames = source.frames(e, 0..last + 1, &CameraSelection::default()).unwrap();
    let picked: Vec<_> = entry.frames.iter().map(|&f| fit(&episode_frames[f], 64, 32, ResizeMode::Crop)).collect();
    let video = frames_to_tensor(&picked).unwrap();
    let pixels = ((&video + 1.0) * 127.5).round().to_kind(Kind::Uint8);
    assert!(clip.frames.as_ref().unwrap().equal(&pixels), "cached pixel frames are the dataset's frames, resized");
    let vae = WanVae::load_any(vae_file(), Kind::Float, Device::Cpu).unwrap();
    let (reference, cached_decoded, reference_decoded) = tch::no_grad(|| {
        let z = vae.encode(&video.unsqueeze(0)).unwrap().squeeze_dim(0);
        let a = vae.decode(&clip.latents.unsqueeze(0)).unwrap();
        let b = vae.decode(&z.unsqueeze(0)).unwrap();
        (z, a, b)
    });
    // bf16 keeps 8 significant bits: rounding an f32 to it moves it by at most 2^-9 of its
    // magnitude. The cache is the bf16 rounding of this encode (2^-8 leaves room for the f32
    // encode differing in its last bits between processes).
    let latent_err = (&clip.latents - &reference).abs() - reference.abs() * (1.0 / 256.0);
    assert!(max_abs(&latent_err.clamp_min(0.0)) <= 1e-6, "cached latents are not the bf16 rounding of the encode");
    assert!(max_abs(&(&clip.latents - &reference)) > 0.0, "latents are expected to be stored in bf16");
    // The decode of latents off by bf16 rounding: the decoder, a composition of convolutions
    // and normalizations, changes its output by about as much relative to its range; 2^-7 of
    // the decoded range allows a gain of 2 over the latents' relative error.
    let range = max_abs(&reference_decoded);
    let decode_err = max_abs(&(&cached_decoded - &reference_decoded));
    println!("round trip: latents max |cached - encode| {:.3e} (max |encode| {:.3}); decoded max diff {decode_err:.3e} of range {range:.3}", max_abs(&(&clip.latents - &reference)), max_abs(&reference));
    assert!(decode_err <= range / 128.0, "decoded cached latents differ by {decode_err} (range {range})");
    // The actions: the normalized rows of exactly the clip's frames.
    let stats = ActionStats::read(&data.join("stat.json"), "state_pose").unwrap();
    let rows = source.vectors(e, &ActionSpec::eef_abs()).unwrap();
    let expected: Vec<f32> = entry.frames.iter().flat_map(|&f| stats.normalize(&rows[f])).collect();
    assert_eq!(Vec::<f32>::try_from(clip.actions.view([-1])).unwrap(), expected);

    // Interrupted after its first shard: only that complete shard, no index, no temporary file;
    // the rerun finishes with the uninterrupted result.
    let resumed = dir.join("resumed");
    let out = prepare_cmd(&[&common[..], &["--out", resumed.to_str().unwrap()], &stride("32")].concat()).env("BWM_FAULT_EXIT_AFTER_SHARDS", "1").output().unwrap();
    show(&out);
    assert_eq!(out.status.code(), Some(3));
    assert_eq!(names(&resumed), ["progress.rank-0-of-1.json", "shard-00000.safetensors"]);
    let merge = |out: &Path| Command::new(bwm()).args(["prepare", "--merge", "--out", out.to_str().unwrap()]).output().unwrap();
    let out = merge(&resumed);
    let (_, stderr) = show(&out);
    assert!(!out.status.success() && stderr.contains("3 shards are not finished yet"), "{stderr}");
    let stdout = run(&resumed, &[]);
    assert!(stdout.contains("4 of the 4 shards are this rank's, 1 already done"), "{stdout}");
    assert_same_cache(&full, &resumed);

    // Two ranks at once in one folder: the same cache as one process.
    let ranks = dir.join("ranks");
    let children: Vec<_> = (0..2)
        .map(|r| {
            prepare_cmd(&[&common[..], &["--out", ranks.to_str().unwrap(), "--rank", &r.to_string(), "--world", "2"], &stride("32")].concat())
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for c in children {
        let out = c.wait_with_output().unwrap();
        show(&out);
        assert!(out.status.success());
    }
    assert_same_cache(&full, &ranks);
    assert!(names(&ranks).contains(&"progress.rank-1-of-2.json".to_string()));
    // --merge writes the same index from the ranks' progress files.
    std::fs::remove_file(ranks.join("index.json")).unwrap();
    let out = merge(&ranks);
    show(&out);
    assert!(out.status.success());
    assert_same_cache(&full, &ranks);

    // Rerunning a complete cache does nothing; another plan is refused unless --overwrite.
    assert!(run(&full, &[]).contains("nothing to do"));
    let err = prepare_err(&[&common[..], &["--out", full.to_str().unwrap()], &stride("48")].concat());
    assert!(err.contains("other arguments") && err.contains("clip") && err.contains("--overwrite"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    prepare(&[&common[..], &["--out", full.to_str().unwrap(), "--overwrite"], &stride("48")].concat());
    let replaced = LatentCache::open(&full).unwrap();
    assert_eq!(replaced.len(), 10, "143, 150, 143 frames: future starts 1, 49, 97 (, 145)");
    assert_eq!(names(&full).iter().filter(|n| n.starts_with("shard-")).count(), 3, "shards of the old plan are removed");
}

#[test]
fn lerobot_and_robotwin_fixtures_prepare_with_defects_upscaling_and_enhancement() {
    let dir = temp_dir("prepare-fixtures");
    let fx = fixtures();
    let clip = ["--history", "4", "--future", "4", "--stride", "4", "--clips-per-shard", "2"];
    let small = [&clip[..], &["--resolution", "64x32"]].concat();

    // LeRobot v2.1, two cameras stacked (64x48 over 64x32), a column:indices action vector;
    // no stat.json in the dataset, so statistics are computed and written into the cache.
    let lerobot = dir.join("lerobot");
    let stdout = prepare(
        &[
            &small[..],
            &["--data", fx.join("lerobot_v21").to_str().unwrap(), "--out", lerobot.to_str().unwrap()],
            &["--actions", "observation.state:0-5", "--camera", "observation.images.top,observation.images.wrist"],
        ]
        .concat(),
    );
    assert!(stdout.contains("computed over 3 training episodes"), "{stdout}");
    let cache = LatentCache::open(&lerobot).unwrap();
    // 10, 12 and 9 frames: future starts 1 and 5 in each.
    assert_eq!(cache.len(), 6);
    assert_eq!(cache.index.action_dim, 6);
    assert_eq!(cache.extras.source_resolution, [[64, 80]]);
    let stats = ActionStats::read(&lerobot.join("stat.json"), "observation.state").unwrap();
    let entry = &cache.index.clips[3];
    assert_eq!(entry.episode, 1);
    assert_eq!(entry.frames, [0, 1, 2, 3, 4, 5, 6, 7, 8]);
    let expected: Vec<f32> =
        entry.frames.iter().flat_map(|&t| stats.normalize(&(0..6).map(|j| ((100 + t) as f64 + 0.1 * j as f64) as f32).collect::<Vec<_>>())).collect();
    let got = Vec::<f32>::try_from(cache.load(3, Device::Cpu).unwrap().actions.view([-1])).unwrap();
    assert!(got.iter().zip(&expected).all(|(a, b)| (a - b).abs() < 1e-6), "{got:?} vs {expected:?}");

    // A LeRobot dataset with one usable episode and one of each defect: skipped and counted.
    let bad = dir.join("bad");
    let stdout = prepare(&[&small[..], &["--data", fx.join("lerobot_v21_bad").to_str().unwrap(), "--out", bad.to_str().unwrap(), "--actions", "observation.state:0-5"]].concat());
    assert!(stdout.contains("8 episodes: 1 used (2 clips), 7 skipped"), "{stdout}");
    for reason in ["too short", "non-finite action", "missing video", "frame/row count mismatch", "unreadable video", "unreadable data"] {
        assert!(stdout.contains(reason), "{reason}: {stdout}");
    }
    assert_eq!(LatentCache::open(&bad).unwrap().len(), 2);
    // Statistics read the action data only: the NaN row and the corrupted parquet are skipped.
    let stat = dir.join("bad-stat.json");
    let out = Command::new(bwm())
        .args(["stats", "--data", fx.join("lerobot_v21_bad").to_str().unwrap(), "--actions", "observation.state:0-5", "--out", stat.to_str().unwrap()])
        .output()
        .unwrap();
    let (stdout, stderr) = show(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(stdout.contains("8 episodes: 6 used") && stdout.contains("non-finite action") && stdout.contains("unreadable data"), "{stdout}");
    assert!(ActionStats::read(&stat, "observation.state").unwrap().p01.iter().all(|v| v.is_finite()));

    // RoboTwin (original layout), the action preset picked from the format.
    let robotwin = fx.join("robotwin/original");
    let rt = dir.join("robotwin");
    prepare(&[&small[..], &["--data", robotwin.to_str().unwrap(), "--out", rt.to_str().unwrap()]].concat());
    let cache = LatentCache::open(&rt).unwrap();
    assert_eq!(cache.len(), 3, "8 and 10 frames: future starts 1 / 1, 5");
    assert_eq!(cache.index.action_dim, 14);
    assert_eq!(cache.extras.plan.as_ref().unwrap()["actions"]["column"], "endpose");

    // Upscaling 64x48 frames to 96x64 is refused, and done when allowed.
    let up = dir.join("up");
    let up_args = [&clip[..], &["--data", robotwin.to_str().unwrap(), "--out", up.to_str().unwrap(), "--resolution", "96x64"]].concat();
    let err = prepare_err(&up_args);
    assert!(err.contains("64x48") && err.contains("--allow-upscale"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    prepare(&[&up_args[..], &["--allow-upscale"]].concat());
    assert_eq!(LatentCache::open(&up).unwrap().index.resolution, [96, 64]);

    // An enhancement command that returns x0 unchanged gives the same latents; one that fails
    // skips the episodes with its reason, here all of them: a one-line error.
    let same = dir.join("enhanced");
    prepare(&[&small[..], &["--data", robotwin.to_str().unwrap(), "--out", same.to_str().unwrap(), "--enhance-x0", "cp {in} {out}"]].concat());
    let (a, b) = (LatentCache::open(&rt).unwrap(), LatentCache::open(&same).unwrap());
    assert_eq!(a.index.clips, b.index.clips);
    for i in 0..a.len() {
        assert!(a.load(i, Device::Cpu).unwrap().latents.equal(&b.load(i, Device::Cpu).unwrap().latents), "clip {i}");
    }
    let failing = dir.join("failing");
    let out = prepare_cmd(&[&small[..], &["--data", robotwin.to_str().unwrap(), "--out", failing.to_str().unwrap(), "--enhance-x0", "echo no model >&2; exit 2 # {in} {out}"]].concat())
        .output()
        .unwrap();
    let (stdout, stderr) = show(&out);
    assert!(!out.status.success());
    assert!(stdout.contains("skipped 1 clip of episode 0") && stdout.contains("skipped 2 clips of episode 1"), "{stdout}");
    assert!(stdout.contains("exit status: 2") && stdout.contains("no model"), "{stdout}");
    assert!(stderr.contains("every planned clip was skipped"), "{stderr}");

    // No episode long enough for one clip: a one-line error naming the reason.
    let err = prepare_err(&["--data", robotwin.to_str().unwrap(), "--out", dir.join("none").to_str().unwrap(), "--resolution", "64x32", "--future", "40"]);
    assert!(err.contains("no usable episode") && err.contains("too short"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
}

/// A tiny-model training run of 2 steps on `cache` (clips of 1 + 4 + 4 frames at 64x32).
fn train_tiny(dir: &Path, name: &str, cache: &Path, vae: Option<&Path>) -> Output {
    let vae = vae.map(|v| format!("vae = \"{}\"\n", v.display())).unwrap_or_default();
    let config = dir.join(format!("{name}.toml"));
    let text = format!(
        "[run]\nname = \"{name}\"\nout_dir = \"{out}\"\ndevice = \"cpu\"\n[model]\npreset = \"tiny\"\ndtype = \"f32\"\n[data]\nlatent_cache = \"{cache}\"\n{vae}[objective]\ncondition_latents = 2\n[optim]\nlr = 1e-3\n[train]\nsteps = 2\n[checkpoint]\nevery = 2\n[log]\nprogress = false\n",
        out = dir.join(name).display(),
        cache = cache.display()
    );
    std::fs::write(&config, text).unwrap();
    let out = Command::new(bwm()).args(["train", "--config"]).arg(&config).env_remove("RANK").env_remove("WORLD_SIZE").output().unwrap();
    show(&out);
    out
}

#[test]
fn raw_clips_train_like_their_encoded_cache() {
    let dir = temp_dir("prepare-raw");
    let data = demo_data();
    let common = ["--data", data.to_str().unwrap(), "--resolution", "64x32", "--history", "4", "--future", "4", "--stride", "64", "--clips-per-shard", "4"];
    let encoded = dir.join("encoded");
    prepare(&[&common[..], &["--out", encoded.to_str().unwrap()]].concat());
    // Raw clips need no VAE to prepare: the latent shape is the Wan2.2 VAE's.
    let raw = dir.join("raw");
    let out = Command::new(bwm()).args(["prepare", "--raw", "--device", "cpu", "--out", raw.to_str().unwrap()]).args(common).env_remove("RANK").env_remove("WORLD_SIZE").output().unwrap();
    let (stdout, stderr) = show(&out);
    assert!(out.status.success(), "bwm prepare --raw failed: {stderr}");
    assert!(stdout.contains("clips/s"), "{stdout}");
    let (a, b) = (LatentCache::open(&encoded).unwrap(), LatentCache::open(&raw).unwrap());
    assert!(!b.index.has_latents && b.index.has_frames && a.index.has_latents);
    assert_eq!(a.index.latent_shape, b.index.latent_shape);
    assert_eq!(a.index.clips, b.index.clips);
    let err = format!("{:#}", b.load(0, Device::Cpu).err().expect("a raw cache has no latents to load"));
    assert!(err.contains("raw clips"), "{err}");
    // The raw frames encode to the encoded cache's latents; the actions are the same.
    let vae = WanVae::load_any(vae_file(), Kind::Float, Device::Cpu).unwrap();
    for i in [0, b.len() - 1] {
        let (frames, actions) = b.load_frames(i, Device::Cpu).unwrap();
        let clip = a.load(i, Device::Cpu).unwrap();
        assert!(actions.equal(&clip.actions), "clip {i}: actions");
        let z = vae.encode_u8(&frames.unsqueeze(0)).unwrap().squeeze_dim(0).to_kind(Kind::Float);
        assert!(z.equal(&clip.latents), "clip {i}: the raw frames encode to other latents than the cached ones");
    }
    // Training on raw clips needs data.vae, and then trains the weights of the encoded cache.
    let out = train_tiny(&dir, "raw-no-vae", &raw, None);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("raw clips") && stderr.contains("data.vae"), "{stderr}");
    assert!(train_tiny(&dir, "from-latents", &encoded, None).status.success());
    assert!(train_tiny(&dir, "from-raw", &raw, Some(vae_file())).status.success());
    assert_close(&final_weights(&dir.join("from-latents")), &final_weights(&dir.join("from-raw")), "raw clips encoded by the trainer vs the encoded cache");
}
