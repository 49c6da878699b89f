//! A linear layer trained in FP8: `linear(x, w, b)` is x W^T + b whose forward product and both
//! backward products (the gradients of x and of W) run through libtorch's `_scaled_mm` in float8,
//! as torchao's float8 "tensorwise" training recipe does: x and W in e4m3, the incoming gradient in
//! e5m2, each scaled from its own absolute maximum on every call. The weights themselves (and any
//! fp32 masters and optimizer state the trainer keeps) are untouched; only the products are FP8.
//! libtorch's autograd cannot be given a custom backward from tch, so the function is C++
//! (src/fp8_linear.cpp); each quantization (the scale, the cast, the transposed copy the backward
//! products need) is one pass of `bwm_fused_ops::fp8_quantize_pass`.

use std::ffi::{c_char, CStr};
use std::sync::Once;

use anyhow::{bail, ensure, Result};
use tch::Tensor;
use torch_sys::C_tensor;

extern "C" {
    fn bwm_fp8_set_quantize_pass(pass: bwm_fused_ops::Fp8QuantizePass);
    fn bwm_fp8_linear(x: *const C_tensor, w: *const C_tensor, b: *const C_tensor, out: *mut *mut C_tensor) -> *const c_char;
}

/// Whether `linear` takes this weight [out, in] and bias [out]: both weight dimensions multiples
/// of 16 (CUDA's FP8 matmuls).
pub fn check_weight(w: &Tensor, b: &Tensor) -> Result<()> {
    let ws = w.size();
    ensure!(ws.len() == 2, "an FP8 linear's weight must be [out, in], got {ws:?}");
    ensure!(ws[0] % 16 == 0 && ws[1] % 16 == 0, "FP8 matmuls need both weight dimensions to be multiples of 16, got {ws:?}");
    ensure!(b.size() == [ws[0]], "the bias must be [{}], got {:?}", ws[0], b.size());
    Ok(())
}

