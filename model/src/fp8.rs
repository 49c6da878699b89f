//! FP8 linear layers for inference: a weight quantized once to float8 e4m3 with its scale, the
//! activations scaled on each call from their own absolute maximum (dynamic scaling, as torchao's
//! float8 recipe does), the product by `_scaled_mm` with the bias added in the output dtype. Two
//! granularities: one scale per tensor (any device) or one per row of the activations and per
//! output channel of the weight (CUDA only: libtorch's CPU `_scaled_mm` takes per-tensor scales).

use anyhow::{bail, ensure, Result};
use tch::{Kind, Tensor};

/// The largest finite float8 e4m3fn value.
pub const E4M3_MAX: f64 = 448.0;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fp8Scaling {
    /// One scale for the whole weight, one for the whole activation.
    Tensor,
    /// One per output channel of the weight and one per token of the activation (CUDA).
    Row,
}

impl std::str::FromStr for Fp8Scaling {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "tensor" => Ok(Self::Tensor),
            "row" => Ok(Self::Row),
            _ => Err(format!("'{s}': expected tensor or row")),
        }
    }
}

impl std::fmt::Display for Fp8Scaling {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Tensor => "tensor",
            Self::Row => "row",
        })
    }
}

/// A weight [out, in] in float8 e4m3 with its scale: weight ≈ quantized * scale.
pub struct Fp8Weight {
    quantized: Tensor,
    /// f32: [] (Tensor) or [1, out] (Row), the layout `_scaled_mm` takes for its second operand.
    scale: Tensor,
    scaling: Fp8Scaling,
}

/// `t` / scale in e4m3 and the f32 scale, from the absolute maximum over `dims` (all when empty).
/// The element-wise work stays in `t`'s dtype (bf16 activations: half the memory traffic of f32;
/// either holds e4m3's 3 mantissa bits): the multiplier is rounded to that dtype first and the
/// scale is its exact inverse, and the clamp keeps a product rounded past 448 from becoming NaN
/// (the e4m3fn cast does not saturate).
fn quantize(t: &Tensor, dims: &[i64]) -> (Tensor, Tensor) {
    let amax = if dims.is_empty() { t.abs().max() } else { t.abs().amax(dims, true) }.to_kind(Kind::Float);
    // An all-zero tensor or row gets a finite multiplier rather than a division by zero.
    let multiplier = (E4M3_MAX / amax.clamp_min(1e-12)).clamp_max(f32::MAX as f64).to_kind(t.kind());
    let scale = multiplier.to_kind(Kind::Float).reciprocal();
    ((t * &multiplier).clamp(-E4M3_MAX, E4M3_MAX).to_kind(Kind::Float8e4m3fn), scale)
}

impl Fp8Weight {
    /// Quantizes `weight` [out, in]. `_scaled_mm` on CUDA needs both dimensions to be multiples of 16.
    pub fn new(weight: &Tensor, scaling: Fp8Scaling) -> Result<Self> {
        let s = weight.size();
        ensure!(s.len() == 2, "an FP8 weight must be [out, in], got {s:?}");
        ensure!(s[0] % 16 == 0 && s[1] % 16 == 0, "FP8 matmuls need both weight dimensions to be multiples of 16, got {s:?}");
        if scaling == Fp8Scaling::Row && !weight.device().is_cuda() {
            bail!("row-wise FP8 scaling needs a CUDA device (libtorch's CPU _scaled_mm takes per-tensor scales only); use tensor");
        }
        let weight = weight.to_kind(Kind::Float);
        let (quantized, scale) = match scaling {
            Fp8Scaling::Tensor => quantize(&weight, &[]),
            Fp8Scaling::Row => {
                let (q, s) = quantize(&weight, &[1]);
                (q, s.view([1, -1]))
            }
        };
        Ok(Self { quantized, scale, scaling })
    }

    /// x [..., in] -> x W^T + bias [..., out] in `out_kind`.
    pub fn linear(&self, x: &Tensor, bias: &Tensor, out_kind: Kind) -> Tensor {
        let shape = x.size();
        let (k, n) = (self.quantized.size()[1], self.quantized.size()[0]);
        let x2 = x.reshape([-1, k]);
        let (xq, x_scale) = match self.scaling {
            Fp8Scaling::Tensor => quantize(&x2, &[]),
            Fp8Scaling::Row => quantize(&x2, &[1]),
        };
        let y = xq.internal_scaled_mm(&self.quantized.tr(), &x_scale, &self.scale, None::<Tensor>, None::<Tensor>, out_kind, true);
        let mut out_shape = shape[..shape.len() - 1].to_vec();
        out_shape.push(n);
        (y + bias.to_kind(out_kind)).view(out_shape.as_slice())
    }

