//! The small layers the DiT and VAE are made of. Parameters are named as in PyTorch
//! (`weight`, `bias`), so the module path plus the field is the checkpoint key.

use std::any::Any;

use tch::{Kind, Tensor};

use crate::vb::{Init, Vb};
use crate::weights::WeightsError;

/// `nn.Linear(in, out)`; weight [out, in].
pub struct Linear {
    pub weight: Tensor,
    pub bias: Tensor,
    /// Where the layer sits in the module tree: its name, and where parameters added to it go.
    vb: Vb,
    /// The product as a conversion from outside the model replaced it (`crate::convert`); the
    /// plain one while None.
    replaced: Option<Box<dyn LinearForward>>,
}

/// A linear layer's product as a conversion (`crate::convert`) replaces it. `forward` sees the
/// input in the parameters' dtype and returns the output in it; `forward_f32` sees and returns
/// fp32 (what `Linear::forward_f32` computes; the plain fp32 product unless the replacement says
/// otherwise).
pub trait LinearForward: Any {
    fn forward(&self, layer: &Linear, x: &Tensor) -> Tensor;

    fn forward_f32(&self, layer: &Linear, x: &Tensor) -> Tensor {
        layer.plain_f32(x)
    }

    /// What the layer carries, for messages (`an adapter`).
    fn describe(&self) -> String;
}

impl Linear {
    pub fn new(vb: &Vb, in_dim: i64, out_dim: i64) -> Result<Self, WeightsError> {
        Self::drawn(vb, in_dim, out_dim, Init::Uniform { bound: 1.0 / (in_dim as f64).sqrt() })
    }

    /// As `new`, the weight and bias zero where they are drawn rather than read: a layer whose
    /// output starts at nothing (the last layer of a module added to a model).
    pub fn zeros(vb: &Vb, in_dim: i64, out_dim: i64) -> Result<Self, WeightsError> {
        Self::drawn(vb, in_dim, out_dim, Init::Zeros)
    }

    /// Weight and bias read from `vb`, or drawn from `init` where it draws.
    fn drawn(vb: &Vb, in_dim: i64, out_dim: i64, init: Init) -> Result<Self, WeightsError> {
        let weight = vb.get(&[out_dim, in_dim], "weight", init)?;
        let bias = vb.get(&[out_dim], "bias", init)?;
        Ok(Self { weight, bias, vb: vb.clone(), replaced: None })
    }

    /// In the parameters' dtype; `x` is cast to it.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let x = x.to_kind(self.weight.kind());
        match &self.replaced {
            Some(product) => product.forward(self, &x),
            None => x.linear(&self.weight, Some(&self.bias)),
        }
    }

    /// In fp32 whatever the parameters' dtype (time embedding, as the reference keeps it in fp32).
    pub fn forward_f32(&self, x: &Tensor) -> Tensor {
        let x = x.to_kind(Kind::Float);
        match &self.replaced {
            Some(product) => product.forward_f32(self, &x),
            None => self.plain_f32(&x),
        }
    }

    /// The product in fp32 of an fp32 `x`.
    pub fn plain_f32(&self, x: &Tensor) -> Tensor {
        x.linear(&self.weight.to_kind(Kind::Float), Some(&self.bias.to_kind(Kind::Float)))
    }

    /// The module path (`blocks.0.self_attn.q`): the parameters' checkpoint names less `.weight`
    /// and `.bias`.
    pub fn path(&self) -> &str {
        self.vb.prefix()
    }

    /// The layer's place in the module tree, for parameters a conversion adds to it (`Vb::add`).
    pub fn vb(&self) -> &Vb {
        &self.vb
    }

    /// Replaces the layer's product (a conversion's step), returning the replacement it had.
    pub fn replace_forward(&mut self, product: Box<dyn LinearForward>) -> Option<Box<dyn LinearForward>> {
        self.replaced.replace(product)
    }

    /// The replacement of the layer's product, if a conversion made one.
    pub fn replaced_forward(&self) -> Option<&dyn LinearForward> {
        self.replaced.as_deref()
    }

    /// The replacement of the layer's product, if it is a `T`.
    pub fn replaced_forward_as<T: LinearForward>(&self) -> Option<&T> {
        self.replaced.as_deref().and_then(|p| (p as &dyn Any).downcast_ref::<T>())
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
