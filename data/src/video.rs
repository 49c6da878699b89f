//! Video files in, RGB frames out, and back: decoding (any container and codec FFmpeg reads,
//! mp4/H.264 for the datasets) and mp4 writing. Built on FFmpeg's libraries through
//! `ffmpeg-next` when the `video` feature is on (the default); without it the API is the same and
//! every function returns an error saying so.

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use image::RgbImage;

/// What a video file holds, as `read_frames` sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoInfo {
    pub width: u32,
    pub height: u32,
    /// Frames counted by decoding the whole stream: exactly the frames `read_frames` can return.
    pub frames: usize,
    /// The frame count the container declares (for mp4, the sample count), when it has one.
    pub declared_frames: Option<usize>,
    /// The stream's average frame rate.
    pub fps: f64,
    /// The decoder's short name, e.g. "h264".
    pub codec: String,
}

/// What a video file's headers say, without decoding (`stream_info`).
#[derive(Debug, Clone, PartialEq)]
pub struct StreamInfo {
    pub width: u32,
    pub height: u32,
    /// The frame count the container declares (for mp4, the sample count), when it has one.
    pub declared_frames: Option<usize>,
    /// The stream's average frame rate.
    pub fps: f64,
    /// The stream's duration in seconds (the container's when the stream states none).
    pub duration_s: Option<f64>,
    /// The decoder FFmpeg picks, e.g. "h264", "libdav1d".
    pub codec: String,
}

/// The encoders `write_mp4_with` can use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mp4Encoder {
    /// H.264 through libx264 (present when the FFmpeg build links it, as Debian's does).
    H264,
    /// MPEG-4 part 2, FFmpeg's built-in `mpeg4` encoder: always there, larger files.
    Mpeg4,
}

impl Mp4Encoder {
    /// FFmpeg's name for the encoder.
    pub fn ffmpeg_name(self) -> &'static str {
        match self {
            Mp4Encoder::H264 => "libx264",
            Mp4Encoder::Mpeg4 => "mpeg4",
        }
    }

    /// The best encoder this FFmpeg has: H.264 when libx264 is linked, else MPEG-4 part 2.
    pub fn best() -> Result<Self> {
        if imp::has_encoder(Mp4Encoder::H264)? {
            Ok(Mp4Encoder::H264)
        } else {
            Ok(Mp4Encoder::Mpeg4)
        }
    }
}

/// Opens the file and decodes its video stream once to count the frames.
pub fn probe(path: &Path) -> Result<VideoInfo> {
    imp::probe(path).with_context(|| format!("probing video {}", path.display()))
}

/// Reads the headers of a video file (no decoding); fails when FFmpeg has no decoder for it.
pub fn stream_info(path: &Path) -> Result<StreamInfo> {
    imp::stream_info(path).with_context(|| format!("reading video {}", path.display()))
}

/// Decodes the frames whose presentation times are nearest to `times` (seconds, non-decreasing),
/// as LeRobot does: each request takes the closest frame, which must lie within `tolerance_s`.
/// Seeks to the key frame before the first request instead of decoding from the start.
pub fn read_frames_at(path: &Path, times: &[f64], tolerance_s: f64) -> Result<Vec<RgbImage>> {
    ensure!(
        tolerance_s.is_finite() && tolerance_s > 0.0,
        "{}: timestamp tolerance {tolerance_s} is not a positive number",
        path.display()
    );
    ensure!(times.iter().all(|t| t.is_finite()), "{}: a requested timestamp is not finite", path.display());
    ensure!(times.windows(2).all(|w| w[0] <= w[1]), "{}: requested timestamps are not in increasing order", path.display());
    if times.is_empty() {
        return Ok(Vec::new());
    }
    imp::read_frames_at(path, times, tolerance_s).with_context(|| format!("reading frames of video {}", path.display()))
}

/// Decodes the frames with indices in `range` (0 = the first decoded frame), as RGB8. Decodes
/// from the start of the file. A range reaching past the last frame is an error.
pub fn read_frames(path: &Path, range: Range<usize>) -> Result<Vec<RgbImage>> {
    ensure!(range.start <= range.end, "{}: frame range {}..{} is reversed", path.display(), range.start, range.end);
    imp::read_frames(path, range).with_context(|| format!("reading frames of video {}", path.display()))
}

