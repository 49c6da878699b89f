//! The small layers the DiT and VAE are made of. Parameters are named as in PyTorch
//! (`weight`, `bias`), so the module path plus the field is the checkpoint key.

use tch::{Kind, Tensor};

use crate::fp8::Fp8Weight;
use crate::lora::LoraAdapter;
use crate::vb::{Init, Vb};
use crate::weights::WeightsError;

/// `nn.Linear(in, out)`; weight [out, in]; with a LoRA adapter where the model's LoRA config
/// targets the layer.
pub struct Linear {
    pub weight: Tensor,
    pub bias: Tensor,
    pub lora: Option<LoraAdapter>,
    /// The weight in FP8, used by `forward` instead of `weight` once set (inference only: no
    /// gradient flows through it).
    pub fp8: Option<Fp8Weight>,
    /// The forward and backward products in FP8 from `weight` itself on each call of at least
    /// this many rows (training; `fp8_dit::train_dit_blocks_in_fp8` sets it after checking the
    /// shapes and the device); smaller products in the parameters' dtype.
    pub fp8_training: Option<i64>,
}

impl Linear {
    pub fn new(vb: &Vb, in_dim: i64, out_dim: i64) -> Result<Self, WeightsError> {
        let bound = 1.0 / (in_dim as f64).sqrt();
        let weight = vb.get(&[out_dim, in_dim], "weight", Init::Uniform { bound })?;
        let bias = vb.get(&[out_dim], "bias", Init::Uniform { bound })?;
        let lora = vb.lora_target().map(|state| LoraAdapter::new(vb, state, in_dim, out_dim)).transpose()?;
        Ok(Self { weight, bias, lora, fp8: None, fp8_training: None })
    }

    /// In the parameters' dtype; `x` is cast to it.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let x = x.to_kind(self.weight.kind());
        let y = match &self.fp8 {
            Some(w) => w.linear(&x, &self.bias, self.weight.kind()),
            None if self.fp8_training.is_some_and(|min_rows| x.numel() as i64 >= min_rows * self.weight.size()[1]) => {
                bwm_fp8_autograd::linear(&x, &self.weight, &self.bias)
                    .expect("an FP8 training linear failed after fp8_dit::train_dit_blocks_in_fp8 checked its shapes and device")
            }
            None => x.linear(&self.weight, Some(&self.bias)),
        };
        match &self.lora {
            Some(adapter) => y + adapter.forward(&x),
            None => y,
        }
    }

    /// In fp32 whatever the parameters' dtype (time embedding, as the reference keeps it in fp32).
    pub fn forward_f32(&self, x: &Tensor) -> Tensor {
        let x = x.to_kind(Kind::Float);
        let y = x.linear(&self.weight.to_kind(Kind::Float), Some(&self.bias.to_kind(Kind::Float)));
        match &self.lora {
            Some(adapter) => y + adapter.forward(&x.to_kind(adapter.a.kind())).to_kind(Kind::Float),
            None => y,
        }
    }
}

/// LayerNorm over the last dimension in x's dtype (the reference's `WanLayerNorm` normalizes in
/// fp32 and casts back; ATen's kernel accumulates in fp32 for bf16 inputs, so it is the same);
/// `affine` = (weight, bias) for `norm3`.
pub fn layer_norm(x: &Tensor, affine: Option<(&Tensor, &Tensor)>, eps: f64) -> Tensor {
    let d = *x.size().last().expect("layer_norm on a 0-d tensor");
    match affine {
        Some((w, b)) => x.layer_norm([d], Some(w.to_kind(x.kind())), Some(b.to_kind(x.kind())), eps, true),
        None => x.layer_norm([d], None::<Tensor>, None::<Tensor>, eps, true),
    }
}

/// `nn.LayerNorm(dim, elementwise_affine=True)`.
pub struct AffineLayerNorm {
    pub weight: Tensor,
    pub bias: Tensor,
    eps: f64,
}

impl AffineLayerNorm {
    pub fn new(vb: &Vb, dim: i64, eps: f64) -> Result<Self, WeightsError> {
        Ok(Self { weight: vb.get(&[dim], "weight", Init::Ones)?, bias: vb.get(&[dim], "bias", Init::Zeros)?, eps })
    }

    /// In x's dtype.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        layer_norm(x, Some((&self.weight, &self.bias)), self.eps)
    }
}

/// RMSNorm over the last dimension with a learned scale (Wan's q/k norm, over the full width),
/// normalized in fp32. ATen's `rms_norm` (one fused kernel on CUDA) scales before the cast back to
/// the input dtype where the reference casts, then scales: one bf16 rounding fewer.
pub struct RmsNorm {
    pub weight: Tensor,
    eps: f64,
}

impl RmsNorm {
    pub fn new(vb: &Vb, dim: i64, eps: f64) -> Result<Self, WeightsError> {
        Ok(Self { weight: vb.get(&[dim], "weight", Init::Ones)?, eps })
    }

    pub fn forward(&self, x: &Tensor) -> Tensor {
        let d = *x.size().last().expect("rms_norm on a 0-d tensor");
        x.rms_norm([d], Some(self.weight.to_kind(x.kind())), self.eps)
    }
}

/// Scaled dot-product attention over [B, L, heads*head_dim] inputs (no mask, default scale).
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor, num_heads: i64) -> Tensor {
    let (b, lq, d) = q.size3().expect("attention: q must be [B, L, D]");
    let lk = k.size()[1];
    let hd = d / num_heads;
    let q = q.view([b, lq, num_heads, hd]).transpose(1, 2);
    let k = k.view([b, lk, num_heads, hd]).transpose(1, 2);
    let v = v.view([b, lk, num_heads, hd]).transpose(1, 2);
    Tensor::scaled_dot_product_attention(&q, &k, &v, None::<Tensor>, 0.0, false, None, false)
        .transpose(1, 2)
        .reshape([b, lq, d])
}

/// `x * (1 + scale) + shift`, one kernel over x (`shift` and `scale` broadcast).
pub fn modulate(x: &Tensor, shift: &Tensor, scale: &Tensor) -> Tensor {
    frame_addcmul(shift, x, &(scale + 1.0))
}

/// `a + b * c` with b [B, F, P, D], c [B, F, 1, D] and a either: on a CUDA device, where the three
/// share a dtype, `bwm_fused_ops::frame_addcmul` (one pass each way; its backward sums c's
/// gradient in fp32), else libtorch's broadcasting addcmul.
pub fn frame_addcmul(a: &Tensor, b: &Tensor, c: &Tensor) -> Tensor {
    if b.device().is_cuda() && bwm_fused_ops::frame_addcmul_takes(a, b, c) {
        return bwm_fused_ops::frame_addcmul(a, b, c).expect("the frame multiply-add failed on operands it takes");
    }
    a.addcmul(b, c)
}
