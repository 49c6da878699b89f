//! The Wan2.2 VAE (`WanVAE_` of `wan/modules/vae2_2.py`, `VideoVAE38_` in DiffSynth-Studio):
//! 2x2 patchify, causal 3D convolutions run chunk by chunk with a feature cache, 16x (or 8x) spatial and
//! 4x temporal compression, 48 latent channels. Field paths equal the keys of `Wan2.2_VAE.pth`.
//!
//! Encode runs the first frame alone, then 4 frames at a time; decode runs one latent frame at a
//! time. Each temporal operator keeps what the next chunk needs in a cache slot, visited in a
//! fixed order per chunk (the reference's `feat_cache` list), so a long video is processed in
//! memory bounded by one chunk.

use anyhow::{ensure, Result};
use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use crate::vb::{Init, Vb};
use crate::weights::WeightsError;

/// Published latent statistics of the Wan2.2 VAE (48 channels).
pub const WAN22_LATENTS_MEAN: [f64; 48] = [
    -0.2289, -0.0052, -0.1323, -0.2339, -0.2799, 0.0174, 0.1838, 0.1557, -0.1382, 0.0542, 0.2813, 0.0891, 0.1570,
    -0.0098, 0.0375, -0.1825, -0.2246, -0.1207, -0.0698, 0.5109, 0.2665, -0.2108, -0.2158, 0.2502, -0.2055, -0.0322,
    0.1109, 0.1567, -0.0729, 0.0899, -0.2799, -0.1230, -0.0313, -0.1649, 0.0117, 0.0723, -0.2839, -0.2083, -0.0520,
    0.3748, 0.0152, 0.1957, 0.1433, -0.2944, 0.3573, -0.0548, -0.1681, -0.0667,
];
pub const WAN22_LATENTS_STD: [f64; 48] = [
    0.4765, 1.0364, 0.4514, 1.1677, 0.5313, 0.4990, 0.4818, 0.5013, 0.8158, 1.0344, 0.5894, 1.0901, 0.6885, 0.6165,
    0.8454, 0.4978, 0.5759, 0.3523, 0.7135, 0.6804, 0.5833, 1.4146, 0.8986, 0.5659, 0.7069, 0.5338, 0.4889, 0.4917,
    0.4069, 0.4999, 0.6866, 0.4093, 0.5709, 0.6065, 0.6415, 0.4944, 0.5726, 1.2042, 0.5458, 1.6887, 0.3971, 1.0600,
    0.3943, 0.5537, 0.5444, 0.4089, 0.7468, 0.7744,
];

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VaeConfig {
    /// Encoder base width (160 for Wan2.2).
    pub dim: i64,
    /// Decoder base width (256 for Wan2.2).
    pub dec_dim: i64,
    pub z_dim: i64,
    pub dim_mult: Vec<i64>,
    pub num_res_blocks: i64,
    /// Per encoder stage: whether it halves time (the decoder mirrors it).
    pub temporal_downsample: Vec<bool>,
}

impl VaeConfig {
    /// The Wan2.2 VAE (`Wan2.2_VAE.pth`).
    pub fn wan22() -> Self {
        Self {
            dim: 160,
            dec_dim: 256,
            z_dim: 48,
            dim_mult: vec![1, 2, 4, 4],
            num_res_blocks: 2,
            temporal_downsample: vec![false, true, true],
        }
    }

    /// The same architecture at a smaller width.
    pub fn with_width(dim: i64, dec_dim: i64) -> Self {
        Self { dim, dec_dim, ..Self::wan22() }
    }

    /// The same architecture with a spatial stride of 16 (Wan2.2's four stages) or 8 (its first
    /// stage, which halves space only, left out: twice the latent grid per side, for frames too
    /// small for a 16x grid to place things in).
    pub fn with_spatial_stride(self, stride: i64) -> Result<Self> {
        let Self { dim_mult, temporal_downsample, .. } = Self::wan22();
        match stride {
            16 => Ok(Self { dim_mult, temporal_downsample, ..self }),
            8 => Ok(Self { dim_mult: dim_mult[1..].to_vec(), temporal_downsample: temporal_downsample[1..].to_vec(), ..self }),
            _ => anyhow::bail!("the VAE's spatial stride must be 8 or 16, got {stride}"),
        }
    }

    pub fn validate(&self) -> Result<()> {
        ensure!(self.dim > 0 && self.dec_dim > 0 && self.z_dim > 0, "vae.dim, vae.dec_dim and vae.z_dim must be positive");
        ensure!(
            matches!(self.dim_mult.len(), 3 | 4),
            "vae.dim_mult must have 3 or 4 stages (8x or 16x spatial compression), got {:?}",
            self.dim_mult
        );
        ensure!(self.dim_mult.iter().all(|&m| m > 0), "vae.dim_mult must be positive");
        ensure!(self.num_res_blocks > 0, "vae.num_res_blocks must be positive");
        ensure!(
            self.temporal_downsample.len() == self.dim_mult.len() - 1,
            "vae.temporal_downsample must have one entry per downsampling stage ({}), got {:?}",
            self.dim_mult.len() - 1,
            self.temporal_downsample
        );
        ensure!(
            self.temporal_downsample.iter().filter(|&&t| t).count() == 2,
            "vae.temporal_downsample must halve time twice (4x), got {:?}",
            self.temporal_downsample
        );
        // Each stage's parameter-free shortcut averages groups of its input values (channels x
        // the cells it merges) into each output channel, so a stage may widen by at most that factor.
        let widths: Vec<i64> = std::iter::once(1).chain(self.dim_mult.iter().copied()).collect();
        for (i, pair) in widths.windows(2).enumerate() {
            let merged = self.temporal_downsample.get(i).map_or(1, |&t| if t { 8 } else { 4 });
            ensure!(
                pair[0] * merged % pair[1] == 0 && pair[0] * merged >= pair[1],
                "vae.dim_mult {:?}: stage {i} widens x{} {} (it can widen by a divisor of {merged})",
                self.dim_mult,
                pair[1] as f64 / pair[0] as f64,
                if i + 1 == self.dim_mult.len() { "without downsampling" } else { "while downsampling" }
            );
        }
        Ok(())
    }

