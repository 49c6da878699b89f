//! Wan's 3-axis rotary position embedding: within each head, adjacent channel pairs (2j, 2j+1)
//! rotate; the first pairs by the latent-frame index, then by the row, then by the column. Each
//! axis has its own frequencies theta^(-2j/D_axis). Angles are computed in f64.

use tch::{Device, Kind, Tensor};

/// Rotations e^(i angle), [L, 1, head_dim/2] complex64, for a token grid (f, h, w) in row-major order.
pub struct Rope {
    rotations: Tensor,
}

impl Rope {
    pub fn new(grid: (i64, i64, i64), axes: [i64; 3], theta: f64, device: Device) -> Self {
        let (f, h, w) = grid;
        let freqs: Vec<Vec<f64>> = axes
            .iter()
            .map(|&d| (0..d / 2).map(|j| theta.powf(-(2 * j) as f64 / d as f64)).collect())
            .collect();
        let pairs: usize = freqs.iter().map(|v| v.len()).sum();
        let len = (f * h * w) as usize;
        let mut cos = Vec::with_capacity(len * pairs);
        let mut sin = Vec::with_capacity(len * pairs);
        for fi in 0..f {
            for hi in 0..h {
                for wi in 0..w {
                    for (pos, axis) in [fi, hi, wi].iter().zip(&freqs) {
                        for &om in axis {
                            let angle = *pos as f64 * om;
                            cos.push(angle.cos() as f32);
                            sin.push(angle.sin() as f32);
                        }
                    }
                }
            }
        }
        let shape = [len as i64, 1, pairs as i64];
        let cos = Tensor::from_slice(&cos).view(shape);
        let sin = Tensor::from_slice(&sin).view(shape);
        Self { rotations: Tensor::complex(&cos, &sin).to_device(device) }
    }

    /// The same rotations (the tensor shared, not copied).
    pub fn shallow_clone(&self) -> Self {
        Self { rotations: self.rotations.shallow_clone() }
    }

    /// Whether both hold the same tensor (not only equal values).
    pub fn same_tensor(&self, other: &Rope) -> bool {
        self.rotations.data_ptr() == other.rotations.data_ptr()
    }

    /// Rotates x [B, L, heads, head_dim] in fp32 and returns it in x's dtype: each pair
    /// (x0, x1) as the complex number x0 + i x1, times its rotation. On a CUDA device one kernel
    /// reads and writes x once each way (`bwm_fused_ops::rotate`); on the CPU, or where that kernel cannot
    /// be compiled, the complex product of libtorch's tensors (three passes each way).
    pub fn apply(&self, x: &Tensor) -> Tensor {
        if x.device().is_cuda() && bwm_fused_ops::available(x.device()) {
            return bwm_fused_ops::rotate(x, &self.rotations).expect("the rotary kernel failed on the rotations made for x's token grid");
        }
        self.apply_tensors(x)
    }

    /// [`Rope::apply`] through libtorch's complex product.
    pub fn apply_tensors(&self, x: &Tensor) -> Tensor {
        let size = x.size();
        let (b, l, n, d) = (size[0], size[1], size[2], size[3]);
        let pairs = x.to_kind(Kind::Float).view([b, l, n, d / 2, 2]).view_as_complex();
        (pairs * &self.rotations).view_as_real().view([b, l, n, d]).to_kind(x.kind())
    }
}