/// Writes `frames` (all the same size, even width and height) as an mp4 at `fps`, with the best
/// encoder available (`Mp4Encoder::best`).
pub fn write_mp4(path: &Path, frames: &[RgbImage], fps: f64) -> Result<()> {
    let encoder = Mp4Encoder::best().with_context(|| format!("writing video {}", path.display()))?;
    write_mp4_with(path, frames, fps, encoder)
}

/// Whether this build reads and writes video (the `video` feature).
pub const AVAILABLE: bool = cfg!(feature = "video");

/// `frames` as an mp4 at `path` when this build has video, else as a PNG contact sheet (rows of
/// `per_row` frames) beside it with the extension `png`, so that builds without FFmpeg still
/// leave something to look at. Returns the path written.
pub fn write_mp4_or_sheet(path: &Path, frames: &[RgbImage], fps: f64, per_row: usize) -> Result<PathBuf> {
    if AVAILABLE {
        write_mp4(path, frames, fps)?;
        return Ok(path.to_path_buf());
    }
    let rows: Vec<Vec<RgbImage>> = frames.chunks(per_row.max(1)).map(<[RgbImage]>::to_vec).collect();
    let sheet = crate::frames::frame_strip(&rows).with_context(|| format!("contact sheet for {}", path.display()))?;
    let png = path.with_extension("png");
    let tmp = temp_path(&png)?;
    sheet.save_with_format(&tmp, image::ImageFormat::Png).with_context(|| format!("writing {}", png.display()))?;
    commit(&tmp, &png)?;
    Ok(png)
}

/// `write_mp4` with a chosen encoder. The file is written under a temporary name in the same
/// directory and renamed when complete, so `path` never holds a partial video.
pub fn write_mp4_with(path: &Path, frames: &[RgbImage], fps: f64, encoder: Mp4Encoder) -> Result<()> {
    let ctx = || format!("writing video {}", path.display());
    let Some(first) = frames.first() else { bail!("{}: no frames to write", path.display()) };
    let (width, height) = first.dimensions();
    ensure!(
        width > 0 && height > 0 && width % 2 == 0 && height % 2 == 0,
        "{}: frames are {width}x{height}; 4:2:0 video needs even, non-zero width and height",
        path.display()
    );
    if let Some((i, f)) = frames.iter().enumerate().find(|(_, f)| f.dimensions() != (width, height)) {
        bail!("{}: frame {i} is {}x{}, frame 0 is {width}x{height}", path.display(), f.width(), f.height());
    }
    ensure!(fps.is_finite() && fps > 0.0, "{}: frame rate {fps} is not a positive number", path.display());

    let tmp = temp_path(path).with_context(ctx)?;
    let written = imp::write_mp4(&tmp, frames, fps, encoder)
        .and_then(|()| commit(&tmp, path));
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written.with_context(ctx)
}

/// Makes the complete file `tmp` durable and renames it to `path`, then syncs the folder so
/// that the rename survives a crash: `path` holds the whole file or what it held before.
fn commit(tmp: &Path, path: &Path) -> Result<()> {
    let renamed = || -> std::io::Result<()> {
        std::fs::File::open(tmp)?.sync_all()?;
        std::fs::rename(tmp, path)
    };
    renamed().with_context(|| format!("renaming {} to {}", tmp.display(), path.display()))?;
    crate::latent_cache::sync_dir(path.parent().context("a file path has a folder")?);
    Ok(())
}

/// A hidden sibling of `path`, unique to this process and call.
fn temp_path(path: &Path) -> Result<PathBuf> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    static COUNTER: AtomicUsize = AtomicUsize::new(0);
    let name = path.file_name().with_context(|| format!("{} names no file", path.display()))?;
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    Ok(path.with_file_name(format!(".{}.{}-{n}.tmp", name.to_string_lossy(), std::process::id())))
}

#[cfg(not(feature = "video"))]
mod imp {
    use super::*;

    const MISSING: &str = "bwm-data was built without the `video` feature (FFmpeg); rebuild with it to read or write video";

    pub fn has_encoder(_: Mp4Encoder) -> Result<bool> {
        bail!(MISSING)
    }
    pub fn probe(_: &Path) -> Result<VideoInfo> {
        bail!(MISSING)
    }
    pub fn read_frames(_: &Path, _: Range<usize>) -> Result<Vec<RgbImage>> {
        bail!(MISSING)
    }
    pub fn stream_info(_: &Path) -> Result<StreamInfo> {
        bail!(MISSING)
    }
    pub fn read_frames_at(_: &Path, _: &[f64], _: f64) -> Result<Vec<RgbImage>> {
        bail!(MISSING)
    }
    pub fn write_mp4(_: &Path, _: &[RgbImage], _: f64, _: Mp4Encoder) -> Result<()> {
        bail!(MISSING)
    }
}