    pub fn temporal_stride(&self) -> i64 {
        1 << self.temporal_downsample.iter().filter(|&&t| t).count()
    }

    /// Pixels per latent cell along each side: the 2x2 patchify times 2 per downsampling stage.
    pub fn spatial_stride(&self) -> i64 {
        2 << (self.dim_mult.len().max(1) - 1)
    }

    /// [z, 1 + (F - 1) / temporal stride, H / s, W / s] (s = `spatial_stride`): the latent shape of
    /// a clip of `frames` pixel frames (1 + stride * k) of `height` x `width`.
    pub fn latent_shape(&self, frames: i64, height: i64, width: i64) -> Vec<i64> {
        let s = self.spatial_stride();
        vec![self.z_dim, 1 + (frames - 1) / self.temporal_stride(), height / s, width / s]
    }
}

/// One cache slot per temporal operator, in visiting order.
#[derive(Default)]
enum Slot {
    #[default]
    Empty,
    /// An upsample3d that has seen the first chunk (it skipped its time conv there).
    Rep,
    Frames(Tensor),
}

/// The reference's `feat_cache` + `feat_idx`: rewound at the start of every chunk.
#[derive(Default)]
pub struct FeatCache {
    slots: Vec<Slot>,
    next: usize,
}

impl FeatCache {
    fn rewind(&mut self) {
        self.next = 0;
    }

    fn slot(&mut self) -> &mut Slot {
        if self.next == self.slots.len() {
            self.slots.push(Slot::Empty);
        }
        self.next += 1;
        &mut self.slots[self.next - 1]
    }

    /// Bytes held by the cache (for the bounded-memory check).
    pub fn bytes(&self) -> i64 {
        self.slots
            .iter()
            .map(|s| match s {
                Slot::Frames(t) => t.numel() as i64 * t.kind().elt_size_in_bytes() as i64,
                _ => 0,
            })
            .sum()
    }
}

fn last_frames(x: &Tensor, n: i64) -> Tensor {
    let t = x.size()[2];
    x.narrow(2, (t - n).max(0), n.min(t))
}

/// `CausalConv3d`: zero padding in the past only (2*pt frames), replaced by cached frames.
pub struct CausalConv3d {
    pub weight: Tensor,
    pub bias: Tensor,
    stride: [i64; 3],
    pad: [i64; 3],
}

impl CausalConv3d {
    fn new(vb: &Vb, cin: i64, cout: i64, kernel: [i64; 3], stride: [i64; 3], pad: [i64; 3]) -> Result<Self, WeightsError> {
        let bound = 1.0 / ((cin * kernel.iter().product::<i64>()) as f64).sqrt();
        Ok(Self {
            weight: vb.get(&[cout, cin, kernel[0], kernel[1], kernel[2]], "weight", Init::Uniform { bound })?,
            bias: vb.get(&[cout], "bias", Init::Uniform { bound })?,
            stride,
            pad,
        })
    }

    fn k3(vb: &Vb, cin: i64, cout: i64) -> Result<Self, WeightsError> {
        Self::new(vb, cin, cout, [3, 3, 3], [1, 1, 1], [1, 1, 1])
    }

    fn k1(vb: &Vb, cin: i64, cout: i64) -> Result<Self, WeightsError> {
        Self::new(vb, cin, cout, [1, 1, 1], [1, 1, 1], [0, 0, 0])
    }

    fn forward(&self, x: &Tensor, cache: Option<&Tensor>) -> Tensor {
        let mut front = 2 * self.pad[0];
        let mut x = x.shallow_clone();
        if let (Some(c), true) = (cache, front > 0) {
            x = Tensor::cat(&[c, &x], 2);
            front -= c.size()[2];
        }
        if front > 0 {
            let mut s = x.size();
            s[2] = front;
            x = Tensor::cat(&[Tensor::zeros(&s, (x.kind(), x.device())), x], 2);
        }
        x.conv3d(&self.weight, Some(&self.bias), self.stride, [0, self.pad[1], self.pad[2]], [1, 1, 1], 1)
    }

    /// A temporal-kernel conv inside the chunk loop: runs with the previous chunk's last frames
    /// and keeps its own input's last 2 frames (padding a 1-frame input with the previous one).
    fn forward_cached(&self, x: &Tensor, cache: &mut FeatCache) -> Tensor {
        let slot = cache.slot();
        let old = match slot {
            Slot::Frames(t) => Some(t.shallow_clone()),
            _ => None,
        };
        let mut keep = last_frames(x, 2);
        if keep.size()[2] < 2 {
            if let Some(o) = &old {
                keep = Tensor::cat(&[last_frames(o, 1), keep], 2);
            }
        }
        let out = self.forward(x, old.as_ref());
        *slot = Slot::Frames(keep);
        out
    }
}

/// `RMS_norm`: L2-normalize over channels (eps 1e-12), times sqrt(C) and a learned gamma.
pub struct RmsNorm {
    pub gamma: Tensor,
    scale: f64,
}

impl RmsNorm {
    /// `images`: gamma [C,1,1] (2D feature maps) rather than [C,1,1,1].
    fn new(vb: &Vb, dim: i64, images: bool) -> Result<Self, WeightsError> {
        let shape: &[i64] = if images { &[dim, 1, 1] } else { &[dim, 1, 1, 1] };
        Ok(Self { gamma: vb.get(shape, "gamma", Init::Ones)?, scale: (dim as f64).sqrt() })
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let norm = x.norm_scalaropt_dim(2, [1], true).clamp_min(1e-12);
        x / norm * self.scale * &self.gamma
    }
}

