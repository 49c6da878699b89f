//! RGB frame helpers: resizing to the model's size, frames <-> tensors, and composing views and
//! comparison images.

use anyhow::{bail, ensure, Context, Result};
use image::imageops::{self, FilterType};
use image::RgbImage;
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

/// How `fit` maps an image onto a target size of another aspect ratio.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", deny_unknown_fields)]
pub enum ResizeMode {
    /// Scale to cover the target, then cut the centre out (what BWM does).
    #[default]
    Crop,
    /// Scale to fit inside the target, then centre on black.
    Pad,
    /// Scale each axis independently.
    Stretch,
}

/// Triangle (bilinear, widened when shrinking): PIL's `BILINEAR`, which the reference pipelines use.
const FILTER: FilterType = FilterType::Triangle;

/// Resizes `img` to exactly `width` x `height`. An empty source or target gives a black image of
/// the target size.
pub fn fit(img: &RgbImage, width: u32, height: u32, mode: ResizeMode) -> RgbImage {
    let (w, h) = img.dimensions();
    if w == 0 || h == 0 || width == 0 || height == 0 {
        return RgbImage::new(width, height);
    }
    if (w, h) == (width, height) {
        return img.clone();
    }
    let scaled = |scale: f64| {
        let sw = ((w as f64 * scale).round() as u32).max(1);
        let sh = ((h as f64 * scale).round() as u32).max(1);
        (sw, sh)
    };
    let (sx, sy) = (width as f64 / w as f64, height as f64 / h as f64);
    match mode {
        ResizeMode::Stretch => imageops::resize(img, width, height, FILTER),
        ResizeMode::Crop => {
            let (sw, sh) = scaled(sx.max(sy));
            let (sw, sh) = (sw.max(width), sh.max(height));
            let resized = imageops::resize(img, sw, sh, FILTER);
            imageops::crop_imm(&resized, (sw - width) / 2, (sh - height) / 2, width, height).to_image()
        }
        ResizeMode::Pad => {
            let (sw, sh) = scaled(sx.min(sy));
            let (sw, sh) = (sw.min(width), sh.min(height));
            let resized = imageops::resize(img, sw, sh, FILTER);
            let mut canvas = RgbImage::new(width, height);
            imageops::replace(&mut canvas, &resized, ((width - sw) / 2).into(), ((height - sh) / 2).into());
            canvas
        }
    }
}

/// Frames of one size as a [3, F, H, W] f32 tensor on the CPU, pixels mapped to [-1, 1]
/// (x / 127.5 - 1).
pub fn frames_to_tensor(frames: &[RgbImage]) -> Result<Tensor> {
    let Some(first) = frames.first() else { bail!("no frames to convert to a tensor") };
    let (w, h) = first.dimensions();
    ensure!(w > 0 && h > 0, "frames are empty ({w}x{h})");
    if let Some((i, f)) = frames.iter().enumerate().find(|(_, f)| f.dimensions() != (w, h)) {
        bail!("frame {i} is {}x{}, frame 0 is {w}x{h}", f.width(), f.height());
    }
    let mut bytes = Vec::with_capacity(frames.len() * (w * h * 3) as usize);
    for f in frames {
        bytes.extend_from_slice(f.as_raw());
    }
    let t = Tensor::from_slice(&bytes).view([frames.len() as i64, h as i64, w as i64, 3]);
    Ok((t.permute([3, 0, 1, 2]).to_kind(Kind::Float) / 127.5 - 1.0).contiguous())
}

/// Pixels in [-1, 1] (any shape, values outside clamped) as u8 0..255, rounded.
pub fn unit_to_u8(t: &Tensor) -> Tensor {
    ((t.clamp(-1.0, 1.0) + 1.0) * 127.5).round().to_kind(Kind::Uint8)
}

