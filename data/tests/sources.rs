//! Every source reads its format's fixtures (written by scripts/make_fixtures.py with pyarrow, the
//! ffmpeg CLI, h5py and OpenCV) with the known values and colours, and the bundled BWM episodes
//! through the same interface. Bad episodes are skipped with their reasons.

#![cfg(all(feature = "video", feature = "hdf5"))]

mod common;

use bwm_data::clips::{plan_clips, read_clip_frames, ClipSpec};
use bwm_data::frames::{fit, ResizeMode};
use bwm_data::video::{read_frames, stream_info};
use bwm_data::{
    classify, open_dataset, ActionSpec, BwmDataset, CameraLayout, CameraSelection, DefectKind, EpisodeSource, QuatOrder, QuatToEuler,
};
use common::{assert_color, demo_root, fixtures};

const EPISODE_COLORS: [[u8; 3]; 3] = [[200, 40, 40], [40, 200, 40], [40, 40, 200]];
const CAMERA2: [u8; 3] = [128, 128, 40];
const TASKS: [&str; 3] = ["stack the red block", "open the drawer", "push the cup"];

fn state_spec() -> ActionSpec {
    ActionSpec {
        column: "observation.state".into(),
        indices: (0..6).collect(),
        stats_group: "state".into(),
        quat_to_euler: vec![],
        absolute_to_delta: vec![],
    }
}

fn gray(v: u32) -> [u8; 3] {
    [v as u8; 3]
}

/// The LeRobot fixtures' values: state[t][j] = 100e + t + 0.1j, action[t][j] = -(100e + t) - 0.01j.
fn check_lerobot_values(ds: &dyn EpisodeSource, lengths: &[usize]) {
    let action = ActionSpec { column: "action".into(), indices: vec![5, 0], ..state_spec() };
    for (e, &len) in lengths.iter().enumerate() {
        let info = &ds.episodes()[e];
        assert_eq!((info.index, info.length, info.task.as_str()), (e as i64, len, TASKS[e]));
        let s = ds.vectors(e, &state_spec()).unwrap();
        assert_eq!(s.len(), len);
        for (t, row) in s.iter().enumerate() {
            let want: Vec<f32> = (0..6).map(|j| (100.0 * e as f64 + t as f64 + 0.1 * j as f64) as f32).collect();
            assert_eq!(row, &want, "episode {e} frame {t}");
        }
        let a = ds.vectors(e, &action).unwrap();
        assert_eq!(a[3], vec![(-(100.0 * e as f64 + 3.0) - 0.05) as f32, -(100.0 * e as f64 + 3.0) as f32]);
    }
}

/// Frames of camera `top` (episode colour over gray 16 + 12t) stacked over `wrist` (CAMERA2 over
/// the same gray), `top_h` and `wrist_h` high.
fn check_lerobot_frames(ds: &dyn EpisodeSource, e: usize, range: std::ops::Range<usize>, top_h: u32, wrist_h: u32, what: &str) {
    let both = CameraSelection { cameras: vec!["top".into(), "observation.images.wrist".into()], layout: CameraLayout::StackVertically };
    let frames = ds.frames(e, range.clone(), &both).unwrap();
    assert_eq!(frames.len(), range.len());
    for (f, t) in frames.iter().zip(range.clone()) {
        assert_eq!(f.dimensions(), (64, top_h + wrist_h));
        let w = format!("{what} episode {e} frame {t}");
        assert_color(f, 32, top_h / 4, EPISODE_COLORS[e], 12.0, &w);
        assert_color(f, 32, top_h * 3 / 4, gray(16 + 12 * t as u32), 6.0, &w);
        assert_color(f, 32, top_h + wrist_h / 4, CAMERA2, 12.0, &w);
        assert_color(f, 32, top_h + wrist_h * 3 / 4, gray(16 + 12 * t as u32), 6.0, &w);
    }
    let single = ds.frames(e, range.start..range.start + 1, &CameraSelection::single("observation.images.top")).unwrap();
    assert_eq!(single[0].dimensions(), (64, top_h));
    assert!(single[0] == image::imageops::crop_imm(&frames[0], 0, 0, 64, top_h).to_image(), "{what}: camera top alone differs from the top of the stack");
}