pub struct ResidualBlock {
    pub norm1: RmsNorm,
    pub conv1: CausalConv3d,
    pub norm2: RmsNorm,
    pub conv2: CausalConv3d,
    pub shortcut: Option<CausalConv3d>,
}

impl ResidualBlock {
    /// Parameters at `residual.{0,2,3,6}` and `shortcut`.
    fn new(vb: &Vb, cin: i64, cout: i64) -> Result<Self, WeightsError> {
        let r = vb.pp("residual");
        Ok(Self {
            norm1: RmsNorm::new(&r.pp(0), cin, false)?,
            conv1: CausalConv3d::k3(&r.pp(2), cin, cout)?,
            norm2: RmsNorm::new(&r.pp(3), cout, false)?,
            conv2: CausalConv3d::k3(&r.pp(6), cout, cout)?,
            shortcut: if cin != cout { Some(CausalConv3d::k1(&vb.pp("shortcut"), cin, cout)?) } else { None },
        })
    }

    fn forward(&self, x: &Tensor, cache: &mut FeatCache) -> Tensor {
        let h = match &self.shortcut {
            Some(s) => s.forward(x, None),
            None => x.shallow_clone(),
        };
        let y = self.conv1.forward_cached(&self.norm1.forward(x).silu(), cache);
        let y = self.conv2.forward_cached(&self.norm2.forward(&y).silu(), cache);
        y + h
    }
}

/// Single-head spatial self-attention within each frame.
pub struct AttentionBlock {
    pub norm: RmsNorm,
    pub to_qkv_weight: Tensor,
    pub to_qkv_bias: Tensor,
    pub proj_weight: Tensor,
    pub proj_bias: Tensor,
}

impl AttentionBlock {
    fn new(vb: &Vb, dim: i64) -> Result<Self, WeightsError> {
        let bound = 1.0 / (dim as f64).sqrt();
        let (qkv, proj) = (vb.pp("to_qkv"), vb.pp("proj"));
        Ok(Self {
            norm: RmsNorm::new(&vb.pp("norm"), dim, true)?,
            to_qkv_weight: qkv.get(&[3 * dim, dim, 1, 1], "weight", Init::Uniform { bound })?,
            to_qkv_bias: qkv.get(&[3 * dim], "bias", Init::Uniform { bound })?,
            proj_weight: proj.get(&[dim, dim, 1, 1], "weight", Init::Zeros)?,
            proj_bias: proj.get(&[dim], "bias", Init::Uniform { bound })?,
        })
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let s = x.size();
        let (b, c, t, h, w) = (s[0], s[1], s[2], s[3], s[4]);
        let frames = x.permute([0, 2, 1, 3, 4]).reshape([b * t, c, h, w]);
        let qkv = self.norm.forward(&frames).conv2d(&self.to_qkv_weight, Some(&self.to_qkv_bias), [1, 1], [0, 0], [1, 1], 1);
        // [bt, 3c, hw] -> [bt, 1, hw, 3c]; q, k, v are channel thirds.
        let qkv = qkv.reshape([b * t, 1, 3 * c, h * w]).permute([0, 1, 3, 2]).contiguous();
        let parts = qkv.chunk(3, -1);
        let y = Tensor::scaled_dot_product_attention(&parts[0], &parts[1], &parts[2], None::<Tensor>, 0.0, false, None, false);
        let y = y.squeeze_dim(1).permute([0, 2, 1]).reshape([b * t, c, h, w]);
        let y = y.conv2d(&self.proj_weight, Some(&self.proj_bias), [1, 1], [0, 0], [1, 1], 1);
        y.reshape([b, t, c, h, w]).permute([0, 2, 1, 3, 4]) + x
    }
}

#[derive(Clone, Copy, PartialEq)]
enum ResampleMode {
    Down2d,
    Down3d,
    Up2d,
    Up3d,
}

/// `Resample`: a per-frame 2D conv (`resample.1`) and, for the 3D modes, a temporal conv.
pub struct Resample {
    mode: ResampleMode,
    pub conv: (Tensor, Tensor),
    pub time_conv: Option<CausalConv3d>,
}

impl Resample {
    fn new(vb: &Vb, dim: i64, mode: ResampleMode) -> Result<Self, WeightsError> {
        let bound = 1.0 / ((dim * 9) as f64).sqrt();
        let r = vb.pp("resample").pp(1);
        let conv = (r.get(&[dim, dim, 3, 3], "weight", Init::Uniform { bound })?, r.get(&[dim], "bias", Init::Uniform { bound })?);
        let tc = vb.pp("time_conv");
        let time_conv = match mode {
            ResampleMode::Down3d => Some(CausalConv3d::new(&tc, dim, dim, [3, 1, 1], [2, 1, 1], [0, 0, 0])?),
            ResampleMode::Up3d => Some(CausalConv3d::new(&tc, dim, 2 * dim, [3, 1, 1], [1, 1, 1], [1, 0, 0])?),
            _ => None,
        };
        Ok(Self { mode, conv, time_conv })
    }

    /// The 2D conv on every frame, as a 3D conv with a 1-frame kernel.
    fn spatial(&self, x: &Tensor, stride: i64, pad: i64) -> Tensor {
        x.conv3d(&self.conv.0.unsqueeze(2), Some(&self.conv.1), [1, stride, stride], [0, pad, pad], [1, 1, 1], 1)
    }