#[cfg(feature = "video")]
mod imp {
    use std::sync::OnceLock;

    use anyhow::anyhow;
    use ff::format::Pixel;
    use ff::software::scaling::{self, Flags};
    use ff::{codec, color, decoder, encoder, format, frame, media, threading, Dictionary, Packet, Rational};
    use ffmpeg_next as ff;

    use super::*;

    fn init() -> Result<()> {
        static INIT: OnceLock<Result<(), String>> = OnceLock::new();
        INIT.get_or_init(|| {
            ff::init().map_err(|e| e.to_string())?;
            ff::log::set_level(ff::log::Level::Error);
            Ok(())
        })
        .clone()
        .map_err(|e| anyhow!("initializing FFmpeg: {e}"))
    }

    /// "Nothing more now" from a send/receive call, as opposed to a failure.
    fn is_drained(e: &ff::Error) -> bool {
        matches!(e, ff::Error::Eof | ff::Error::Other { errno: ff::error::EAGAIN })
    }

    pub fn has_encoder(which: Mp4Encoder) -> Result<bool> {
        init()?;
        Ok(encoder::find_by_name(which.ffmpeg_name()).is_some())
    }

    struct Source {
        input: format::context::Input,
        stream: usize,
        decoder: decoder::Video,
        declared_frames: Option<usize>,
        fps: f64,
        /// Seconds per timestamp unit of the stream.
        time_base: f64,
        duration_s: Option<f64>,
    }

    fn open(path: &Path) -> Result<Source> {
        init()?;
        let input = format::input(path).context("not a readable media file")?;
        let stream = input.streams().best(media::Type::Video).context("no video stream")?;
        let rate = [stream.avg_frame_rate(), stream.rate()]
            .into_iter()
            .find(|r| r.numerator() > 0 && r.denominator() > 0)
            .context("the video stream declares no frame rate")?;
        let id = stream.parameters().id();
        if decoder::find(id).is_none() {
            let hint = if id == codec::Id::AV1 { " (AV1 needs an FFmpeg built with libdav1d or libaom)" } else { "" };
            bail!("this FFmpeg has no decoder for {} video{hint}", id.name());
        }
        let time_base = f64::from(stream.time_base());
        let duration_s = match stream.duration() {
            d if d > 0 && time_base > 0.0 => Some(d as f64 * time_base),
            _ => Some(input.duration()).filter(|&d| d > 0).map(|d| d as f64 / f64::from(ff::ffi::AV_TIME_BASE)),
        };
        let mut ctx = codec::context::Context::from_parameters(stream.parameters())?;
        ctx.set_threading(threading::Config { kind: threading::Type::Frame, count: 0, ..Default::default() });
        let decoder = ctx.decoder().video().with_context(|| format!("opening the {} decoder", id.name()))?;
        Ok(Source {
            stream: stream.index(),
            declared_frames: usize::try_from(stream.frames()).ok().filter(|&n| n > 0),
            fps: f64::from(rate),
            time_base,
            duration_s,
            decoder,
            input,
        })
    }

    impl Source {
        /// Decodes frames in order, handing each to `each` with its index until `each` returns
        /// false or the stream ends. Returns how many frames were decoded.
        fn decode(&mut self, mut each: impl FnMut(usize, &frame::Video) -> Result<bool>) -> Result<usize> {
            let mut count = 0;
            let mut frame = frame::Video::empty();
            let mut drain = |decoder: &mut decoder::Video, count: &mut usize| -> Result<bool> {
                loop {
                    match decoder.receive_frame(&mut frame) {
                        Ok(()) => {}
                        Err(e) if is_drained(&e) => return Ok(true),
                        Err(e) => return Err(e).with_context(|| format!("decoding frame {count}")),
                    }
                    let go_on = each(*count, &frame)?;
                    *count += 1;
                    if !go_on {
                        return Ok(false);
                    }
                }
            };
            loop {
                let mut packet = Packet::empty();
                match packet.read(&mut self.input) {
                    Ok(()) => {}
                    Err(ff::Error::Eof) => break,
                    Err(e) => return Err(e).with_context(|| format!("reading the packet after frame {count}")),
                }
                if packet.stream() != self.stream {
                    continue;
                }
                self.decoder.send_packet(&packet).with_context(|| format!("decoding frame {count}"))?;
                if !drain(&mut self.decoder, &mut count)? {
                    return Ok(count);
                }
            }
            self.decoder.send_eof()?;
            drain(&mut self.decoder, &mut count)?;
            Ok(count)
        }
    }

