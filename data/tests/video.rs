//! Video decoding and writing on the bundled episodes (`../shared/data/bwm-demo`), and the frame
//! helpers.

use bwm_data::frames::{fit, frame_strip, frames_to_tensor, stack_views_vertically, swap_red_blue, tensor_to_frames};
use bwm_data::ResizeMode;
use bwm_testdir::shared;
use image::{Rgb, RgbImage};
use tch::{Kind, Tensor};

/// A smooth pattern that moves with `t` (no hard edges, which 4:2:0 chroma cannot keep).
fn synthetic(width: u32, height: u32, t: u32) -> RgbImage {
    RgbImage::from_fn(width, height, |x, y| {
        let r = 20 + 150 * x / width + 4 * t;
        let g = 20 + 150 * y / height + 2 * t;
        let b = 30 + 100 * (x + y) / (width + height);
        Rgb([r as u8, g as u8, b as u8])
    })
}

#[cfg(feature = "video")]
mod video {
    use bwm_data::video::{probe, read_frames, write_mp4, write_mp4_with};
    use bwm_data::{BwmDataset, Mp4Encoder};

    use super::*;

    fn mean_abs_diff(a: &RgbImage, b: &RgbImage) -> f64 {
        assert_eq!(a.dimensions(), b.dimensions());
        let sum: u64 = a.as_raw().iter().zip(b.as_raw()).map(|(&x, &y)| x.abs_diff(y) as u64).sum();
        sum as f64 / a.as_raw().len() as f64
    }

    fn demo() -> BwmDataset {
        BwmDataset::open(&shared().join("data/bwm-demo")).unwrap()
    }

    #[test]
    fn bundled_episodes_have_the_manifest_frame_counts() {
        let ds = demo();
        assert_eq!(ds.episodes.len(), 3);
        for ep in &ds.episodes {
            let path = ds.root.join(&ep.video);
            let info = probe(&path).unwrap();
            eprintln!("{}: {info:?}", ep.video);
            assert_eq!(info.frames, ep.length, "{}: decoded frames vs manifest length", path.display());
            assert_eq!(info.declared_frames, Some(info.frames), "{}: container count vs decoded", path.display());
            assert!(info.width > 0 && info.height > 0 && info.fps > 0.0, "{info:?}");
        }
    }

    #[test]
    fn decodes_a_range_the_same_as_from_the_start() {
        let ds = demo();
        let path = ds.root.join(&ds.episodes[0].video);
        let info = probe(&path).unwrap();
        let clip = read_frames(&path, 10..14).unwrap();
        assert_eq!(clip.len(), 4);
        assert!(clip.iter().all(|f| f.dimensions() == (info.width, info.height)));
        let head = read_frames(&path, 0..14).unwrap();
        assert!(head[10..] == clip[..], "frames 10..14 differ between the two reads");
        assert!(clip[0] != clip[3], "consecutive decoded frames are all identical");
        // Frames are not blank.
        let mean = clip[0].as_raw().iter().map(|&v| v as f64).sum::<f64>() / clip[0].as_raw().len() as f64;
        assert!(mean > 10.0 && mean < 245.0, "mean pixel {mean}");

        let last = read_frames(&path, info.frames - 1..info.frames).unwrap();
        assert_eq!(last.len(), 1);
        assert!(read_frames(&path, 5..5).unwrap().is_empty());
    }

    #[test]
    fn a_range_past_the_end_is_an_error_naming_the_file() {
        let ds = demo();
        let ep = &ds.episodes[0];
        let path = ds.root.join(&ep.video);
        let e = format!("{:#}", read_frames(&path, ep.length - 1..ep.length + 1).unwrap_err());
        assert!(e.contains("episode_000040.mp4") && e.contains(&format!("only {} frames", ep.length)), "{e}");
        let e = format!("{:#}", read_frames(&path, 1000..1000).unwrap_err());
        assert!(e.contains("only"), "{e}");
        #[allow(clippy::reversed_empty_ranges)]
        let e = format!("{:#}", read_frames(&path, 4..2).unwrap_err());
        assert!(e.contains("reversed"), "{e}");
        let missing = shared().join("data/bwm-demo/no_such_video.mp4");
        let e = format!("{:#}", probe(&missing).unwrap_err());
        assert!(e.contains("no_such_video.mp4"), "{e}");
    }