/// The inverse of `frames_to_tensor` for [3, F, H, W] or [1, 3, F, H, W] (any float kind and
/// device): values are clamped to [-1, 1] and rounded to the nearest 8-bit level.
pub fn tensor_to_frames(t: &Tensor) -> Result<Vec<RgbImage>> {
    let size = t.size();
    let (c, f, h, w) = match size.as_slice() {
        &[c, f, h, w] | &[1, c, f, h, w] => (c, f, h, w),
        _ => bail!("expected a [3, F, H, W] or [1, 3, F, H, W] tensor, got {size:?}"),
    };
    ensure!(c == 3, "expected 3 colour channels, got shape {size:?}");
    ensure!(t.is_floating_point(), "expected a floating-point tensor, got {:?}", t.kind());
    let t = t.to_device(Device::Cpu).to_kind(Kind::Float).view([3, f, h, w]);
    ensure!(!bool::try_from(t.isnan().any())?, "tensor of shape {size:?} holds NaN");
    let bytes = unit_to_u8(&t).permute([1, 2, 3, 0]).contiguous();
    let bytes = Vec::<u8>::try_from(bytes.view([-1])).context("copying frame bytes out of the tensor")?;
    let (w, h) = (u32::try_from(w)?, u32::try_from(h)?);
    let frame_len = (w * h * 3) as usize;
    if frame_len == 0 {
        return Ok((0..f).map(|_| RgbImage::new(w, h)).collect());
    }
    bytes
        .chunks_exact(frame_len)
        .map(|chunk| RgbImage::from_raw(w, h, chunk.to_vec()).context("frame buffer size mismatch"))
        .collect()
}

/// Camera views of one width stacked top to bottom, in order (BWM's multi-view layout).
pub fn stack_views_vertically(views: &[RgbImage]) -> Result<RgbImage> {
    let Some(first) = views.first() else { bail!("no views to stack") };
    let width = first.width();
    if let Some((i, v)) = views.iter().enumerate().find(|(_, v)| v.width() != width) {
        bail!("view {i} is {} wide, view 0 is {width}", v.width());
    }
    let height = views.iter().try_fold(0u32, |acc, v| acc.checked_add(v.height())).context("stacked height overflows")?;
    let mut pixels = Vec::with_capacity(width as usize * height as usize * 3);
    for v in views {
        pixels.extend_from_slice(v.as_raw());
    }
    RgbImage::from_raw(width, height, pixels).context("stacked buffer size mismatch")
}

/// Swaps the red and blue channels in place: RoboTwin's JPEGs were written from RGB arrays by
/// OpenCV, which takes them as BGR, so a standard JPEG decoder returns R and B exchanged.
pub fn swap_red_blue(img: &mut RgbImage) {
    for p in img.pixels_mut() {
        p.0.swap(0, 2);
    }
}

/// A grid of frames of one size: row r holds `rows[r]` side by side, left to right. Rows may
/// differ in length; the missing cells stay black.
pub fn frame_strip(rows: &[Vec<RgbImage>]) -> Result<RgbImage> {
    let Some(first) = rows.iter().flatten().next() else { bail!("no frames for the strip") };
    let (w, h) = first.dimensions();
    for (r, row) in rows.iter().enumerate() {
        if let Some((c, f)) = row.iter().enumerate().find(|(_, f)| f.dimensions() != (w, h)) {
            bail!("frame {c} of row {r} is {}x{}, the first frame is {w}x{h}", f.width(), f.height());
        }
    }
    let cols = rows.iter().map(Vec::len).max().unwrap_or(0);
    let (width, height) = (
        u32::try_from(cols).ok().and_then(|n| w.checked_mul(n)).context("strip width overflows")?,
        u32::try_from(rows.len()).ok().and_then(|n| h.checked_mul(n)).context("strip height overflows")?,
    );
    let mut canvas = RgbImage::new(width, height);
    for (r, row) in rows.iter().enumerate() {
        for (c, f) in row.iter().enumerate() {
            imageops::replace(&mut canvas, f, (c as u32 * w).into(), (r as u32 * h).into());
        }
    }
    Ok(canvas)
}

/// A `--resize` value: crop, pad or stretch.
pub fn parse_resize(s: &str) -> Result<ResizeMode, String> {
    match s {
        "crop" => Ok(ResizeMode::Crop),
        "pad" => Ok(ResizeMode::Pad),
        "stretch" => Ok(ResizeMode::Stretch),
        _ => Err(format!("'{s}': expected crop, pad or stretch")),
    }
}

/// `WIDTHxHEIGHT` with both multiples of `multiple`.
pub fn parse_resolution(s: &str, multiple: u32) -> Result<(u32, u32)> {
    let (w, h) = s.split_once('x').with_context(|| format!("resolution '{s}': expected WIDTHxHEIGHT"))?;
    let number = |v: &str| v.trim().parse::<u32>().with_context(|| format!("resolution '{s}': '{v}' is not a whole number"));
    let (w, h) = (number(w)?, number(h)?);
    ensure!(w > 0 && h > 0 && w % multiple == 0 && h % multiple == 0, "resolution {w}x{h}: width and height must be positive multiples of {multiple}");
    Ok((w, h))
}