    fn forward(&self, x: &Tensor, cache: &mut FeatCache) -> Tensor {
        match self.mode {
            ResampleMode::Down2d | ResampleMode::Down3d => {
                // ZeroPad2d((0, 1, 0, 1)) then a stride-2 conv.
                let x = self.spatial(&x.constant_pad_nd([0, 1, 0, 1]), 2, 0);
                if self.mode == ResampleMode::Down2d {
                    return x;
                }
                let tc = self.time_conv.as_ref().expect("downsample3d has a time conv");
                let slot = cache.slot();
                let out = match slot {
                    // First chunk: one frame stays one frame; remember it.
                    Slot::Empty | Slot::Rep => x.shallow_clone(),
                    Slot::Frames(prev) => tc.forward(&Tensor::cat(&[last_frames(prev, 1), x.shallow_clone()], 2), None),
                };
                *slot = Slot::Frames(last_frames(&x, 1));
                out
            }
            ResampleMode::Up2d | ResampleMode::Up3d => {
                let mut x = x.shallow_clone();
                if self.mode == ResampleMode::Up3d {
                    let tc = self.time_conv.as_ref().expect("upsample3d has a time conv");
                    let slot = cache.slot();
                    match std::mem::take(slot) {
                        // First chunk: no temporal upsampling.
                        Slot::Empty => *slot = Slot::Rep,
                        prev => {
                            let mut keep = last_frames(&x, 2);
                            let old = match prev {
                                Slot::Frames(t) => Some(t),
                                _ => None,
                            };
                            if keep.size()[2] < 2 {
                                let before = match &old {
                                    Some(o) => last_frames(o, 1),
                                    None => keep.zeros_like(),
                                };
                                keep = Tensor::cat(&[before, keep], 2);
                            }
                            let y = tc.forward(&x, old.as_ref());
                            *slot = Slot::Frames(keep);
                            // [b, 2c, t] -> [b, c, 2t], the two halves interleaved in time.
                            let s = y.size();
                            let (b, c, t, h, w) = (s[0], s[1] / 2, s[2], s[3], s[4]);
                            let y = y.reshape(&[b, 2, c, t, h, w][..]);
                            x = Tensor::stack(&[y.select(1, 0), y.select(1, 1)], 3).reshape([b, c, 2 * t, h, w]);
                        }
                    }
                }
                let x = x.repeat_interleave_self_int(2, 3, None).repeat_interleave_self_int(2, 4, None);
                self.spatial(&x, 1, 1)
            }
        }
    }
}

/// `AvgDown3D`: space/time to channels, then the mean over channel groups (parameter-free).
fn avg_down(x: &Tensor, cout: i64, ft: i64, fs: i64) -> Tensor {
    let t = x.size()[2];
    let pad_t = (ft - t % ft) % ft;
    let x = if pad_t > 0 { x.constant_pad_nd([0, 0, 0, 0, pad_t, 0]) } else { x.shallow_clone() };
    let s = x.size();
    let (b, c, t, h, w) = (s[0], s[1], s[2], s[3], s[4]);
    let factor = ft * fs * fs;
    x.view(&[b, c, t / ft, ft, h / fs, fs, w / fs, fs][..])
        .permute([0, 1, 3, 5, 7, 2, 4, 6])
        .reshape(&[b, cout, c * factor / cout, t / ft, h / fs, w / fs][..])
        .mean_dim(2, false, x.kind())
}

/// `DupUp3D`: channel repeats unfolded into space/time (parameter-free).
fn dup_up(x: &Tensor, cout: i64, ft: i64, fs: i64, first_chunk: bool) -> Tensor {
    let s = x.size();
    let (b, cin, t, h, w) = (s[0], s[1], s[2], s[3], s[4]);
    let repeats = cout * ft * fs * fs / cin;
    let y = x
        .repeat_interleave_self_int(repeats, 1, None)
        .view(&[b, cout, ft, fs, fs, t, h, w][..])
        .permute([0, 1, 5, 2, 6, 3, 7, 4])
        .reshape([b, cout, t * ft, h * fs, w * fs]);
    if first_chunk {
        y.narrow(2, ft - 1, t * ft - (ft - 1))
    } else {
        y
    }
}

pub struct DownBlock {
    pub resnets: Vec<ResidualBlock>,
    pub resample: Option<Resample>,
    shortcut: (i64, i64, i64),
}

pub struct UpBlock {
    pub resnets: Vec<ResidualBlock>,
    pub resample: Option<Resample>,
    shortcut: Option<(i64, i64, i64)>,
}

pub struct Encoder {
    pub conv1: CausalConv3d,
    pub downsamples: Vec<DownBlock>,
    pub middle: (ResidualBlock, AttentionBlock, ResidualBlock),
    pub head_norm: RmsNorm,
    pub head_conv: CausalConv3d,
}

pub struct Decoder {
    pub conv1: CausalConv3d,
    pub middle: (ResidualBlock, AttentionBlock, ResidualBlock),
    pub upsamples: Vec<UpBlock>,
    pub head_norm: RmsNorm,
    pub head_conv: CausalConv3d,
}

fn middle(vb: &Vb, dim: i64) -> Result<(ResidualBlock, AttentionBlock, ResidualBlock), WeightsError> {
    Ok((ResidualBlock::new(&vb.pp(0), dim, dim)?, AttentionBlock::new(&vb.pp(1), dim)?, ResidualBlock::new(&vb.pp(2), dim, dim)?))
}

fn run_middle(m: &(ResidualBlock, AttentionBlock, ResidualBlock), x: &Tensor, cache: &mut FeatCache) -> Tensor {
    let x = m.0.forward(x, cache);
    let x = m.1.forward(&x);
    m.2.forward(&x, cache)
}