#[test]
fn lerobot_v21_reads_values_and_frames() {
    let Some(fixtures) = fixtures() else { return };
    let ds = open_dataset(&fixtures.join("lerobot_v21")).unwrap();
    eprintln!("{}", ds.describe());
    assert!(ds.describe().starts_with("LeRobot v2.1"));
    assert_eq!(ds.cameras(), ["observation.images.top", "observation.images.wrist"]);
    check_lerobot_values(ds.as_ref(), &[10, 12, 9]);
    check_lerobot_frames(ds.as_ref(), 1, 0..12, 48, 32, "v2.1");
    check_lerobot_frames(ds.as_ref(), 2, 5..9, 48, 32, "v2.1");
    assert_eq!(ds.fps(0).unwrap(), 10.0);
    let both = CameraSelection::stacked(&["top", "wrist"]);
    assert_eq!(ds.frame_count(1, &both).unwrap(), 12);

    // Selection errors say what is wrong.
    let e = format!("{:#}", ds.frames(0, 0..1, &CameraSelection::default()).unwrap_err());
    assert!(e.contains("several cameras"), "{e}");
    let e = format!("{:#}", ds.frames(0, 0..1, &CameraSelection::single("side")).unwrap_err());
    assert!(e.contains("no camera 'side'"), "{e}");
    let e = format!("{:#}", ds.frames(0, 0..1, &CameraSelection { cameras: vec!["top".into(), "wrist".into()], layout: CameraLayout::Single }).unwrap_err());
    assert!(e.contains("single"), "{e}");
    let e = format!("{:#}", ds.frames(0, 8..11, &CameraSelection::single("top")).unwrap_err());
    assert!(e.contains("10 frames"), "{e}");
}

#[test]
fn lerobot_image_features_decode_from_parquet_bytes_and_from_files() {
    let Some(fixtures) = fixtures() else { return };
    let ds = open_dataset(&fixtures.join("lerobot_v21_images")).unwrap();
    assert_eq!(ds.episodes().iter().map(|e| e.length).collect::<Vec<_>>(), vec![6, 5]);
    let both = CameraSelection::stacked(&["top", "wrist"]);
    assert_eq!(ds.frame_count(1, &both).unwrap(), 5);
    // PNG is lossless: every pixel is the one written (top half the episode colour or CAMERA2,
    // bottom half the frame's grey).
    for e in 0..2 {
        let frames = ds.frames(e, 1..4, &both).unwrap();
        assert_eq!(frames.len(), 3);
        for (i, f) in frames.iter().enumerate() {
            let t = 1 + i as u8;
            assert_eq!(f.dimensions(), (64, 96));
            assert_eq!(f.get_pixel(10, 5).0, EPISODE_COLORS[e], "episode {e} frame {t} top");
            assert_eq!(f.get_pixel(10, 30).0, [16 + 12 * t; 3], "episode {e} frame {t} top grey");
            assert_eq!(f.get_pixel(10, 48 + 5).0, CAMERA2, "episode {e} frame {t} wrist (from a file)");
        }
    }
    let actions = ds.vectors(0, &ActionSpec { column: "action".into(), indices: (0..6).collect(), stats_group: "x".into(), quat_to_euler: vec![], absolute_to_delta: vec![] }).unwrap();
    assert_eq!(actions.len(), 6);
}

#[test]
fn lerobot_v30_slices_episodes_out_of_shared_av1_files() {
    let Some(fixtures) = fixtures() else { return };
    let root = fixtures.join("lerobot_v30");
    let ds = open_dataset(&root).unwrap();
    eprintln!("{}", ds.describe());
    assert!(ds.describe().starts_with("LeRobot v3.0"));
    let info = stream_info(&root.join("videos/observation.images.top/chunk-000/file-000.mp4")).unwrap();
    eprintln!("AV1 decoder: {info:?}");
    assert_eq!(info.declared_frames, Some(22), "episodes 0 and 1 share the file");
    check_lerobot_values(ds.as_ref(), &[10, 12, 9]);
    // Episode 1 starts 1 s into its files; episode 2 is alone in file-001.
    check_lerobot_frames(ds.as_ref(), 1, 0..12, 64, 64, "v3.0");
    check_lerobot_frames(ds.as_ref(), 1, 7..10, 64, 64, "v3.0");
    check_lerobot_frames(ds.as_ref(), 0, 9..10, 64, 64, "v3.0");
    check_lerobot_frames(ds.as_ref(), 2, 0..9, 64, 64, "v3.0");
    let both = CameraSelection::stacked(&["top", "wrist"]);
    assert_eq!((0..3).map(|e| ds.frame_count(e, &both).unwrap()).collect::<Vec<_>>(), [10, 12, 9]);
}

