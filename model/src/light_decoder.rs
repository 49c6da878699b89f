//! A light decoder for a Wan VAE's latents: per-frame 2D convolutions, each residual block seeing
//! its own input one frame back (a causal memory of one frame), spatial upsampling by nearest
//! neighbour and temporal upsampling by a 1x1 convolution whose channel groups become frames. The
//! layout of TAEHV's decoder (madebyollin/taehv, the tiny autoencoders used with Wan and Hunyuan
//! video), trained here by `bwm train-light-decoder` to reproduce one VAE's decoded frames from the
//! same normalized latents. It reads latents exactly as `WanVae::decode` does and gives the same
//! number of frames, 1 + 4 (T - 1) for T latent frames, in [-1, 1] (not clamped).
//!
//! Written by hand: no crate holds this architecture, and it is four kinds of layer.

use anyhow::{ensure, Context, Result};
use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use crate::vae::VaeConfig;
use crate::vb::{Init, ParamStore, Vb};

/// Safetensors metadata key of a light decoder's config.
pub const CONFIG_KEY: &str = "bwm.light_decoder_config";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightDecoderConfig {
    /// Latent channels (the VAE's z_dim).
    pub z_dim: i64,
    /// Pixels per latent cell along each side (the VAE's spatial stride, 8 or 16).
    pub spatial_stride: i64,
    /// Pixel frames per latent frame after the first (the VAE's temporal stride, 4).
    pub temporal_stride: i64,
    /// Channels of the three stages and of the last convolution (TAEHV: 256, 128, 64, 64).
    pub widths: [i64; 4],
    /// Residual blocks per stage (TAEHV: 3).
    pub blocks: i64,
}

/// Pixels per output cell of the last convolution (its channels are unshuffled 2x2 patches).
const PATCH: i64 = 2;
const STAGES: usize = 3;

impl LightDecoderConfig {
    /// TAEHV's widths for the latents of `vae`.
    pub fn for_vae(vae: &VaeConfig) -> Self {
        Self { z_dim: vae.z_dim, spatial_stride: vae.spatial_stride(), temporal_stride: vae.temporal_stride(), widths: [256, 128, 64, 64], blocks: 3 }
    }

    pub fn validate(&self) -> Result<()> {
        ensure!(self.z_dim > 0 && self.blocks > 0 && self.widths.iter().all(|&w| w > 0), "light decoder: z_dim, blocks and widths must be positive");
        ensure!(
            matches!(self.spatial_stride, 4 | 8 | 16),
            "light decoder: the spatial stride must be 4, 8 or 16 (2 x the stages that double space), got {}",
            self.spatial_stride
        );
        ensure!(matches!(self.temporal_stride, 1 | 2 | 4), "light decoder: the temporal stride must be 1, 2 or 4, got {}", self.temporal_stride);
        Ok(())
    }

    /// Whether stage i doubles space: the last log2(stride / 2) stages do.
    fn doubles_space(&self, stage: usize) -> bool {
        let ups = (self.spatial_stride / PATCH).trailing_zeros() as usize;
        stage >= STAGES - ups
    }

    /// Whether stage i doubles time: the last log2(temporal stride) stages do.
    fn doubles_time(&self, stage: usize) -> bool {
        let ups = self.temporal_stride.trailing_zeros() as usize;
        stage >= STAGES - ups
    }
}

/// A 3x3 (or 1x1) 2D convolution.
struct Conv {
    weight: Tensor,
    bias: Option<Tensor>,
    pad: i64,
}

impl Conv {
    fn new(vb: &Vb, cin: i64, cout: i64, k: i64, bias: bool) -> Result<Self> {
        let bound = 1.0 / ((cin * k * k) as f64).sqrt();
        Ok(Self {
            weight: vb.get(&[cout, cin, k, k], "weight", Init::Uniform { bound })?,
            bias: if bias { Some(vb.get(&[cout], "bias", Init::Uniform { bound })?) } else { None },
            pad: k / 2,
        })
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        x.conv2d(&self.weight, self.bias.as_ref(), [1, 1], [self.pad, self.pad], [1, 1], 1)
    }
}

/// relu(conv(relu(conv(relu(conv([x, x one frame back]))))) + skip(x)).
struct MemBlock {
    convs: [Conv; 3],
}

impl MemBlock {
    fn new(vb: &Vb, c: i64) -> Result<Self> {
        let conv = vb.pp("conv");
        Ok(Self { convs: [Conv::new(&conv.pp(0), 2 * c, c, 3, true)?, Conv::new(&conv.pp(1), c, c, 3, true)?, Conv::new(&conv.pp(2), c, c, 3, true)?] })
    }

