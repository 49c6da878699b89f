//! PSNR and SSIM of videos in [-1, 1].

use tch::{Kind, Tensor};

/// PSNR in dB over all pixels of `a` and `b` ([.., H, W] in [-1, 1], data range 2).
pub fn psnr(a: &Tensor, b: &Tensor) -> f64 {
    let mse = (a.to_kind(Kind::Float) - b.to_kind(Kind::Float)).square().mean(Kind::Double).double_value(&[]);
    db(mse)
}

/// PSNR in dB of each frame of videos [3, F, H, W] in [-1, 1] (data range 2), in one pass.
pub fn psnr_frames(a: &Tensor, b: &Tensor) -> Result<Vec<f64>, tch::TchError> {
    let frames = a.size()[1];
    let mse = (a.to_kind(Kind::Float) - b.to_kind(Kind::Float)).square().transpose(0, 1).reshape([frames, -1]).mean_dim(1, false, Kind::Double);
    Ok(Vec::<f64>::try_from(mse.to_device(tch::Device::Cpu))?.into_iter().map(db).collect())
}

fn db(mse: f64) -> f64 {
    // `f64::max` would turn a NaN error into the 120 dB of a perfect match.
    if mse.is_nan() {
        return f64::NAN;
    }
    10.0 * (4.0 / mse.max(1e-12)).log10()
}

/// Mean SSIM (Gaussian window 11, sigma 1.5, as Wang et al. 2004) of videos [3, F, H, W] in
/// [-1, 1], computed per frame on each channel and averaged: on the frames mapped to [0, 1] (data
/// range 1: C1 = 0.01^2, C2 = 0.03^2), with population variances, over the pixels whose window
/// lies inside the frame. Scikit-image's `structural_similarity(gaussian_weights=True,
/// sigma=1.5, use_sample_covariance=False, data_range=1)` on those frames gives the same (tested).
pub fn ssim(a: &Tensor, b: &Tensor) -> f64 {
    ssim_map(a, b).mean(Kind::Double).double_value(&[])
}

/// `ssim` of each frame of videos [3, F, H, W] (the mean over its channels), in one pass; their
/// mean is `ssim`.
pub fn ssim_frames(a: &Tensor, b: &Tensor) -> Result<Vec<f64>, tch::TchError> {
    let frames = a.size()[1];
    let per_frame = ssim_map(a, b).reshape([frames, -1]).mean_dim(1, false, Kind::Double);
    Vec::<f64>::try_from(per_frame.to_device(tch::Device::Cpu))
}