impl Encoder {
    fn new(vb: &Vb, cfg: &VaeConfig) -> Result<Self, WeightsError> {
        let dims: Vec<i64> = std::iter::once(1).chain(cfg.dim_mult.iter().copied()).map(|m| cfg.dim * m).collect();
        let stages = cfg.dim_mult.len();
        let conv1 = CausalConv3d::k3(&vb.pp("conv1"), 12, dims[0])?;
        let mut downsamples = Vec::new();
        for i in 0..stages {
            let (cin, cout) = (dims[i], dims[i + 1]);
            let temporal = cfg.temporal_downsample.get(i).copied().unwrap_or(false);
            let down = i != stages - 1;
            let vb = vb.pp("downsamples").pp(i).pp("downsamples");
            let mut resnets = Vec::new();
            for j in 0..cfg.num_res_blocks {
                resnets.push(ResidualBlock::new(&vb.pp(j), if j == 0 { cin } else { cout }, cout)?);
            }
            let mode = if temporal { ResampleMode::Down3d } else { ResampleMode::Down2d };
            let resample = if down { Some(Resample::new(&vb.pp(cfg.num_res_blocks), cout, mode)?) } else { None };
            let shortcut = (cout, if temporal { 2 } else { 1 }, if down { 2 } else { 1 });
            downsamples.push(DownBlock { resnets, resample, shortcut });
        }
        let top = dims[stages];
        Ok(Self {
            conv1,
            downsamples,
            middle: middle(&vb.pp("middle"), top)?,
            head_norm: RmsNorm::new(&vb.pp("head").pp(0), top, false)?,
            head_conv: CausalConv3d::k3(&vb.pp("head").pp(2), top, 2 * cfg.z_dim)?,
        })
    }

    /// One chunk of patchified frames -> one latent frame (mean and log-variance channels).
    fn forward(&self, x: &Tensor, cache: &mut FeatCache) -> Tensor {
        cache.rewind();
        let mut x = self.conv1.forward_cached(x, cache);
        for block in &self.downsamples {
            let input = x.shallow_clone();
            for r in &block.resnets {
                x = r.forward(&x, cache);
            }
            if let Some(rs) = &block.resample {
                x = rs.forward(&x, cache);
            }
            let (cout, ft, fs) = block.shortcut;
            x = x + avg_down(&input, cout, ft, fs);
        }
        let x = run_middle(&self.middle, &x, cache);
        self.head_conv.forward_cached(&self.head_norm.forward(&x).silu(), cache)
    }
}

impl Decoder {
    fn new(vb: &Vb, cfg: &VaeConfig) -> Result<Self, WeightsError> {
        let top = *cfg.dim_mult.last().expect("validated");
        let dims: Vec<i64> =
            std::iter::once(top).chain(cfg.dim_mult.iter().rev().copied()).map(|m| cfg.dec_dim * m).collect();
        let stages = cfg.dim_mult.len();
        let temporal_up: Vec<bool> = cfg.temporal_downsample.iter().rev().copied().collect();
        let conv1 = CausalConv3d::k3(&vb.pp("conv1"), cfg.z_dim, dims[0])?;
        let middle = middle(&vb.pp("middle"), dims[0])?;
        let mut upsamples = Vec::new();
        for i in 0..stages {
            let (cin, cout) = (dims[i], dims[i + 1]);
            let temporal = temporal_up.get(i).copied().unwrap_or(false);
            let up = i != stages - 1;
            let vb = vb.pp("upsamples").pp(i).pp("upsamples");
            let mut resnets = Vec::new();
            for j in 0..cfg.num_res_blocks + 1 {
                resnets.push(ResidualBlock::new(&vb.pp(j), if j == 0 { cin } else { cout }, cout)?);
            }
            let mode = if temporal { ResampleMode::Up3d } else { ResampleMode::Up2d };
            let resample = if up { Some(Resample::new(&vb.pp(cfg.num_res_blocks + 1), cout, mode)?) } else { None };
            let shortcut = if up { Some((cout, if temporal { 2 } else { 1 }, 2)) } else { None };
            upsamples.push(UpBlock { resnets, resample, shortcut });
        }
        let out = dims[stages];
        Ok(Self {
            conv1,
            middle,
            upsamples,
            head_norm: RmsNorm::new(&vb.pp("head").pp(0), out, false)?,
            head_conv: CausalConv3d::k3(&vb.pp("head").pp(2), out, 12)?,
        })
    }

    /// One latent frame -> 1 (first chunk) or 4 patchified frames.
    fn forward(&self, x: &Tensor, cache: &mut FeatCache, first_chunk: bool) -> Tensor {
        cache.rewind();
        let x = self.conv1.forward_cached(x, cache);
        let mut x = run_middle(&self.middle, &x, cache);
        for block in &self.upsamples {
            let mut main = x.shallow_clone();
            for r in &block.resnets {
                main = r.forward(&main, cache);
            }
            if let Some(rs) = &block.resample {
                main = rs.forward(&main, cache);
            }
            x = match block.shortcut {
                Some((cout, ft, fs)) => main + dup_up(&x, cout, ft, fs, first_chunk),
                None => main,
            };
        }
        self.head_conv.forward_cached(&self.head_norm.forward(&x).silu(), cache)
    }
}

/// `b c f (h q) (w r) -> b (c r q) f h w`: the column offset r comes before the row offset q.
pub fn patchify(x: &Tensor) -> Tensor {
    let s = x.size();
    let (b, c, f, h, w) = (s[0], s[1], s[2], s[3] / 2, s[4] / 2);
    x.view(&[b, c, f, h, 2, w, 2][..]).permute([0, 1, 6, 4, 2, 3, 5]).reshape([b, c * 4, f, h, w])
}

/// Inverse of `patchify`.
pub fn unpatchify(x: &Tensor) -> Tensor {
    let s = x.size();
    let (b, c, f, h, w) = (s[0], s[1] / 4, s[2], s[3], s[4]);
    x.view(&[b, c, 2, 2, f, h, w][..]).permute([0, 1, 4, 5, 3, 6, 2]).reshape([b, c, f, h * 2, w * 2])
}