    pub fn probe(path: &Path) -> Result<VideoInfo> {
        let mut src = open(path)?;
        let mut size = (src.decoder.width(), src.decoder.height());
        let frames = src.decode(|i, f| {
            if i == 0 {
                size = (f.width(), f.height());
            }
            Ok(true)
        })?;
        let codec = src.decoder.codec().map(|c| c.name().to_string()).unwrap_or_default();
        Ok(VideoInfo { width: size.0, height: size.1, frames, declared_frames: src.declared_frames, fps: src.fps, codec })
    }

    pub fn read_frames(path: &Path, range: Range<usize>) -> Result<Vec<RgbImage>> {
        let mut src = open(path)?;
        if range.end == 0 {
            return Ok(Vec::new());
        }
        let mut to_rgb = ToRgb::default();
        let mut out = Vec::with_capacity(range.len().min(src.declared_frames.unwrap_or(0)));
        let decoded = src.decode(|i, f| {
            if i >= range.start {
                out.push(to_rgb.convert(f).with_context(|| format!("converting frame {i} to RGB"))?);
            }
            Ok(i + 1 < range.end)
        })?;
        ensure!(decoded >= range.end, "frames {}..{} requested but the video has only {decoded} frames", range.start, range.end);
        Ok(out)
    }

    pub fn stream_info(path: &Path) -> Result<StreamInfo> {
        let src = open(path)?;
        Ok(StreamInfo {
            width: src.decoder.width(),
            height: src.decoder.height(),
            declared_frames: src.declared_frames,
            fps: src.fps,
            duration_s: src.duration_s,
            codec: src.decoder.codec().map(|c| c.name().to_string()).unwrap_or_default(),
        })
    }

    pub fn read_frames_at(path: &Path, times: &[f64], tolerance: f64) -> Result<Vec<RgbImage>> {
        let mut src = open(path)?;
        let first = times[0] - tolerance;
        if first > 0.0 {
            let us = (first * f64::from(ff::ffi::AV_TIME_BASE)).floor() as i64;
            if src.input.seek(us, ..us).is_ok() {
                src.decoder.flush();
                let picked = pick_frames(&mut src, times, tolerance)?;
                if picked.iter().all(Option::is_some) {
                    return Ok(picked.into_iter().flatten().collect());
                }
            }
            // The seek failed or landed after a requested time: decode from the start.
            src = open(path)?;
        }
        let picked = pick_frames(&mut src, times, tolerance)?;
        if let Some(i) = picked.iter().position(Option::is_none) {
            bail!("no frame within {tolerance:.4} s of {:.4} s (request {i} of {})", times[i], times.len());
        }
        Ok(picked.into_iter().flatten().collect())
    }

    /// For each requested time, the nearest decoded frame within `tolerance`, decoding until
    /// the frames pass the last request.
    fn pick_frames(src: &mut Source, times: &[f64], tolerance: f64) -> Result<Vec<Option<RgbImage>>> {
        let time_base = src.time_base;
        let last = times[times.len() - 1];
        let mut best: Vec<Option<(f64, RgbImage)>> = vec![None; times.len()];
        let mut to_rgb = ToRgb::default();
        let mut lo = 0;
        src.decode(|i, f| {
            let ts = f.timestamp().with_context(|| format!("decoded frame {i} carries no timestamp"))?;
            let t = ts as f64 * time_base;
            while lo < times.len() && times[lo] + tolerance < t {
                lo += 1;
            }
            let mut rgb: Option<RgbImage> = None;
            for j in lo..times.len() {
                if times[j] - tolerance > t {
                    break;
                }
                let d = (t - times[j]).abs();
                if best[j].as_ref().is_none_or(|(bd, _)| d < *bd) {
                    let img = match &rgb {
                        Some(img) => img.clone(),
                        None => rgb.insert(to_rgb.convert(f).with_context(|| format!("converting the frame at {t:.4} s to RGB"))?).clone(),
                    };
                    best[j] = Some((d, img));
                }
            }
            Ok(t <= last + tolerance)
        })?;
        Ok(best.into_iter().map(|b| b.map(|(_, img)| img)).collect())
    }

    struct ToRgb {
        scaler: Option<scaling::Context>,
        rgb: frame::Video,
    }

