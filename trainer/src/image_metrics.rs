//! PSNR and SSIM of videos in [-1, 1].

use tch::{Kind, Tensor};

/// PSNR in dB over all pixels of `a` and `b` ([.., H, W] in [-1, 1], data range 2).
pub fn psnr(a: &Tensor, b: &Tensor) -> f64 {
    let mse = (a.to_kind(Kind::Float) - b.to_kind(Kind::Float)).square().mean(Kind::Double).double_value(&[]);
    // `f64::max` would turn a NaN error into the 120 dB of a perfect match.
    if mse.is_nan() {
        return f64::NAN;
    }
    10.0 * (4.0 / mse.max(1e-12)).log10()
}

/// Mean SSIM (Gaussian window 11, sigma 1.5, as Wang et al. 2004) of videos [3, F, H, W] in
/// [-1, 1], computed per frame on each channel and averaged.
pub fn ssim(a: &Tensor, b: &Tensor) -> f64 {
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
    let map = ((&mx * &my * 2.0 + c1) * (sxy * 2.0 + c2)) / ((mx.square() + my.square() + c1) * (sxx + syy + c2));
    map.mean(Kind::Double).double_value(&[])
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let noisier = &a + draw(0.6, Tensor::randn);
        let (s1, s2) = (ssim(&a, &noisy), ssim(&a, &noisier));
        assert!(s1 < 0.97 && s2 < s1 - 0.1, "{s1} {s2}");
    }
}