pub struct WanVae {
    pub cfg: VaeConfig,
    pub encoder: Encoder,
    /// Top-level `conv1` (encoder output -> mean, log-variance) and `conv2` (latent -> decoder).
    pub conv1: CausalConv3d,
    pub conv2: CausalConv3d,
    pub decoder: Decoder,
    mean: Tensor,
    inv_std: Tensor,
    /// Frames per clip it was trained on, when its file records it (`bwm train-vae` outputs).
    pub trained_clip_frames: Option<usize>,
}

impl WanVae {
    pub fn new(vb: &Vb, cfg: &VaeConfig) -> Result<Self> {
        cfg.validate()?;
        let z = cfg.z_dim;
        let (mean, std): (Vec<f32>, Vec<f32>) = if z == 48 {
            (WAN22_LATENTS_MEAN.iter().map(|&v| v as f32).collect(), WAN22_LATENTS_STD.iter().map(|&v| v as f32).collect())
        } else {
            (vec![0.0; z as usize], vec![1.0; z as usize])
        };
        let stat = |v: &[f32]| Tensor::from_slice(v).view([1, z, 1, 1, 1]).to_device(vb.device()).to_kind(vb.kind());
        Ok(Self {
            cfg: cfg.clone(),
            encoder: Encoder::new(&vb.pp("encoder"), cfg)?,
            conv1: CausalConv3d::k1(&vb.pp("conv1"), 2 * z, 2 * z)?,
            conv2: CausalConv3d::k1(&vb.pp("conv2"), z, z)?,
            decoder: Decoder::new(&vb.pp("decoder"), cfg)?,
            mean: stat(&mean),
            inv_std: stat(&std).reciprocal(),
            trained_clip_frames: None,
        })
    }

    /// Checks a pixel video [B, 3, F, H, W]: F = 1+4k, H and W multiples of 16, finite values.
    pub fn check_video(&self, video: &Tensor) -> Result<()> {
        self.check_video_shape(video)?;
        ensure!(video.isfinite().all().int64_value(&[]) == 1, "video holds NaN or infinite values");
        Ok(())
    }

    /// The shape half of `check_video` (no device sync).
    fn check_video_shape(&self, video: &Tensor) -> Result<()> {
        let s = video.size();
        ensure!(s.len() == 5 && s[1] == 3, "video must be [B, 3, F, H, W], got shape {s:?}");
        let ts = self.cfg.temporal_stride();
        ensure!(s[2] >= 1 && (s[2] - 1) % ts == 0, "video has {} frames; the VAE needs 1+{ts}k frames (1, 5, 9, ...)", s[2]);
        let stride = self.cfg.spatial_stride();
        ensure!(
            s[3] > 0 && s[4] > 0 && s[3] % stride == 0 && s[4] % stride == 0,
            "video frames are {}x{} (HxW); both must be positive multiples of {stride}",
            s[3],
            s[4],
        );
        Ok(())
    }

    /// Encoder output (mean and log-variance, unnormalized) [B, 2*z, 1+k, H/s, W/s].
    pub fn encode_moments(&self, video: &Tensor) -> Result<Tensor> {
        self.check_video(video)?;
        self.encode_moments_checked(video)
    }

    /// `encode_moments` of a video whose values the caller knows to be finite: only its shape is
    /// checked, so nothing waits for the device (the work can be recorded in a CUDA graph).
    pub fn encode_moments_of_finite(&self, video: &Tensor) -> Result<Tensor> {
        self.check_video_shape(video)?;
        self.encode_moments_checked(video)
    }

    fn encode_moments_checked(&self, video: &Tensor) -> Result<Tensor> {
        let x = patchify(&video.to_kind(self.mean.kind()));
        let frames = x.size()[2];
        let mut cache = FeatCache::default();
        let mut outs = vec![self.encoder.forward(&x.narrow(2, 0, 1), &mut cache)];
        let mut start = 1;
        while start < frames {
            outs.push(self.encoder.forward(&x.narrow(2, start, 4), &mut cache));
            start += 4;
        }
        Ok(self.conv1.forward(&Tensor::cat(&outs, 2), None))
    }

    /// Normalized latent means (mu - mean) / std, [B, z, 1+k, H/s, W/s]; deterministic.
    pub fn encode(&self, video: &Tensor) -> Result<Tensor> {
        Ok(self.normalized_mean(&self.encode_moments(video)?))
    }

    fn normalized_mean(&self, moments: &Tensor) -> Tensor {
        (moments.narrow(1, 0, self.cfg.z_dim) - &self.mean) * &self.inv_std
    }

    /// Normalized latents of u8 video [B, 3, F, H, W] (0..255), rounded to bf16 as a latent
    /// cache stores them (so encoding on the fly gives a cache's values), on the video's device.
    /// u8 holds no NaN, so nothing waits for the device: the encoding is only queued.
    pub fn encode_u8(&self, pixels: &Tensor) -> Result<Tensor> {
        ensure!(pixels.kind() == Kind::Uint8, "pixels must be u8, got {:?}", pixels.kind());
        self.check_video_shape(pixels)?;
        let video = pixels.to_kind(Kind::Float) / 127.5 - 1.0;
        let latents = tch::no_grad(|| self.encode_moments_checked(&video).map(|m| self.normalized_mean(&m)))?;
        Ok(latents.to_kind(Kind::BFloat16))
    }