    impl Default for ToRgb {
        fn default() -> Self {
            Self { scaler: None, rgb: frame::Video::empty() }
        }
    }

    impl ToRgb {
        fn convert(&mut self, frame: &frame::Video) -> Result<RgbImage> {
            let (w, h, format) = (frame.width(), frame.height(), frame.format());
            let current = |s: &scaling::Context| {
                let i = s.input();
                (i.format, i.width, i.height) == (format, w, h)
            };
            let scaler = match &mut self.scaler {
                Some(s) if current(s) => s,
                slot => {
                    let flags = Flags::BILINEAR | Flags::ACCURATE_RND | Flags::FULL_CHR_H_INT;
                    let mut s = scaling::Context::get(format, w, h, Pixel::RGB24, w, h, flags)
                        .with_context(|| format!("no conversion from {format:?} {w}x{h} to RGB"))?;
                    use_frame_matrix(&mut s, frame);
                    self.rgb = frame::Video::empty();
                    slot.insert(s)
                }
            };
            scaler.run(frame, &mut self.rgb)?;
            let (stride, row) = (self.rgb.stride(0), w as usize * 3);
            let data = self.rgb.data(0);
            let mut pixels = Vec::with_capacity(row * h as usize);
            for y in 0..h as usize {
                pixels.extend_from_slice(&data[y * stride..y * stride + row]);
            }
            RgbImage::from_raw(w, h, pixels).context("RGB buffer size mismatch")
        }
    }

    /// Converts with the YUV matrix and range the frame is tagged with (as FFmpeg's `scale`
    /// filter does), rather than swscale's default of BT.601 limited range.
    fn use_frame_matrix(scaler: &mut scaling::Context, frame: &frame::Video) {
        let full_range = frame.color_range() == color::Range::JPEG
            || matches!(frame.format(), Pixel::YUVJ420P | Pixel::YUVJ422P | Pixel::YUVJ444P | Pixel::YUVJ440P);
        let space = ff::ffi::AVColorSpace::from(frame.color_space()) as i32;
        // SAFETY: the context is a valid, initialized swscale context owned by `scaler`;
        // sws_getCoefficients returns a pointer to a static table for any input.
        unsafe {
            let table = ff::ffi::sws_getCoefficients(space);
            let (mut inv, mut src_range, mut tab, mut dst_range) = (std::ptr::null_mut(), 0, std::ptr::null_mut(), 0);
            let (mut brightness, mut contrast, mut saturation) = (0, 0, 0);
            let ctx = scaler.as_mut_ptr();
            if ff::ffi::sws_getColorspaceDetails(
                ctx,
                &mut inv,
                &mut src_range,
                &mut tab,
                &mut dst_range,
                &mut brightness,
                &mut contrast,
                &mut saturation,
            ) < 0
            {
                return;
            }
            ff::ffi::sws_setColorspaceDetails(ctx, table, full_range as i32, tab, dst_range, brightness, contrast, saturation);
        }
    }