fn robotwin_frames_check(ds: &dyn EpisodeSource, e: usize, range: std::ops::Range<usize>, what: &str) {
    // Written as RGB arrays through cv2.imencode: left half red, right half blue, bottom gray.
    let head = ds.frames(e, range.clone(), &CameraSelection::default()).unwrap();
    for (f, t) in head.iter().zip(range.clone()) {
        let w = format!("{what} episode {e} frame {t}");
        assert_eq!(f.dimensions(), (64, 48), "{w}");
        assert_color(f, 10, 12, [255, 0, 0], 12.0, &format!("{w} (red side: the R/B swap must be undone)"));
        assert_color(f, 54, 12, [0, 0, 255], 12.0, &format!("{w} (blue side)"));
        assert_color(f, 10, 44, gray(16 + 20 * t as u32), 6.0, &w);
    }
    // The wrist camera holds the same frames upside down; either camera name works.
    for name in ["left_camera", "cam_left_wrist"] {
        let both = CameraSelection::stacked(&["head_camera", name]);
        let f = &ds.frames(e, range.start..range.start + 1, &both).unwrap()[0];
        assert_eq!(f.dimensions(), (64, 96));
        assert_color(f, 10, 48 + 4, gray(16 + 20 * range.start as u32), 6.0, what);
        assert_color(f, 10, 48 + 36, [255, 0, 0], 12.0, what);
    }
}

/// rpy of the fixtures' quaternions.
fn robotwin_eef(e: usize, t: usize, length: usize) -> [f64; 14] {
    let (t, g) = (t as f64, t as f64 / (length - 1) as f64);
    [0.1 * t, 0.2, 0.3 + e as f64, 0.05 * t, 0.1, -0.2, g, -0.1 * t, -0.2, 0.5, -0.05 * t, -0.1, 0.3 + 0.01 * t, g]
}

fn robotwin_joint(e: usize, t: usize, length: usize) -> Vec<f32> {
    (0..14)
        .map(|k| if k == 6 || k == 13 { t as f64 / (length - 1) as f64 } else { e as f64 + 0.1 * t as f64 + 0.01 * k as f64 } as f32)
        .collect()
}

fn check_close(got: &[f32], want: &[f64], tol: f64, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!((*g as f64 - w).abs() <= tol, "{what}: value {i} is {g}, expected {w}");
    }
}

#[test]
fn robotwin_original_layout() {
    let Some(fixtures) = fixtures() else { return };
    let root = fixtures.join("robotwin/original");
    let ds = open_dataset(&root).unwrap();
    eprintln!("{}", ds.describe());
    assert!(ds.describe().contains("2 original layout"));
    assert_eq!(ds.cameras(), ["head_camera", "left_camera"]);
    for (e, len) in [(0, 8), (1, 10)] {
        let info = &ds.episodes()[e];
        assert_eq!((info.index, info.length, info.task.as_str()), (e as i64, len, TASKS[e]));
        let joint = ds.vectors(e, &ActionSpec { column: "joint".into(), indices: (0..14).collect(), ..state_spec() }).unwrap();
        assert_eq!(joint.len(), len);
        for (t, row) in joint.iter().enumerate() {
            assert_eq!(row, &robotwin_joint(e, t, len), "episode {e} frame {t}");
        }
        let eef = ds.vectors(e, &ActionSpec::robotwin_eef_abs()).unwrap();
        for (t, row) in eef.iter().enumerate() {
            check_close(row, &robotwin_eef(e, t, len), 1e-5, &format!("episode {e} frame {t}"));
        }
        assert_eq!(ds.frame_count(e, &CameraSelection::stacked(&["head_camera", "left_camera"])).unwrap(), len);
    }
    robotwin_frames_check(ds.as_ref(), 0, 0..8, "original");
    robotwin_frames_check(ds.as_ref(), 1, 6..9, "original");
    assert_eq!(ds.fps(0).unwrap(), 30.0);

    // A dataset path works as a column; a 2026-only column is an unknown-column defect.
    let grip = ds.vectors(1, &ActionSpec { column: "/endpose/right_gripper".into(), indices: vec![0], ..state_spec() }).unwrap();
    assert_eq!(grip[9], vec![1.0]);
    let e = ds.vectors(0, &ActionSpec { column: "action_joint".into(), indices: vec![0], ..state_spec() }).unwrap_err();
    assert_eq!(classify(&e), DefectKind::UnknownColumn);
    let e = ds.frames(0, 0..1, &CameraSelection::single("front_camera")).unwrap_err();
    assert_eq!(classify(&e), DefectKind::MissingVideo, "{e:#}");

    // One file opens alone too.
    let one = open_dataset(&root.join("data/episode1.hdf5")).unwrap();
    assert_eq!(one.episodes().len(), 1);
    assert_eq!(one.episodes()[0].length, 10);
}