    /// The VAE's reconstruction of video [B, 3, F, H, W] in [-1, 1], for any F >= 1: the last
    /// frame is repeated up to the next 1+4k frames for the encoder and the repeats dropped after
    /// decoding. Clamped to [-1, 1]; no gradients.
    pub fn round_trip(&self, video: &Tensor) -> Result<Tensor> {
        let s = video.size();
        ensure!(s.len() == 5 && s[1] == 3 && s[2] >= 1, "video must be [B, 3, F, H, W] with F >= 1, got shape {s:?}");
        let ts = self.cfg.temporal_stride();
        let pad = (ts - (s[2] - 1) % ts) % ts;
        let padded = match pad {
            0 => video.shallow_clone(),
            _ => Tensor::cat(&[video.shallow_clone(), video.narrow(2, s[2] - 1, 1).repeat([1, 1, pad, 1, 1])], 2),
        };
        let out = tch::no_grad(|| self.encode(&padded).and_then(|z| self.decode(&z)))?;
        Ok(out.narrow(2, 0, s[2]).clamp(-1.0, 1.0))
    }

    /// Starts a streaming decode of normalized latents: one latent frame in, its pixel frames out.
    pub fn decoder_stream(&self) -> DecodeStream<'_> {
        DecodeStream { vae: self, cache: FeatCache::default(), first: true }
    }

    /// Decodes normalized latents [B, z, T, h, w] to pixels [B, 3, 1+4(T-1), 16h, 16w], not clamped.
    pub fn decode(&self, latents: &Tensor) -> Result<Tensor> {
        let frames = self.check_latents(latents)?;
        let mut stream = self.decoder_stream();
        let outs = (0..frames).map(|i| stream.next(&latents.narrow(2, i, 1))).collect::<Result<Vec<_>>>()?;
        Ok(Tensor::cat(&outs, 2))
    }

    fn check_latents(&self, latents: &Tensor) -> Result<i64> {
        let s = latents.size();
        ensure!(
            s.len() == 5 && s[1] == self.cfg.z_dim && s[2] > 0,
            "latents must be [B, {}, T, h, w], got shape {s:?}",
            self.cfg.z_dim
        );
        Ok(s[2])
    }
}

/// Decoding state between latent frames: memory is bounded by the feature cache, whatever the
/// length of the video.
pub struct DecodeStream<'a> {
    vae: &'a WanVae,
    cache: FeatCache,
    first: bool,
}

impl DecodeStream<'_> {
    /// One normalized latent frame [B, z, 1, h, w] -> pixel frames [B, 3, 1 or 4, 16h, 16w].
    pub fn next(&mut self, latent: &Tensor) -> Result<Tensor> {
        let frames = self.vae.check_latents(latent)?;
        ensure!(frames == 1, "the decode stream takes one latent frame at a time, got {frames}");
        let vae = self.vae;
        let z = latent.to_kind(vae.mean.kind()) / &vae.inv_std + &vae.mean;
        let x = vae.conv2.forward(&z, None);
        let out = vae.decoder.forward(&x, &mut self.cache, self.first);
        self.first = false;
        Ok(unpatchify(&out))
    }

    pub fn cache_bytes(&self) -> i64 {
        self.cache.bytes()
    }
}

impl WanVae {
    /// Random weights drawn after seeding libtorch's generator with `seed` (`vb::with_seed`).
    pub fn random(cfg: &VaeConfig, kind: Kind, device: tch::Device, seed: i64) -> Result<(Self, std::rc::Rc<crate::vb::ParamStore>)> {
        crate::vb::with_seed(seed, || {
            let store = crate::vb::ParamStore::random(kind, device);
            Ok((Self::new(&store.root(), cfg)?, store))
        })
    }

    /// Weights by name (the keys of `Wan2.2_VAE.pth`) from the `.pth` itself or safetensors.
    pub fn load(path: &std::path::Path, cfg: &VaeConfig, kind: Kind, device: tch::Device) -> Result<Self> {
        let source = crate::weight_file::open_source(path)?;
        let store = crate::vb::ParamStore::from_weights(source, &[], kind, device);
        let vae = Self::new(&store.root(), cfg)?;
        store.check_all_consumed()?;
        Ok(vae)
    }
}

/// The diffusers `AutoencoderKLWan` name of a `Wan2.2_VAE.pth` key (docs/wan22-ti2v-5b.md, table "VAE keys").
pub fn diffusers_key(wan: &str) -> String {
    let parts: Vec<&str> = wan.split('.').collect();
    let resnet = |rest: &[&str]| -> String {
        let tail = rest.join(".");
        match rest.first().copied() {
            Some("residual") => {
                let layer = match rest.get(1).copied() {
                    Some("0") => "norm1",
                    Some("2") => "conv1",
                    Some("3") => "norm2",
                    _ => "conv2",
                };
                format!("{layer}.{}", rest[2..].join("."))
            }
            Some("shortcut") => format!("conv_shortcut.{}", rest[1..].join(".")),
            _ => tail,
        }
    };
    let middle = |side: &str, rest: &[&str]| -> String {
        match rest[0] {
            "1" => format!("{side}.mid_block.attentions.0.{}", rest[1..].join(".")),
            i => format!("{side}.mid_block.resnets.{}.{}", if i == "0" { 0 } else { 1 }, resnet(&rest[1..])),
        }
    };
    match parts.as_slice() {
        ["conv1", rest @ ..] => format!("quant_conv.{}", rest.join(".")),
        ["conv2", rest @ ..] => format!("post_quant_conv.{}", rest.join(".")),
        [side, "conv1", rest @ ..] => format!("{side}.conv_in.{}", rest.join(".")),
        [side, "head", "0", rest @ ..] => format!("{side}.norm_out.{}", rest.join(".")),
        [side, "head", "2", rest @ ..] => format!("{side}.conv_out.{}", rest.join(".")),
        [side, "middle", rest @ ..] => middle(side, rest),
        [side, stage @ ("downsamples" | "upsamples"), i, _, j, rest @ ..] => {
            let (blocks, sampler) = if *stage == "downsamples" { ("down_blocks", "downsampler") } else { ("up_blocks", "upsampler") };
            if rest.first().is_some_and(|r| *r == "resample" || *r == "time_conv") {
                format!("{side}.{blocks}.{i}.{sampler}.{}", rest.join("."))
            } else {
                format!("{side}.{blocks}.{i}.resnets.{j}.{}", resnet(rest))
            }
        }
        _ => wan.to_string(),
    }
}

