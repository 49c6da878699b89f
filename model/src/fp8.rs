//! FP8 applied to linear layers from outside the model code, as the trainer and the inference
//! loader choose (conversions, see `crate::convert`):
//!
//! - inference (`quantize_linears`): a weight quantized once to float8 e4m3 with its scale, the
//!   activations scaled on each call from their own absolute maximum (dynamic scaling, as
//!   torchao's float8 recipe does), the product by `_scaled_mm` with the bias added in the output
//!   dtype. Two granularities: one scale per tensor (any device) or one per row of the
//!   activations and per output channel of the weight (CUDA only: libtorch's CPU `_scaled_mm`
//!   takes per-tensor scales);
//! - training (`train_in_fp8`): the layers' three products in FP8 from their weights on each call
//!   (`bwm_fp8_autograd`).

use anyhow::{bail, ensure, Context, Result};
use tch::{Kind, Tensor};

use crate::convert::{self, Linears};
use crate::nn::{Linear, LinearForward};

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

impl LinearForward for Fp8Weight {
    fn forward(&self, layer: &Linear, x: &Tensor) -> Tensor {
        self.linear(x, &layer.bias, layer.weight.kind())
    }

    fn describe(&self) -> String {
        format!("FP8 weights ({} scaling)", self.scaling)
    }
}

/// The linear layers of every DiT block (self- and cross-attention q, k, v, o and the FFN): the
/// embeddings, time projection and head are left out, as torchao's float8 recipe leaves the first
/// and last layers. What the trainer's `train.fp8` and inference's `--fp8` convert.
pub const BLOCK_LINEARS: &[&str] = &["blocks.*"];

/// The layers of `model` that `patterns` select (`convert::select`), each checked to be plain (no
/// conversion replaced its product yet).
fn plain_layers<'a, M: Linears + ?Sized>(model: &'a mut M, patterns: &[impl AsRef<str>], what: &str) -> Result<Vec<&'a mut Linear>> {
    let layers = convert::select(model, patterns)?;
    for layer in &layers {
        if let Some(other) = layer.replaced_forward() {
            bail!("{} carries {}; {what} takes plain linear layers (merge adapters into the weights first)", layer.path(), other.describe());
        }
    }
    Ok(layers)
}

/// Quantizes the linear layers of `model` that `patterns` select to FP8 for inference (no
/// gradient flows through them); the weights stay as they are beside their quantized copies. An
/// error leaves the model as it was. Returns how many layers were quantized.
pub fn quantize_linears<M: Linears + ?Sized>(model: &mut M, patterns: &[impl AsRef<str>], scaling: Fp8Scaling) -> Result<usize> {
    let mut layers = plain_layers(model, patterns, "FP8 quantization")?;
    let quantized = layers
        .iter()
        .map(|layer| tch::no_grad(|| Fp8Weight::new(&layer.weight, scaling)).with_context(|| layer.path().to_string()))
        .collect::<Result<Vec<_>>>()?;
    for (layer, weight) in layers.iter_mut().zip(quantized) {
        layer.replace_forward(Box::new(weight));
    }
    Ok(layers.len())
}

/// A layer trained with its products in FP8 (`bwm_fp8_autograd`) when they have at least
/// `min_rows` rows; smaller products in the parameters' dtype.
pub struct Fp8Training {
    pub min_rows: i64,
}

impl LinearForward for Fp8Training {
    fn forward(&self, layer: &Linear, x: &Tensor) -> Tensor {
        if x.numel() as i64 >= self.min_rows * layer.weight.size()[1] {
            bwm_fp8_autograd::linear(x, &layer.weight, &layer.bias).expect("an FP8 training linear failed after train_in_fp8 checked its shapes and device")
        } else {
            x.linear(&layer.weight, Some(&layer.bias))
        }
    }

    fn describe(&self) -> String {
        format!("FP8 training products (from {} rows)", self.min_rows)
    }
}