    /// `x` [B*T, C, H, W] of `frames` = T frames per video, in time order.
    fn forward(&self, x: &Tensor, frames: i64) -> Tensor {
        let s = x.size();
        let v = x.view([-1, frames, s[1], s[2], s[3]]);
        // Each frame's memory is the frame before it; the first frame's is empty.
        let past = Tensor::cat(&[v.narrow(1, 0, 1).zeros_like(), v.narrow(1, 0, frames - 1)], 1).view([-1, s[1], s[2], s[3]]);
        let h = self.convs[0].forward(&Tensor::cat(&[x, &past], 1)).relu();
        let h = self.convs[1].forward(&h).relu();
        (self.convs[2].forward(&h) + x).relu()
    }
}

struct Stage {
    blocks: Vec<MemBlock>,
    doubles_space: bool,
    /// 1x1 convolution to `time` x channels, whose groups become `time` consecutive frames.
    grow: Conv,
    time: i64,
    proj: Conv,
}

pub struct LightDecoder {
    pub cfg: LightDecoderConfig,
    pre: Conv,
    stages: Vec<Stage>,
    post: Conv,
}

impl LightDecoder {
    pub fn new(vb: &Vb, cfg: &LightDecoderConfig) -> Result<Self> {
        cfg.validate()?;
        let w = cfg.widths;
        let pre = Conv::new(&vb.pp("pre"), cfg.z_dim, w[0], 3, true)?;
        let stages = (0..STAGES)
            .map(|i| -> Result<Stage> {
                let sv = vb.pp("stages").pp(i);
                let time = if cfg.doubles_time(i) { 2 } else { 1 };
                Ok(Stage {
                    blocks: (0..cfg.blocks).map(|j| MemBlock::new(&sv.pp("blocks").pp(j), w[i])).collect::<Result<_>>()?,
                    doubles_space: cfg.doubles_space(i),
                    grow: Conv::new(&sv.pp("grow"), w[i], w[i] * time, 1, false)?,
                    time,
                    proj: Conv::new(&sv.pp("proj"), w[i], w[i + 1], 3, false)?,
                })
            })
            .collect::<Result<_>>()?;
        let post = Conv::new(&vb.pp("post"), w[3], 3 * PATCH * PATCH, 3, true)?;
        Ok(Self { cfg: cfg.clone(), pre, stages, post })
    }

    /// Random weights drawn after seeding libtorch's generator with `seed`.
    pub fn random(cfg: &LightDecoderConfig, kind: Kind, device: tch::Device, seed: i64) -> Result<(Self, std::rc::Rc<ParamStore>)> {
        crate::vb::with_seed(seed, || {
            let store = ParamStore::random(kind, device);
            Ok((Self::new(&store.root(), cfg)?, store))
        })
    }

    /// A `bwm train-light-decoder` output: its config in the metadata, its weights by name.
    pub fn load(path: &std::path::Path, kind: Kind, device: tch::Device) -> Result<Self> {
        let meta = crate::weights::safetensors_metadata(path).with_context(|| format!("reading the light decoder {}", path.display()))?;
        let cfg_json = meta
            .get(CONFIG_KEY)
            .with_context(|| format!("{} is not a light decoder (no {CONFIG_KEY} in its metadata; `bwm train-light-decoder` writes one)", path.display()))?;
        let cfg: LightDecoderConfig =
            serde_json::from_str(cfg_json).with_context(|| format!("{}: metadata {CONFIG_KEY} is not a light decoder config", path.display()))?;
        let source = crate::weights::SafetensorsSource::open(path)?;
        let store = ParamStore::from_weights(Box::new(source), &[], kind, device);
        let decoder = Self::new(&store.root(), &cfg).with_context(|| format!("loading the light decoder {}", path.display()))?;
        store.check_all_consumed()?;
        Ok(decoder)
    }

    /// Refuses a VAE whose latents this decoder was not made for.
    pub fn check_vae(&self, vae: &VaeConfig) -> Result<()> {
        let c = &self.cfg;
        ensure!(
            c.z_dim == vae.z_dim && c.spatial_stride == vae.spatial_stride() && c.temporal_stride == vae.temporal_stride(),
            "the light decoder reads latents of {} channels at stride {}x{} (space x time); the VAE makes {} channels at {}x{}",
            c.z_dim,
            c.spatial_stride,
            c.temporal_stride,
            vae.z_dim,
            vae.spatial_stride(),
            vae.temporal_stride()
        );
        Ok(())
    }