impl WanVae {
    /// Weights from a diffusers `AutoencoderKLWan` safetensors file (renamed to Wan names).
    pub fn load_diffusers(path: &std::path::Path, cfg: &VaeConfig, kind: Kind, device: tch::Device) -> Result<Self> {
        let shapes = crate::vb::ParamStore::shapes_only(Kind::Float);
        Self::new(&shapes.root(), cfg)?;
        let to_wan: std::collections::BTreeMap<String, String> =
            shapes.named_parameters().into_iter().map(|(n, _)| (diffusers_key(&n), n)).collect();
        let source = crate::weights::RenamedSource::new(crate::weights::SafetensorsSource::open(path)?, |k| {
            Some(to_wan.get(k).cloned().unwrap_or_else(|| k.to_string()))
        });
        let store = crate::vb::ParamStore::from_weights(Box::new(source), &[], kind, device);
        let vae = Self::new(&store.root(), cfg)?;
        store.check_all_consumed()?;
        Ok(vae)
    }
}

/// Metadata key of a VAE file written by `bwm train-vae`: the `VaeConfig` as JSON. Such a file
/// also holds `latents_mean` and `latents_std` `[z]`, the statistics its latents are normalized with.
pub const TRAINED_CONFIG_KEY: &str = "bwm.vae_config";
/// Metadata key of a `bwm train-vae` file: the frames per clip it was trained on.
pub const TRAINED_CLIP_FRAMES_KEY: &str = "bwm.clip_frames";

/// A warning when a VAE trained on `trained`-frame clips is to encode or decode `used`-frame
/// clips: its causal convolutions always saw the video's start during training, and the latents
/// past its training clip come out poorly (docs/fidelity.md at abaed68, run 10: 27.8 dB on
/// training-length clips, 18.6 dB on whole episodes).
pub fn clip_length_warning(trained: Option<usize>, used: usize) -> Option<String> {
    let trained = trained?;
    (used > trained).then(|| {
        format!(
            "this VAE was trained on {trained}-frame clips and these clips have {used} frames; a VAE reconstructs the frames past its training clip poorly: train it with `bwm train-vae --clip-frames {used}`"
        )
    })
}

impl WanVae {
    /// Replaces the latent normalization constants (a VAE other than the published one).
    pub fn set_latent_stats(&mut self, mean: &Tensor, std: &Tensor) -> Result<()> {
        let z = self.cfg.z_dim;
        ensure!(mean.size() == [z] && std.size() == [z], "latent statistics must be [{z}], got {:?} and {:?}", mean.size(), std.size());
        let (kind, device) = (self.mean.kind(), self.mean.device());
        self.mean = mean.to_kind(kind).to_device(device).view([1, z, 1, 1, 1]);
        self.inv_std = std.to_kind(kind).to_device(device).view([1, z, 1, 1, 1]).reciprocal();
        Ok(())
    }

    /// The latent normalization constants `[z]` (mean, std).
    pub fn latent_stats(&self) -> (Tensor, Tensor) {
        (self.mean.flatten(0, -1), self.inv_std.reciprocal().flatten(0, -1))
    }

    /// The config of the VAE file `load_any` would load, read without its weights (a `bwm
    /// train-vae` output's own, else the published Wan2.2 VAE's).
    pub fn config_of(path: &std::path::Path) -> Result<VaeConfig> {
        Ok(Self::config_and_metadata(path)?.0)
    }

    fn config_and_metadata(path: &std::path::Path) -> Result<(VaeConfig, std::collections::BTreeMap<String, String>)> {
        let is_safetensors = path.extension().and_then(|e| e.to_str()) == Some("safetensors");
        let meta = if is_safetensors { crate::weights::safetensors_metadata(path)? } else { Default::default() };
        let cfg = match meta.get(TRAINED_CONFIG_KEY) {
            Some(cfg_json) => serde_json::from_str(cfg_json)
                .map_err(|e| anyhow::anyhow!("{}: metadata {TRAINED_CONFIG_KEY} is not a VAE config: {e}", path.display()))?,
            None => VaeConfig::wan22(),
        };
        Ok((cfg, meta))
    }

    /// Loads any VAE file this project reads: a `bwm train-vae` output (config, latent statistics
    /// and training clip length inside), else the published Wan2.2 VAE as `.pth` or safetensors.
    pub fn load_any(path: &std::path::Path, kind: Kind, device: tch::Device) -> Result<Self> {
        let (cfg, meta) = Self::config_and_metadata(path)?;
        if !meta.contains_key(TRAINED_CONFIG_KEY) {
            return Self::load(path, &cfg, kind, device);
        }
        let file = crate::weights::SafetensorsSource::open(path)?;
        let stats = |name: &str| crate::weights::WeightSource::load(&file, name, Kind::Float, device);
        let (mean, std) = (stats("latents_mean")?, stats("latents_std")?);
        let source = crate::weights::RenamedSource::new(file, |k| (!k.starts_with("latents_")).then(|| k.to_string()));
        let store = crate::vb::ParamStore::from_weights(Box::new(source), &[], kind, device);
        let mut vae = Self::new(&store.root(), &cfg)?;
        store.check_all_consumed()?;
        vae.set_latent_stats(&mean, &std)?;
        vae.trained_clip_frames = meta
            .get(TRAINED_CLIP_FRAMES_KEY)
            .map(|v| v.parse::<usize>().map_err(|e| anyhow::anyhow!("{}: metadata {TRAINED_CLIP_FRAMES_KEY} = {v:?}: {e}", path.display())))
            .transpose()?;
        Ok(vae)
    }
}