/// Trains the linear layers of `model` that `patterns` select with their three products in FP8
/// (`bwm_fp8_autograd`: per-tensor dynamic scales, e4m3 forward, e5m2 gradients); the weights,
/// and whatever masters and optimizer state the trainer keeps, stay as they are. Checks every
/// layer's shape and, with one small product, that the device has FP8 matmuls; an error leaves
/// the model as it was. Products of fewer than `min_rows` rows stay in the weights' dtype (where
/// scaling the weight costs more than FP8 saves). Returns how many layers train so.
pub fn train_in_fp8<M: Linears + ?Sized>(model: &mut M, patterns: &[impl AsRef<str>], min_rows: i64) -> Result<usize> {
    let mut layers = plain_layers(model, patterns, "FP8 training")?;
    for layer in &layers {
        bwm_fp8_autograd::check_weight(&layer.weight, &layer.bias).map_err(|e| e.context(format!("{} cannot train in FP8", layer.path())))?;
    }
    // The layers share one device and dtype: one product says whether it has FP8 matmuls.
    if let Some(layer) = layers.first() {
        let w = &layer.weight;
        let x = Tensor::zeros([1, w.size()[1]], (w.kind(), w.device()));
        tch::no_grad(|| bwm_fp8_autograd::linear(&x, w, &layer.bias).map(drop))
            .map_err(|e| e.context(format!("{} cannot train in FP8 on {:?}", layer.path(), w.device())))?;
    }
    for layer in &mut layers {
        layer.replace_forward(Box::new(Fp8Training { min_rows }));
    }
    Ok(layers.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DitConfig;
    use crate::dit::WanDit;
    use crate::lora::LoraConfig;
    use crate::vb::{with_seed, ParamStore};
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

    fn tiny() -> WanDit {
        with_seed(0, || WanDit::new(&ParamStore::random(Kind::Float, Device::Cpu).root(), &DitConfig::tiny())).unwrap()
    }

    /// The training products of each selected layer, or None where the layer is not converted so.
    fn training(dit: &mut WanDit) -> Vec<(String, Option<i64>)> {
        convert::select(dit, BLOCK_LINEARS).unwrap().iter().map(|l| (l.path().to_string(), l.replaced_forward_as::<Fp8Training>().map(|t| t.min_rows))).collect()
    }

    #[test]
    fn every_block_linear_is_named_and_switched() {
        let mut dit = tiny();
        let names: Vec<String> = training(&mut dit).into_iter().map(|(n, _)| n).collect();
        assert_eq!(names.len(), 10 * dit.blocks.len());
        assert_eq!((names[0].as_str(), names[9].as_str()), ("blocks.0.self_attn.q", "blocks.0.ffn.2"));
        assert_eq!(train_in_fp8(&mut dit, BLOCK_LINEARS, 0).unwrap(), names.len());
        assert!(training(&mut dit).iter().all(|(_, t)| *t == Some(0)));
        assert!(dit.head.head.replaced_forward().is_none() && dit.time_projection.replaced_forward().is_none(), "only the blocks' layers");
    }

    #[test]
    fn layers_with_lora_adapters_are_refused() {
        let mut dit = tiny();
        let lora = LoraConfig { rank: 2, alpha: None, dropout: 0.0, targets: vec!["blocks.*.ffn.*".into()] };
        crate::lora::add_adapters(&mut dit, lora, 0).unwrap();
        let e = train_in_fp8(&mut dit, BLOCK_LINEARS, 0).unwrap_err().to_string();
        assert!(e.contains("blocks.0.ffn.0 carries a LoRA adapter"), "{e}");
        assert!(training(&mut dit).iter().all(|(_, t)| t.is_none()), "no layer switched");
        let e = quantize_linears(&mut dit, BLOCK_LINEARS, Fp8Scaling::Tensor).unwrap_err().to_string();
        assert!(e.contains("blocks.0.ffn.0 carries a LoRA adapter"), "{e}");
        assert!(dit.blocks[0].self_attn.q.replaced_forward().is_none(), "no layer quantized");
    }

    /// Products of at least `min_rows` rows go through float8, smaller ones are the exact linear.
    #[test]
    fn products_under_the_row_threshold_stay_exact() {
        let mut dit = tiny();
        train_in_fp8(&mut dit, BLOCK_LINEARS, 8).unwrap();
        let linear = &dit.blocks[0].ffn.l0;
        let w = &linear.weight;
        for rows in [1, 3, 4, 40] {
            let x = Tensor::randn([2, rows, w.size()[1]], (w.kind(), w.device()));
            let exact = x.linear(w, Some(&linear.bias));
            let y = linear.forward(&x);
            assert_eq!(y.equal(&exact), 2 * rows < 8, "a product of {} rows", 2 * rows);
        }
    }

    /// A quantized layer computes `Fp8Weight::linear` from its weight, in the weight's dtype.
    #[test]
    fn a_quantized_layer_computes_the_fp8_product() {
        let mut dit = tiny();
        assert_eq!(quantize_linears(&mut dit, &["blocks.0.ffn.0"], Fp8Scaling::Tensor).unwrap(), 1);
        let layer = &dit.blocks[0].ffn.l0;
        let x = draw(&[3, layer.weight.size()[1]], 8);
        let expected = Fp8Weight::new(&layer.weight, Fp8Scaling::Tensor).unwrap().linear(&x, &layer.bias, Kind::Float);
        assert!(layer.forward(&x).equal(&expected));
        assert!(layer.forward_f32(&x).equal(&layer.plain_f32(&x)), "the fp32 product stays exact");
        assert_eq!(layer.replaced_forward().unwrap().describe(), "FP8 weights (tensor scaling)");
        let e = quantize_linears(&mut dit, &["blocks.0.ffn.0"], Fp8Scaling::Tensor).unwrap_err().to_string();
        assert!(e.contains("blocks.0.ffn.0 carries FP8 weights"), "{e}");
    }
}