#[test]
fn robotwin_2026_layout() {
    let Some(fixtures) = fixtures() else { return };
    let ds = open_dataset(&fixtures.join("robotwin/v2026")).unwrap();
    eprintln!("{}", ds.describe());
    assert!(ds.describe().contains("2 2026 layout"));
    assert_eq!(ds.cameras(), ["cam_head", "cam_left_wrist"]);
    for (e, written) in [(0, 8), (1, 10)] {
        // States and frames of frames 0..T-2; the action is the next frame's state.
        let len = written - 1;
        let info = &ds.episodes()[e];
        assert_eq!((info.length, info.task.as_str()), (len, TASKS[e]));
        let joint = ds.vectors(e, &ActionSpec { column: "joint".into(), indices: (0..14).collect(), ..state_spec() }).unwrap();
        let next = ds.vectors(e, &ActionSpec { column: "action_joint".into(), indices: (0..14).collect(), ..state_spec() }).unwrap();
        assert_eq!((joint.len(), next.len()), (len, len));
        for t in 0..len {
            check_close(&joint[t], &robotwin_joint(e, t, written).iter().map(|&v| v as f64).collect::<Vec<_>>(), 1e-6, "state");
            check_close(&next[t], &robotwin_joint(e, t + 1, written).iter().map(|&v| v as f64).collect::<Vec<_>>(), 1e-6, "action");
        }
        let eef = ds.vectors(e, &ActionSpec::robotwin_eef_abs()).unwrap();
        for (t, row) in eef.iter().enumerate() {
            check_close(row, &robotwin_eef(e, t, written), 1e-5, &format!("episode {e} frame {t}"));
        }
        assert_eq!(ds.frame_count(e, &CameraSelection::default()).unwrap(), len);
    }
    robotwin_frames_check(ds.as_ref(), 0, 0..7, "2026");
    robotwin_frames_check(ds.as_ref(), 1, 2..5, "2026");
    let e = ds.frames(0, 6..8, &CameraSelection::default()).unwrap_err();
    assert!(format!("{e:#}").contains("7 frames"), "{e:#}");
}

#[test]
fn conversions_apply_through_a_source() {
    let Some(fixtures) = fixtures() else { return };
    // Deltas of the fixture state: 1 per frame on every value, 0 at frame 0.
    let ds = open_dataset(&fixtures.join("lerobot_v21")).unwrap();
    let spec = ActionSpec { absolute_to_delta: vec![0, 2], ..state_spec() };
    let v = ds.vectors(1, &spec).unwrap();
    assert_eq!(v[0][0], 0.0);
    assert!(v[1..].iter().all(|r| r[0] == 1.0 && r[2] == 1.0 && r[1] != 1.0));
    // Values 0..4 taken as an x, y, z, w quaternion: converted, the vector shrinks by one.
    let q = ActionSpec { quat_to_euler: vec![QuatToEuler { start: 0, order: QuatOrder::Xyzw }], ..state_spec() };
    assert_eq!(ds.vectors(0, &q).unwrap()[4].len(), 5);
}