    pub fn write_mp4(tmp: &Path, frames: &[RgbImage], fps: f64, which: Mp4Encoder) -> Result<()> {
        init()?;
        let codec = encoder::find_by_name(which.ffmpeg_name())
            .with_context(|| format!("this FFmpeg has no {} encoder", which.ffmpeg_name()))?;
        let (width, height) = frames[0].dimensions();
        // Terms within 16 bits: MPEG-4 part 2 cannot code a larger time base (29.97 -> 30000/1001).
        // SAFETY: av_d2q is a pure function of its arguments.
        let rate = Rational::from(unsafe { ff::ffi::av_d2q(fps, 65535) });
        ensure!(rate.numerator() > 0 && rate.denominator() > 0, "frame rate {fps} has no usable fraction");
        let time_base = rate.invert();

        let mut octx = format::output_as(tmp, "mp4").with_context(|| format!("creating {}", tmp.display()))?;
        let global_header = octx.format().flags().contains(format::Flags::GLOBAL_HEADER);
        let mut enc = codec::context::Context::new_with_codec(codec).encoder().video()?;
        enc.set_width(width);
        enc.set_height(height);
        enc.set_format(Pixel::YUV420P);
        enc.set_time_base(time_base);
        enc.set_frame_rate(Some(rate));
        // swscale's RGB -> YUV default is BT.601 limited range; say so in the stream.
        enc.set_color_range(color::Range::MPEG);
        // SAFETY: plain field write on the encoder context it owns (ffmpeg-next's
        // `set_colorspace` writes the wrong field).
        unsafe { (*enc.as_mut_ptr()).colorspace = ff::ffi::AVColorSpace::AVCOL_SPC_SMPTE170M };
        let mut flags = codec::Flags::empty();
        if global_header {
            flags |= codec::Flags::GLOBAL_HEADER;
        }
        let mut options = Dictionary::new();
        let quality = match which {
            Mp4Encoder::H264 => {
                options.set("preset", "medium");
                options.set("crf", "18");
                None
            }
            Mp4Encoder::Mpeg4 => {
                // Fixed quantizer 3 (FFmpeg's `-q:v 3`), applied per frame below.
                let lambda = 3 * ff::ffi::FF_QP2LAMBDA;
                flags |= codec::Flags::QSCALE;
                enc.set_global_quality(lambda);
                Some(lambda)
            }
        };
        enc.set_flags(flags);
        let mut enc = enc.open_with(options).with_context(|| format!("opening the {} encoder", which.ffmpeg_name()))?;

        let stream = {
            let mut ost = octx.add_stream(codec)?;
            ost.set_parameters(&enc);
            ost.set_time_base(time_base);
            ost.set_avg_frame_rate(rate);
            ost.index()
        };
        let mut muxer_options = Dictionary::new();
        muxer_options.set("movflags", "+faststart");
        octx.write_header_with(muxer_options).context("writing the mp4 header")?;
        let stream_time_base = octx.stream(stream).context("the output stream vanished")?.time_base();

        let mut scaler = scaling::Context::get(
            Pixel::RGB24,
            width,
            height,
            Pixel::YUV420P,
            width,
            height,
            Flags::BILINEAR | Flags::ACCURATE_RND,
        )?;
        let mut rgb = frame::Video::new(Pixel::RGB24, width, height);
        let row = width as usize * 3;
        for (i, img) in frames.iter().enumerate() {
            let stride = rgb.stride(0);
            let data = rgb.data_mut(0);
            for (y, src) in img.as_raw().chunks_exact(row).enumerate() {
                data[y * stride..y * stride + row].copy_from_slice(src);
            }
            // A fresh frame each time: the encoder may keep a reference to the previous one.
            let mut yuv = frame::Video::empty();
            scaler.run(&rgb, &mut yuv)?;
            yuv.set_pts(Some(i as i64));
            if let Some(lambda) = quality {
                // SAFETY: plain field write on a frame we own.
                unsafe { (*yuv.as_mut_ptr()).quality = lambda };
            }
            enc.send_frame(&yuv).with_context(|| format!("encoding frame {i}"))?;
            write_packets(&mut enc, &mut octx, stream, time_base, stream_time_base)?;
        }
        enc.send_eof()?;
        write_packets(&mut enc, &mut octx, stream, time_base, stream_time_base)?;
        octx.write_trailer().context("writing the mp4 trailer")?;
        Ok(())
    }

    fn write_packets(
        enc: &mut encoder::Video,
        octx: &mut format::context::Output,
        stream: usize,
        from: Rational,
        to: Rational,
    ) -> Result<()> {
        let mut packet = Packet::empty();
        loop {
            match enc.receive_packet(&mut packet) {
                Ok(()) => {}
                Err(e) if is_drained(&e) => return Ok(()),
                Err(e) => return Err(e).context("encoding"),
            }
            packet.set_stream(stream);
            packet.rescale_ts(from, to);
            packet.write_interleaved(octx).context("writing a packet")?;
        }
    }
}

#[cfg(test)]
mod durability_tests {
    use super::*;
    use crate::fsync_log::synced_in;

    #[test]
    fn a_written_video_or_sheet_is_synced_under_its_temporary_name_then_its_folder() {
        let dir = bwm_testdir::TestDir::new("video-sync");
        let dir = dir.canonicalize().unwrap();
        let frames = vec![RgbImage::from_pixel(16, 16, image::Rgb([200, 30, 30])); 2];
        let written = write_mp4_or_sheet(&dir.join("clip.mp4"), &frames, 10.0, 2).unwrap();
        assert!(written.is_file());
        let synced = synced_in(&dir);
        let file = synced.iter().position(|p| p.parent() == Some(dir.as_path()) && p != &written);
        let folder = synced.iter().rposition(|p| p == &dir);
        assert!(file.is_some() && folder.is_some() && file < folder, "fsyncs in {}: {synced:?}", dir.display());
        let left: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(left.len(), 1, "only the video is left: {left:?}");
    }
}