/// x [..., in] -> x W^T + b [..., out] in x's dtype, differentiable in x, W and b. W [out, in]
/// needs both dimensions multiples of 16 (CUDA's FP8 matmuls); x's rows may be any number.
pub fn linear(x: &Tensor, w: &Tensor, b: &Tensor) -> Result<Tensor> {
    check_weight(w, b)?;
    let ws = w.size();
    let shape = x.size();
    ensure!(shape.last() == Some(&ws[1]), "the input's last dimension must be {}, got {shape:?}", ws[1]);
    let x2 = x.reshape([-1, ws[1]]);
    static SET: Once = Once::new();
    // SAFETY: hands the C++ side a function of the signature it declares.
    SET.call_once(|| unsafe { bwm_fp8_set_quantize_pass(bwm_fused_ops::fp8_quantize_pass) });
    let mut out: *mut C_tensor = std::ptr::null_mut();
    // SAFETY: the pointers are live tch tensors (at::Tensor*), and `out` receives a new
    // at::Tensor* that `Tensor::from_ptr` takes ownership of.
    let err = unsafe { bwm_fp8_linear(x2.as_ptr(), w.as_ptr(), b.as_ptr(), &mut out) };
    if !err.is_null() {
        bail!("FP8 linear: {}", unsafe { CStr::from_ptr(err) }.to_string_lossy());
    }
    let y = unsafe { Tensor::from_ptr(out) };
    let mut out_shape = shape[..shape.len() - 1].to_vec();
    out_shape.push(ws[0]);
    Ok(y.view(out_shape.as_slice()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    fn rel_err(a: &Tensor, b: &Tensor) -> f64 {
        let (a, b) = (a.to_kind(Kind::Float), b.to_kind(Kind::Float));
        (&a - &b).norm().double_value(&[]) / b.norm().double_value(&[])
    }

    /// Forward and both gradients against the same products in fp32, for fp32 and bf16 inputs:
    /// FP8's 3 (e4m3) and 2 (e5m2) mantissa bits leave a few percent of relative error, not more.
    #[test]
    fn the_products_and_gradients_follow_fp32() {
        follow_fp32(Device::Cpu);
    }

    /// The same on a CUDA device (the quantization kernel and CUDA's FP8 matmuls), and its
    /// results next to the CPU's: the same float8 operands, products summed in another order.
    #[test]
    #[ignore = "needs a CUDA device"]
    fn the_products_and_gradients_follow_fp32_and_the_cpu_on_cuda() {
        let device = Device::Cuda(0);
        let gpu = follow_fp32(device);
        let cpu = follow_fp32(Device::Cpu);
        for (kind, (g, c)) in [Kind::Float, Kind::BFloat16].into_iter().zip(gpu.iter().zip(&cpu)) {
            for (name, (a, b)) in ["y", "dx", "dW", "db"].into_iter().zip(g.iter().zip(c)) {
                let e = rel_err(&a.to_device(Device::Cpu), b);
                assert!(e < 0.01, "{kind:?} {name}: CUDA and CPU {e:.5} apart");
            }
        }
    }

    /// `the_products_and_gradients_follow_fp32` on `device`; each dtype's y and gradients.
    fn follow_fp32(device: Device) -> Vec<[Tensor; 4]> {
        let mut out = Vec::new();
        for kind in [Kind::Float, Kind::BFloat16] {
            tch::manual_seed(0);
            // 37 rows: not a multiple of 16, so the padding is exercised.
            let leaf = |t: Tensor| t.to_kind(kind).to_device(device).set_requires_grad(true);
            let x = leaf(Tensor::randn([37, 64], (Kind::Float, Device::Cpu)));
            let w = leaf(Tensor::randn([32, 64], (Kind::Float, Device::Cpu)) * 0.1);
            let b = leaf(Tensor::randn([32], (Kind::Float, Device::Cpu)));
            let up = Tensor::randn([37, 32], (Kind::Float, Device::Cpu)).to_device(device);

            let y = linear(&x, &w, &b).unwrap();
            assert_eq!((y.size(), y.kind()), (vec![37, 32], kind));
            (y.to_kind(Kind::Float) * &up).sum(Kind::Float).backward();
            let got = [y.detach(), x.grad().copy(), w.grad().copy(), b.grad().copy()];
            assert!(got[1..].iter().all(|g| g.kind() == kind), "gradients in the parameters' dtype");

            let leaf32 = |t: &Tensor| t.detach().to_kind(Kind::Float).set_requires_grad(true);
            let (x32, w32, b32) = (leaf32(&x), leaf32(&w), leaf32(&b));
            let reference = x32.linear(&w32, Some(&b32));
            (&reference * &up).sum(Kind::Float).backward();
            let want = [reference.detach(), x32.grad(), w32.grad(), b32.grad()];
            for ((name, tol), (g, r)) in [("y", 0.08), ("dx", 0.12), ("dW", 0.12), ("db", 0.01)].into_iter().zip(got.iter().zip(&want)) {
                let e = rel_err(g, r);
                assert!(e < tol, "{kind:?} {name}: relative error {e:.4} (tolerance {tol})");
            }
            // And not the same numbers: the products really went through float8.
            assert!(rel_err(&got[0], &want[0]) > 1e-3, "{kind:?}");
            out.push(got);
        }
        out
    }

    /// The casts to float8 do not saturate (a value past the format's largest becomes NaN), so the
    /// scale must keep every scaled value in range whatever the input's largest magnitude.
    #[test]
    fn no_scale_sends_a_value_past_the_format() {
        let w = (Tensor::randn([16, 32], (Kind::Float, Device::Cpu)) * 0.1).to_kind(Kind::BFloat16).set_requires_grad(true);
        let b = Tensor::zeros([16], (Kind::BFloat16, Device::Cpu));
        for k in 0..200 {
            let magnitude = 10f64.powf(-4.0 + 8.0 * k as f64 / 199.0);
            let x = (Tensor::randn([5, 32], (Kind::Float, Device::Cpu)) * magnitude).to_kind(Kind::BFloat16).set_requires_grad(true);
            let y = linear(&x, &w, &b).unwrap();
            (y.to_kind(Kind::Float) * magnitude.recip()).sum(Kind::Float).backward();
            for (name, t) in [("y", y.detach()), ("dx", x.grad()), ("dW", w.grad())] {
                assert!(t.isfinite().all().int64_value(&[]) == 1, "{name} not finite at input magnitude {magnitude:e}");
            }
            let _ = w.grad().zero_();
        }
    }

    /// Products of one input with several weights (q, k and v) share its quantization; a write
    /// to the input between them, or other values at the same place, is not served the old one.
    #[test]
    fn an_input_read_again_is_quantized_again_only_when_it_changed() {
        tch::manual_seed(3);
        let kind = Kind::BFloat16;
        let mut x = Tensor::randn([2, 37, 64], (Kind::Float, Device::Cpu)).to_kind(kind);
        let ws: Vec<Tensor> = (0..3).map(|_| (Tensor::randn([32, 64], (Kind::Float, Device::Cpu)) * 0.1).to_kind(kind)).collect();
        let b = Tensor::zeros([32], (kind, Device::Cpu));
        // Each against the same product from a copy of x (its own storage: quantized on its own).
        for w in &ws {
            let shared = linear(&x, w, &b).unwrap();
            let alone = linear(&x.copy(), w, &b).unwrap();
            assert!(shared.equal(&alone), "a product of the shared quantization differs");
        }
        let before = linear(&x, &ws[0], &b).unwrap();
        let _ = tch::no_grad(|| x.g_mul_scalar_(4.0));
        let after = linear(&x, &ws[0], &b).unwrap();
        assert!(after.equal(&linear(&x.copy(), &ws[0], &b).unwrap()), "the input written in place was served its old quantization");
        assert!(rel_err(&after, &(&before * 4.0)) < 0.01);
        // A view of other values at the same address (a narrower shape) is not the same input.
        let rows = x.view([-1, 64]);
        let part = rows.narrow(0, 0, 10);
        let _ = linear(&rows, &ws[1], &b).unwrap();
        assert!(linear(&part, &ws[1], &b).unwrap().equal(&linear(&part.copy(), &ws[1], &b).unwrap()));
    }

    #[test]
    fn leading_dimensions_are_kept_and_bad_shapes_refused() {
        let x = Tensor::randn([2, 3, 32], (Kind::Float, Device::Cpu));
        let w = Tensor::randn([16, 32], (Kind::Float, Device::Cpu));
        let b = Tensor::zeros([16], (Kind::Float, Device::Cpu));
        assert_eq!(linear(&x, &w, &b).unwrap().size(), [2, 3, 16]);
        let e = linear(&x, &Tensor::randn([16, 24], (Kind::Float, Device::Cpu)), &b).unwrap_err().to_string();
        assert!(e.contains("multiples of 16"), "{e}");
        let e = linear(&Tensor::randn([2, 16], (Kind::Float, Device::Cpu)), &w, &b).unwrap_err().to_string();
        assert!(e.contains("last dimension must be 32"), "{e}");
    }
}