    fn round_trip(encoder: Mp4Encoder, tag: &str) -> f64 {
        let dir = bwm_testdir::TestDir::new(tag);
        let path = dir.join("clip.mp4");
        let frames: Vec<_> = (0..12).map(|t| synthetic(96, 64, t)).collect();
        write_mp4_with(&path, &frames, 12.0, encoder).unwrap();
        let info = probe(&path).unwrap();
        assert_eq!((info.width, info.height, info.frames), (96, 64, 12), "{info:?}");
        assert!((info.fps - 12.0).abs() < 1e-6, "{info:?}");
        let back = read_frames(&path, 0..12).unwrap();
        let worst = frames.iter().zip(&back).map(|(a, b)| mean_abs_diff(a, b)).fold(0.0, f64::max);
        for (i, b) in back.iter().enumerate().skip(1) {
            assert!(mean_abs_diff(b, &frames[i]) < mean_abs_diff(b, &frames[i - 1]), "frame {i} reads back out of order");
        }
        let names: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, ["clip.mp4"], "temporary files left behind");
        worst
    }

    #[test]
    fn write_mp4_reads_back_close_to_the_input() {
        let best = Mp4Encoder::best().unwrap();
        eprintln!("write_mp4 encoder: {best:?} ({})", best.ffmpeg_name());
        let worst = round_trip(best, "best");
        eprintln!("{best:?}: worst per-frame mean abs diff {worst:.3}");
        assert!(worst < 2.0, "{best:?}: mean abs diff {worst}");
        let worst = round_trip(Mp4Encoder::Mpeg4, "mpeg4");
        eprintln!("Mpeg4: worst per-frame mean abs diff {worst:.3}");
        assert!(worst < 2.5, "mpeg4: mean abs diff {worst}");

        let dir = bwm_testdir::TestDir::new("write-default");
        let path = dir.join("default.mp4");
        write_mp4(&path, &[synthetic(32, 32, 0), synthetic(32, 32, 1)], 30000.0 / 1001.0).unwrap();
        let info = probe(&path).unwrap();
        assert_eq!(info.frames, 2);
        assert!((info.fps - 30000.0 / 1001.0).abs() < 1e-9, "{info:?}");
        write_mp4_with(&path, &[synthetic(32, 32, 0)], 30000.0 / 1001.0, Mp4Encoder::Mpeg4).unwrap();
        let info = probe(&path).unwrap();
        assert_eq!((info.frames, info.codec.as_str()), (1, "mpeg4"), "{info:?}");
        assert!((info.fps - 30000.0 / 1001.0).abs() < 1e-9, "{info:?}");
    }

    #[test]
    fn write_mp4_rejects_bad_input_and_leaves_nothing() {
        let dir = bwm_testdir::TestDir::new("write-bad");
        let path = dir.join("bad.mp4");
        let e = format!("{:#}", write_mp4(&path, &[synthetic(33, 32, 0)], 10.0).unwrap_err());
        assert!(e.contains("bad.mp4") && e.contains("even"), "{e}");
        let e = format!("{:#}", write_mp4(&path, &[synthetic(32, 32, 0), synthetic(34, 32, 0)], 10.0).unwrap_err());
        assert!(e.contains("frame 1"), "{e}");
        assert!(write_mp4(&path, &[], 10.0).is_err());
        assert!(write_mp4(&path, &[synthetic(32, 32, 0)], 0.0).is_err());
        assert!(write_mp4(&dir.join("missing_dir/x.mp4"), &[synthetic(32, 32, 0)], 10.0).is_err());
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0, "files left behind");
    }

    #[test]
    fn a_decoded_clip_becomes_a_model_input() {
        let ds = demo();
        let frames = read_frames(&ds.root.join(&ds.episodes[1].video), 0..5).unwrap();
        let fitted: Vec<_> = frames.iter().map(|f| fit(f, 160, 96, ResizeMode::Crop)).collect();
        let t = frames_to_tensor(&fitted).unwrap();
        assert_eq!(t.size(), [3, 5, 96, 160]);
        assert_eq!(tensor_to_frames(&t).unwrap(), fitted);
    }
}

#[cfg(not(feature = "video"))]
#[test]
fn video_functions_say_the_feature_is_missing() {
    let e = format!("{:#}", bwm_data::video::probe(&shared().join("x.mp4")).unwrap_err());
    assert!(e.contains("without the `video` feature"), "{e}");
}

#[test]
fn frames_tensor_round_trip() {
    let frames: Vec<_> = (0..3).map(|t| synthetic(20, 12, t)).collect();
    let t = frames_to_tensor(&frames).unwrap();
    assert_eq!(t.size(), [3, 3, 12, 20]);
    assert_eq!(t.kind(), Kind::Float);
    let px = frames[2].get_pixel(7, 5);
    for c in 0..3 {
        let v = t.double_value(&[c, 2, 5, 7]);
        assert!((v - (px[c as usize] as f64 / 127.5 - 1.0)).abs() < 1e-6);
    }
    assert_eq!(tensor_to_frames(&t).unwrap(), frames);
    assert_eq!(tensor_to_frames(&t.unsqueeze(0)).unwrap(), frames);
    // Small errors round away, out-of-range values clamp.
    let noisy = &t + 0.001 * Tensor::ones_like(&t);
    assert_eq!(tensor_to_frames(&noisy).unwrap(), frames);
    let over = tensor_to_frames(&(Tensor::ones([3, 1, 2, 2], (Kind::Float, tch::Device::Cpu)) * 5.0)).unwrap();
    assert!(over[0].as_raw().iter().all(|&v| v == 255));

    assert!(frames_to_tensor(&[]).is_err());
    let e = frames_to_tensor(&[synthetic(20, 12, 0), synthetic(20, 10, 0)]).unwrap_err().to_string();
    assert!(e.contains("frame 1"), "{e}");
    assert!(tensor_to_frames(&Tensor::zeros([4, 1, 2, 2], (Kind::Float, tch::Device::Cpu))).is_err());
    assert!(tensor_to_frames(&Tensor::zeros([2, 3, 1, 2, 2], (Kind::Float, tch::Device::Cpu))).is_err());
    assert!(tensor_to_frames(&Tensor::full([3, 1, 2, 2], f64::NAN, (Kind::Float, tch::Device::Cpu))).is_err());
}