#[test]
fn bad_episodes_are_skipped_with_reasons() {
    let Some(fixtures) = fixtures() else { return };
    let ds = open_dataset(&fixtures.join("lerobot_v21_bad")).unwrap();
    let all: Vec<usize> = (0..ds.episodes().len()).collect();
    let clip = ClipSpec { history: 4, future: 4, stride: 4 };
    let plan = plan_clips(ds.as_ref(), &all, &state_spec(), &CameraSelection::default(), &clip).unwrap();
    eprintln!("{}", plan.report);
    for s in &plan.report.skipped {
        eprintln!("  episode {}: {}: {}", s.index, s.kind, s.reason);
    }
    assert_eq!((plan.report.episodes, plan.report.used), (8, 1));
    assert_eq!(plan.episodes[0].info.index, 0);
    assert_eq!(plan.report.clips, clip.windows(12).len());
    let kinds: Vec<(i64, DefectKind)> = plan.report.skipped.iter().map(|s| (s.index, s.kind)).collect();
    assert_eq!(
        kinds,
        [
            (1, DefectKind::NonFinite),
            (2, DefectKind::MissingVideo),
            (3, DefectKind::CountMismatch),
            (4, DefectKind::TooShort),
            (5, DefectKind::UnreadableVideo),
            (6, DefectKind::UnreadableVideo),
            (7, DefectKind::Unreadable)
        ]
    );
    assert!(plan.report.skipped[0].reason.contains("row 3"), "{}", plan.report.skipped[0].reason);
    let summary = plan.report.to_string();
    assert!(summary.contains("8 episodes: 1 used") && summary.contains("1 missing video"), "{summary}");
    assert!(plan.report.skipped[6].reason.contains("episode_000007.parquet"), "{}", plan.report.skipped[6].reason);

    // Decoding the garbage or cut-off video is an error, not a crash.
    for e in [5, 6] {
        let e = ds.frames(e, 0..1, &CameraSelection::default()).unwrap_err();
        assert_eq!(classify(&e), DefectKind::UnreadableVideo, "{e:#}");
    }

    // A column no episode has: the whole dataset is unusable, said in one line.
    let spec = ActionSpec { column: "observation.nope".into(), ..state_spec() };
    let e = format!("{:#}", plan_clips(ds.as_ref(), &all, &spec, &CameraSelection::default(), &clip).unwrap_err());
    eprintln!("{e}");
    assert!(!e.contains('\n') && e.contains("no usable episode") && e.contains("unknown column") && e.contains("observation.nope"), "{e}");
}

#[test]
fn bundled_episodes_through_the_source_interface() {
    let ds = open_dataset(&demo_root()).unwrap();
    let direct = BwmDataset::open(&demo_root()).unwrap();
    assert!(ds.describe().starts_with("BWM layout"));
    assert_eq!(ds.episodes().len(), 3);
    let spec = ActionSpec::eef_abs();
    for (e, ep) in direct.episodes.iter().enumerate() {
        let v = ds.vectors(e, &spec).unwrap();
        assert_eq!(v, direct.actions(ep, &spec).unwrap());
        assert_eq!((v.len(), v[0].len()), (ep.length, 14));
        assert_eq!(ds.frame_count(e, &CameraSelection::default()).unwrap(), ep.length, "frames = parquet rows");
        assert_eq!(ds.episodes()[e].task, ep.task);
    }
    assert_eq!(ds.fps(0).unwrap(), 30.0);
    let f = ds.frames(0, 10..14, &CameraSelection::single("video")).unwrap();
    assert!(f == read_frames(&demo_root().join(&direct.episodes[0].video), 10..14).unwrap());
    assert!(ds.frames(0, 0..1, &CameraSelection::single("head")).is_err());

    // Clips of the paper's shape (x0 + 8 history + 72 future) every 24 frames, at 640x480 and
    // at a small test resolution.
    let clip = ClipSpec { history: 8, future: 72, stride: 24 };
    let plan = plan_clips(ds.as_ref(), &[0, 1, 2], &spec, &CameraSelection::default(), &clip).unwrap();
    eprintln!("bundled episodes: {}", plan.report);
    assert_eq!(plan.report.used, 3);
    let ep = &plan.episodes[1];
    let w = &ep.windows[1];
    assert_eq!(w.future_start, 25);
    assert_eq!(w.frames.len(), 81);
    assert_eq!(ep.clip_actions(w).len(), 81);
    assert_eq!(ep.clip_actions(w)[0], ep.actions[0]);
    let frames = read_clip_frames(ds.as_ref(), 1, w, &CameraSelection::default()).unwrap();
    assert_eq!(frames.len(), 81);
    assert!(frames.iter().all(|f| f.dimensions() == (640, 480)));
    let reread = ds.frames(1, 17..25, &CameraSelection::default()).unwrap();
    assert!(frames[1..9] == reread[..], "history frames are frames 17..25");
    let small: Vec<_> = frames.iter().map(|f| fit(f, 160, 128, ResizeMode::Crop)).collect();
    assert!(small.iter().all(|f| f.dimensions() == (160, 128)));
}