    /// The weight this stands for, dequantized (for tests and error reports).
    pub fn dequantized(&self) -> Tensor {
        match self.scaling {
            Fp8Scaling::Tensor => self.quantized.to_kind(Kind::Float) * &self.scale,
            Fp8Scaling::Row => self.quantized.to_kind(Kind::Float) * self.scale.view([-1, 1]),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    fn draw(shape: &[i64], key: u64) -> Tensor {
        crate::keyed_rng::normal(shape, 21, key, crate::keyed_rng::Purpose::Augment)
    }

    #[test]
    fn a_per_tensor_fp8_linear_is_close_to_the_exact_one() {
        let (w, b, x) = (draw(&[48, 64], 0) * 0.1, draw(&[48], 1), draw(&[2, 5, 64], 2));
        let f = Fp8Weight::new(&w, Fp8Scaling::Tensor).unwrap();
        // e4m3 keeps 3 mantissa bits: each weight within 1/16 of itself, relative.
        let rel = ((f.dequantized() - &w).abs() / (w.abs() + 1e-3)).max().double_value(&[]);
        assert!(rel <= 0.0626, "weight rounding {rel}");
        let exact = x.linear(&w, Some(&b));
        let got = f.linear(&x, &b, Kind::Float);
        assert_eq!(got.size(), [2, 5, 48]);
        let err = ((&got - &exact).norm() / exact.norm()).double_value(&[]);
        assert!(err < 0.05, "relative error {err}");
        assert!(err > 1e-5, "the product went through FP8 (error {err}), not the exact path");
    }

    #[test]
    fn bf16_activations_are_scaled_in_bf16_with_a_consistent_scale() {
        let (w, b, x) = (draw(&[32, 48], 5) * 0.1, draw(&[32], 6), draw(&[7, 48], 7) * 30.0);
        let f = Fp8Weight::new(&w, Fp8Scaling::Tensor).unwrap();
        let exact = x.linear(&w, Some(&b));
        let got = f.linear(&x.to_kind(Kind::BFloat16), &b, Kind::BFloat16);
        assert_eq!(got.kind(), Kind::BFloat16);
        let err = ((got.to_kind(Kind::Float) - &exact).norm() / exact.norm()).double_value(&[]);
        assert!(err < 0.05, "relative error {err}");
        // The largest activation lands on e4m3's largest value, not past it (a NaN).
        let (q, scale) = quantize(&x.to_kind(Kind::BFloat16), &[]);
        let q = q.to_kind(Kind::Float);
        assert!(bool::try_from(q.isfinite().all()).unwrap());
        assert!(q.abs().max().double_value(&[]) <= E4M3_MAX);
        let back = ((&q * &scale) - x.to_kind(Kind::BFloat16).to_kind(Kind::Float)).abs().max().double_value(&[]);
        assert!(back <= x.abs().max().double_value(&[]) / 16.0 + 1e-6, "dequantized activations off by {back}");
    }

    #[test]
    fn bad_shapes_and_row_scaling_on_cpu_are_errors() {
        let e = Fp8Weight::new(&draw(&[48, 60], 0), Fp8Scaling::Tensor).err().unwrap().to_string();
        assert!(e.contains("multiples of 16"), "{e}");
        let e = Fp8Weight::new(&draw(&[48, 64], 0).to_device(Device::Cpu), Fp8Scaling::Row).err().unwrap().to_string();
        assert!(e.contains("CUDA"), "{e}");
        assert_eq!("row".parse::<Fp8Scaling>(), Ok(Fp8Scaling::Row));
        assert!("rows".parse::<Fp8Scaling>().is_err());
    }

    #[test]
    fn a_zero_weight_stays_zero() {
        let f = Fp8Weight::new(&Tensor::zeros([16, 16], (Kind::Float, Device::Cpu)), Fp8Scaling::Tensor).unwrap();
        let y = f.linear(&draw(&[3, 16], 4), &Tensor::zeros([16], (Kind::Float, Device::Cpu)), Kind::Float);
        assert_eq!(y.abs().max().double_value(&[]), 0.0);
    }
}