#[test]
fn fit_gives_the_requested_size_and_crop_keeps_the_centre() {
    // 200x100: blue in the middle columns 50..150, red elsewhere.
    let blue = Rgb([0, 0, 255]);
    let img = RgbImage::from_fn(200, 100, |x, _| if (50..150).contains(&x) { blue } else { Rgb([255, 0, 0]) });
    for mode in [ResizeMode::Crop, ResizeMode::Pad, ResizeMode::Stretch] {
        for (w, h) in [(50, 50), (64, 16), (300, 90), (200, 100)] {
            assert_eq!(fit(&img, w, h, mode).dimensions(), (w, h), "{mode:?} {w}x{h}");
        }
    }
    // Cover scale 0.5 gives 100x50; the centre 50x50 is source columns 50..150: all blue.
    let crop = fit(&img, 50, 50, ResizeMode::Crop);
    assert!(crop.pixels().all(|p| p[2] > 200 && p[0] < 40), "crop left the centre");
    // Pad: 50x25 content centred vertically on black.
    let pad = fit(&img, 50, 50, ResizeMode::Pad);
    assert_eq!(*pad.get_pixel(25, 2), Rgb([0, 0, 0]));
    assert_eq!(*pad.get_pixel(25, 47), Rgb([0, 0, 0]));
    assert!(pad.get_pixel(25, 25)[2] > 200);
    assert!(pad.get_pixel(2, 25)[0] > 200);
    // Stretch keeps all columns: red at both edges.
    let stretch = fit(&img, 50, 50, ResizeMode::Stretch);
    assert!(stretch.get_pixel(1, 25)[0] > 200 && stretch.get_pixel(48, 25)[0] > 200);

    assert_eq!(fit(&RgbImage::new(0, 0), 8, 4, ResizeMode::Crop).dimensions(), (8, 4));
    assert_eq!(serde_json::from_str::<ResizeMode>("\"pad\"").unwrap(), ResizeMode::Pad);
    assert!(serde_json::from_str::<ResizeMode>("\"Crop\"").is_err());
}

#[test]
fn strips_and_stacks_have_the_grid_size() {
    let f = |v: u8| RgbImage::from_pixel(8, 6, Rgb([v, v, v]));
    let strip = frame_strip(&[vec![f(10), f(20), f(30)], vec![f(40), f(50), f(60)]]).unwrap();
    assert_eq!(strip.dimensions(), (24, 12));
    assert_eq!(*strip.get_pixel(2 * 8 + 3, 6 + 2), Rgb([60, 60, 60]));
    assert_eq!(*strip.get_pixel(0, 0), Rgb([10, 10, 10]));
    let ragged = frame_strip(&[vec![f(1), f(2)], vec![f(3)]]).unwrap();
    assert_eq!(ragged.dimensions(), (16, 12));
    assert_eq!(*ragged.get_pixel(12, 9), Rgb([0, 0, 0]));
    assert!(frame_strip(&[]).is_err());
    assert!(frame_strip(&[vec![f(1)], vec![RgbImage::new(4, 6)]]).is_err());

    let stacked = stack_views_vertically(&[f(1), RgbImage::from_pixel(8, 4, Rgb([2, 2, 2]))]).unwrap();
    assert_eq!(stacked.dimensions(), (8, 10));
    assert_eq!(*stacked.get_pixel(3, 5), Rgb([1, 1, 1]));
    assert_eq!(*stacked.get_pixel(3, 6), Rgb([2, 2, 2]));
    assert!(stack_views_vertically(&[f(1), RgbImage::new(4, 4)]).is_err());
    assert!(stack_views_vertically(&[]).is_err());
}

#[test]
fn swap_red_blue_exchanges_the_outer_channels() {
    let mut img = RgbImage::from_pixel(3, 2, Rgb([10, 20, 30]));
    swap_red_blue(&mut img);
    assert!(img.pixels().all(|p| *p == Rgb([30, 20, 10])));
}