    /// Normalized latents [B, z, T, h, w] -> pixels [B, 3, 1 + s (T - 1), s' h, s' w] (s, s': the
    /// temporal and spatial strides), not clamped.
    pub fn decode(&self, latents: &Tensor) -> Result<Tensor> {
        let s = latents.size();
        ensure!(s.len() == 5 && s[1] == self.cfg.z_dim && s[2] > 0, "latents must be [B, {}, T, h, w], got shape {s:?}", self.cfg.z_dim);
        let (b, t) = (s[0], s[2]);
        // Frames side by side in the batch: [B*T, z, h, w].
        let z = latents.to_kind(self.pre.weight.kind()).permute([0, 2, 1, 3, 4]).reshape([b * t, s[1], s[3], s[4]]);
        let mut x = self.pre.forward(&((&z / 3.0).tanh() * 3.0)).relu();
        let mut frames = t;
        for stage in &self.stages {
            for block in &stage.blocks {
                x = block.forward(&x, frames);
            }
            if stage.doubles_space {
                let xs = x.size();
                x = x.upsample_nearest2d([xs[2] * 2, xs[3] * 2], None, None);
            }
            let g = stage.grow.forward(&x);
            let gs = g.size();
            // [B*T, time*C, H, W] -> [B*T*time, C, H, W]: each group one frame, in order.
            x = g.reshape([gs[0] * stage.time, gs[1] / stage.time, gs[2], gs[3]]);
            frames *= stage.time;
            x = stage.proj.forward(&x);
        }
        let y = self.post.forward(&x.relu()).pixel_shuffle(PATCH);
        let ys = y.size();
        let video = y.view([b, frames, 3, ys[2], ys[3]]).permute([0, 2, 1, 3, 4]);
        // The first latent frame stands for one frame, as the VAE's causal decoder has it: its
        // first stride - 1 outputs are dropped.
        let drop = self.cfg.temporal_stride - 1;
        Ok(video.narrow(2, drop, frames - drop))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    fn tiny(stride: i64) -> LightDecoderConfig {
        LightDecoderConfig { z_dim: 4, spatial_stride: stride, temporal_stride: 4, widths: [8, 8, 4, 4], blocks: 1 }
    }

    #[test]
    fn decodes_as_many_frames_and_pixels_as_the_vae() {
        for stride in [8, 16] {
            let (d, _) = LightDecoder::random(&tiny(stride), Kind::Float, Device::Cpu, 0).unwrap();
            let out = d.decode(&Tensor::randn([2, 4, 3, 2, 3], (Kind::Float, Device::Cpu))).unwrap();
            assert_eq!(out.size(), [2, 3, 9, 2 * stride, 3 * stride], "stride {stride}");
        }
    }

    #[test]
    fn a_frame_depends_on_earlier_latents_only() {
        let (d, _) = LightDecoder::random(&tiny(16), Kind::Float, Device::Cpu, 1).unwrap();
        let z = Tensor::randn([1, 4, 3, 1, 1], (Kind::Float, Device::Cpu));
        let a = d.decode(&z).unwrap();
        // Change the last latent frame: the frames of the first two (1 + 4) stay, later ones move.
        let z2 = z.copy();
        let _ = z2.narrow(2, 2, 1).fill_(5.0);
        let b = d.decode(&z2).unwrap();
        let diff = (&a - &b).abs().amax([1, 3, 4], false).squeeze_dim(0);
        let diff: Vec<f64> = (0..9).map(|i| diff.double_value(&[i])).collect();
        assert!(diff[..5].iter().all(|&v| v == 0.0), "{diff:?}");
        assert!(diff[5..].iter().all(|&v| v > 0.0), "{diff:?}");
    }

    #[test]
    fn refuses_latents_of_another_shape_and_another_vae() {
        let (d, _) = LightDecoder::random(&tiny(16), Kind::Float, Device::Cpu, 0).unwrap();
        let e = d.decode(&Tensor::zeros([1, 5, 2, 1, 1], (Kind::Float, Device::Cpu))).unwrap_err();
        assert!(e.to_string().contains("[B, 4, T, h, w]"), "{e}");
        let vae = VaeConfig { z_dim: 4, ..VaeConfig::with_width(8, 8) };
        d.check_vae(&vae).unwrap();
        let e = d.check_vae(&vae.clone().with_spatial_stride(8).unwrap()).unwrap_err();
        assert!(e.to_string().contains("stride 16x4"), "{e}");
        let bad = LightDecoderConfig { spatial_stride: 32, ..tiny(16) };
        assert!(LightDecoder::random(&bad, Kind::Float, Device::Cpu, 0).is_err());
    }
}