/// The SSIM map of every frame and channel, frame-major ([F * 3, 1, H', W']).
fn ssim_map(a: &Tensor, b: &Tensor) -> Tensor {
    let to_images = |t: &Tensor| {
        let s = t.size();
        ((t.to_kind(Kind::Float) + 1.0) / 2.0).permute([1, 0, 2, 3]).reshape([s[1] * s[0], 1, s[2], s[3]])
    };
    let (x, y) = (to_images(a), to_images(b));
    let size = 11.min(x.size()[2]).min(x.size()[3]);
    let coords = Tensor::arange(size, (Kind::Float, x.device())) - (size - 1) as f64 / 2.0;
    let g = (-(coords.square()) / (2.0 * 1.5 * 1.5)).exp();
    let g = &g / g.sum(Kind::Float);
    let window = g.unsqueeze(1).matmul(&g.unsqueeze(0)).view([1, 1, size, size]);
    let blur = |t: &Tensor| t.conv2d(&window, None::<Tensor>, [1, 1], [0, 0], [1, 1], 1);
    let (mx, my) = (blur(&x), blur(&y));
    let sxx = blur(&(&x * &x)) - &mx * &mx;
    let syy = blur(&(&y * &y)) - &my * &my;
    let sxy = blur(&(&x * &y)) - &mx * &my;
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    ((&mx * &my * 2.0 + c1) * (sxy * 2.0 + c2)) / ((mx.square() + my.square() + c1) * (sxx + syy + c2))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// |ssim - scikit-image| allowed: f32 arithmetic (E[xy] - E[x]E[y] over windows of values in
    /// [0, 1]) against scikit-image's f64, measured up to 1.3e-6 on the pairs below. Scikit-image
    /// with a uniform window, sigma 1.4, data range 2 or sample covariances lies outside it (the
    /// test checks that too).
    const SKIMAGE_BOUND: f64 = 1e-5;

    #[test]
    fn identical_videos_are_perfect_and_noise_lowers_both() {
        // Under `with_seed`'s lock, so that these draws cannot land inside another test's seeded model.
        let draw = |scale: f64, f: fn([i64; 4], (Kind, tch::Device)) -> Tensor| bwm_model::vb::with_seed(1, || f([3, 2, 32, 32], (Kind::Float, tch::Device::Cpu))) * scale;
        let a = draw(2.0, Tensor::rand) - 1.0;
        assert!((ssim(&a, &a) - 1.0).abs() < 1e-6);
        assert!(psnr(&a, &a) > 100.0);
        let noisy = &a + draw(0.2, Tensor::randn);
        // Noise of std 0.2 on a range of 2: MSE 0.04 -> PSNR 10 log10(4 / 0.04) = 20 dB.
        assert!((psnr(&a, &noisy) - 20.0).abs() < 0.5);
        let broken = a.copy();
        let _ = broken.get(0).fill_(f64::NAN);
        assert!(psnr(&broken, &a).is_nan(), "a NaN frame is no match");
        // Per frame: each frame's own PSNR, in order.
        let half = Tensor::cat(&[a.narrow(1, 0, 1), noisy.narrow(1, 1, 1)], 1);
        let frames = psnr_frames(&half, &a).unwrap();
        assert!(frames[0] > 100.0 && (frames[1] - psnr(&noisy.narrow(1, 1, 1), &a.narrow(1, 1, 1))).abs() < 1e-9, "{frames:?}");
        let noisier = &a + draw(0.6, Tensor::randn);
        let (s1, s2) = (ssim(&a, &noisy), ssim(&a, &noisier));
        assert!(s1 < 0.97 && s2 < s1 - 0.1, "{s1} {s2}");
    }

    /// Scikit-image's `structural_similarity` (the virtualenv's; `bwm_testdir::python_with`) with
    /// the settings documented above: images mapped to [0, 1] (data range 1), an 11-wide Gaussian
    /// window of sigma 1.5, population (not sample) covariances, the mean over the pixels whose
    /// window lies inside the image, each channel and frame apart; scikit-image computes in f64,
    /// `ssim` in f32. Pairs of noise, blur, a contrast and brightness change and unrelated images.
    #[test]
    fn ssim_matches_scikit_image() {
        let Some(py) = bwm_testdir::python_with(bwm_testdir::Dep::Python, &["skimage", "numpy", "safetensors"]) else { return };
        let dir = bwm_testdir::TestDir::new("ssim-skimage");
        let (a, unrelated, noise) = bwm_model::vb::with_seed(4, || {
            let draw = |shape: [i64; 4]| Tensor::rand(shape, (Kind::Float, tch::Device::Cpu));
            // Smooth textures (upsampled noise) with fine detail, in [-1, 1]; 40 x 56, not square.
            let texture = |t: Tensor| t.upsample_bilinear2d([40, 56], false, None, None) * 1.6 + draw([3, 2, 40, 56]) * 0.4 - 1.0;
            (texture(draw([3, 2, 10, 14])), texture(draw([3, 2, 10, 14])), Tensor::randn([3, 2, 40, 56], (Kind::Float, tch::Device::Cpu)))
        });
        let blurred = a.view([6, 1, 40, 56]).avg_pool2d([3, 3], [1, 1], [1, 1], false, true, None::<i64>).view([3, 2, 40, 56]);
        let pairs = [
            ("noise", (&a + &noise * 0.1).clamp(-1.0, 1.0)),
            ("blur", blurred),
            ("contrast and brightness", &a * 0.7 + 0.2),
            ("unrelated", unrelated),
        ];
        let mut tensors = vec![("a".to_string(), a.shallow_clone())];
        tensors.extend(pairs.iter().enumerate().map(|(i, (_, b))| (format!("b{i}"), b.shallow_clone())));
        let file = dir.join("pairs.safetensors");
        Tensor::write_safetensors(&tensors, &file).unwrap();
        // Each pair under the settings above ("match") and under one setting changed: the bound
        // must tell those apart.
        let script = r#"
import json, sys
import numpy as np
from safetensors.numpy import load_file
from skimage.metrics import structural_similarity
t = load_file(sys.argv[1])
a = (t["a"].astype(np.float64) + 1) / 2
settings = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0)
variants = {"match": {}, "uniform window": dict(gaussian_weights=False, win_size=11), "sigma 1.4": dict(sigma=1.4),
            "data range 2": dict(data_range=2.0), "sample covariances": dict(use_sample_covariance=True)}
out = {}
for name, changed in variants.items():
    out[name] = []
    for i in range(int(sys.argv[2])):
        b = (t[f"b{i}"].astype(np.float64) + 1) / 2
        frames = [structural_similarity(a[:, f], b[:, f], channel_axis=0, **{**settings, **changed}) for f in range(a.shape[1])]
        out[name].append(float(np.mean(frames)))
        if not changed:
            out.setdefault("match per frame", []).append(frames)
print(json.dumps(out))
"#;
        let out = std::process::Command::new(py).args(["-c", script]).arg(&file).arg(pairs.len().to_string()).output().unwrap();
        assert!(out.status.success(), "scikit-image failed: {}", String::from_utf8_lossy(&out.stderr));
        let mut theirs: std::collections::BTreeMap<String, serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap();
        let per_frame: Vec<Vec<f64>> = serde_json::from_value(theirs.remove("match per frame").unwrap()).unwrap();
        let theirs: std::collections::BTreeMap<String, Vec<f64>> = theirs.into_iter().map(|(k, v)| (k, serde_json::from_value(v).unwrap())).collect();
        for ((what, b), want) in pairs.iter().zip(&per_frame) {
            let got = ssim_frames(&a, b).unwrap();
            assert_eq!(got.len(), want.len());
            for (g, w) in got.iter().zip(want) {
                assert!((g - w).abs() <= SKIMAGE_BOUND, "{what}: a frame's ssim {g}, scikit-image {w}");
            }
        }
        let ours: Vec<f64> = pairs.iter().map(|(_, b)| ssim(&a, b)).collect();
        for (((what, _), got), want) in pairs.iter().zip(&ours).zip(&theirs["match"]) {
            println!("{what}: ssim {got:.7}, scikit-image {want:.7}, difference {:.2e}", (got - want).abs());
            assert!((got - want).abs() <= SKIMAGE_BOUND, "{what}: ssim {got}, scikit-image {want}");
        }
        for (variant, values) in theirs.iter().filter(|(name, _)| *name != "match") {
            let apart = ours.iter().zip(values).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            println!("scikit-image with {variant}: up to {apart:.2e} from ssim");
            assert!(apart > 2.0 * SKIMAGE_BOUND, "scikit-image with {variant} is within {apart:e} of ssim: the bound cannot tell it apart");
        }
    }
}
