//! The Wan2.2 DiT (`WanModel`), TI2V variant: per-token timesteps, 3-axis RoPE self-attention,
//! cross-attention to a context, AdaLN-style modulation (`modulation + t_mod`, 6 vectors), a
//! modulated head. Field paths equal the Wan-native checkpoint keys.
//!
//! Precision: parameters and matmuls in the store's dtype (f32 or bf16); sinusoids, time MLP, RoPE
//! and the modulation sums in fp32; the residual stream, its norms and gates in fp32 as the official
//! code, or in the parameters' dtype as DiffSynth-Studio (`WanDit::residual`).
//!
//! Shape convention: tokens are frame-major (f, h', w') and every token of one latent frame
//! shares that frame's timestep (Wan TI2V and BWM give condition frames t=0, the rest t), so the
//! time embedding is computed per frame, [B, F, D], and broadcast over the frame's tokens; this is
//! the same arithmetic as the reference's per-token embedding.

use anyhow::{ensure, Result};
use tch::{Device, Kind, Tensor};

use crate::config::DitConfig;
use crate::nn::{attention, frame_addcmul, layer_norm, modulate, AffineLayerNorm, Linear, RmsNorm};
use crate::rope::Rope;
use crate::vb::{Init, Vb};
use crate::weights::WeightsError;

/// `nn.Sequential(Linear, act, Linear)` with parameters at `.0` and `.2`.
pub struct Mlp2 {
    pub l0: Linear,
    pub l2: Linear,
}

impl Mlp2 {
    pub fn new(vb: &Vb, in_dim: i64, hidden: i64, out_dim: i64) -> Result<Self, WeightsError> {
        Ok(Self { l0: Linear::new(&vb.pp(0), in_dim, hidden)?, l2: Linear::new(&vb.pp(2), hidden, out_dim)? })
    }
}

pub struct Attention {
    pub q: Linear,
    pub k: Linear,
    pub v: Linear,
    pub o: Linear,
    pub norm_q: RmsNorm,
    pub norm_k: RmsNorm,
    num_heads: i64,
}

impl Attention {
    fn new(vb: &Vb, cfg: &DitConfig) -> Result<Self, WeightsError> {
        let d = cfg.dim;
        Ok(Self {
            q: Linear::new(&vb.pp("q"), d, d)?,
            k: Linear::new(&vb.pp("k"), d, d)?,
            v: Linear::new(&vb.pp("v"), d, d)?,
            o: Linear::new(&vb.pp("o"), d, d)?,
            norm_q: RmsNorm::new(&vb.pp("norm_q"), d, cfg.eps)?,
            norm_k: RmsNorm::new(&vb.pp("norm_k"), d, cfg.eps)?,
            num_heads: cfg.num_heads,
        })
    }

    /// Self-attention with RoPE on q and k (after their RMSNorm).
    fn self_attention(&self, x: &Tensor, rope: &Rope) -> Tensor {
        let (b, l, d) = x.size3().expect("[B, L, D]");
        let x = &x.to_kind(self.q.weight.kind());
        let heads = |t: Tensor| t.view([b, l, self.num_heads, d / self.num_heads]);
        let q = rope.apply(&heads(self.norm_q.forward(&self.q.forward(x)))).view([b, l, d]);
        let k = rope.apply(&heads(self.norm_k.forward(&self.k.forward(x)))).view([b, l, d]);
        let v = self.v.forward(x);
        self.o.forward(&attention(&q, &k, &v, self.num_heads))
    }

    /// Cross-attention from x to the context (no positions, no mask).
    fn cross_attention(&self, x: &Tensor, context: &Tensor) -> Tensor {
        let q = self.norm_q.forward(&self.q.forward(x));
        let k = self.norm_k.forward(&self.k.forward(context));
        let v = self.v.forward(context);
        self.o.forward(&attention(&q, &k, &v, self.num_heads))
    }
}

/// `WanAttentionBlock`: norm1 -> self-attn, norm3 (affine) -> cross-attn, norm2 -> FFN.
pub struct Block {
    pub modulation: Tensor,
    pub self_attn: Attention,
    pub cross_attn: Attention,
    pub norm3: AffineLayerNorm,
    pub ffn: Mlp2,
    eps: f64,
}

impl Block {
    fn new(vb: &Vb, cfg: &DitConfig) -> Result<Self, WeightsError> {
        let std = 1.0 / (cfg.dim as f64).sqrt();
        Ok(Self {
            modulation: vb.get(&[1, 6, cfg.dim], "modulation", Init::Randn { std })?,
            self_attn: Attention::new(&vb.pp("self_attn"), cfg)?,
            cross_attn: Attention::new(&vb.pp("cross_attn"), cfg)?,
            norm3: AffineLayerNorm::new(&vb.pp("norm3"), cfg.dim, cfg.eps)?,
            ffn: Mlp2::new(&vb.pp("ffn"), cfg.dim, cfg.ffn_dim, cfg.dim)?,
            eps: cfg.eps,
        })
    }

    /// x: tokens [B, L, D] of the residual stream (fp32 or the parameters' dtype, see
    /// `WanDit::residual`) -> tokens of the same dtype. Each gate and residual add is one multiply-add.
    pub fn forward(&self, x: &Tensor, cond: &Conditioning) -> Tensor {
        let (b, l, d) = x.size3().expect("[B, L, D]");
        let f = cond.e0.size()[1];
        let per_frame = |t: &Tensor| t.view([b, f, l / f, d]);
        let tokens = |t: Tensor| t.view([b, l, d]);
        // [B, F, 6, D] -> six [B, F, 1, D]: shift/scale/gate for attention, then for the FFN; summed
        // in fp32, then in the residual stream's dtype.
        let m = (self.modulation.to_kind(Kind::Float).unsqueeze(0) + &cond.e0).unsqueeze(2).to_kind(x.kind());
        let m: Vec<Tensor> = (0..6).map(|i| m.select(3, i)).collect();

        let h = modulate(&per_frame(&layer_norm(x, None, self.eps)), &m[0], &m[1]);
        let y = self.self_attn.self_attention(&tokens(h), &cond.rope);
        let x = tokens(frame_addcmul(&per_frame(x), &per_frame(&y), &m[2]));

        let y = self.cross_attn.cross_attention(&self.norm3.forward(&x), &cond.context);
        let x = &x + y;

        let h = tokens(modulate(&per_frame(&layer_norm(&x, None, self.eps)), &m[3], &m[4]));
        let y = self.ffn.l2.forward(&self.ffn.l0.forward(&h).gelu("tanh"));
        tokens(frame_addcmul(&per_frame(&x), &per_frame(&y), &m[5]))
    }
}

/// The output head, modulated by the time embedding `e` (no SiLU).
pub struct Head {
    pub head: Linear,
    pub modulation: Tensor,
    eps: f64,
}

impl Head {
    fn new(vb: &Vb, cfg: &DitConfig) -> Result<Self, WeightsError> {
        let std = 1.0 / (cfg.dim as f64).sqrt();
        Ok(Self {
            head: Linear::new(&vb.pp("head"), cfg.dim, cfg.out_dim * cfg.patch_volume())?,
            modulation: vb.get(&[1, 2, cfg.dim], "modulation", Init::Randn { std })?,
            eps: cfg.eps,
        })
    }

    fn forward(&self, x: &Tensor, e: &Tensor) -> Tensor {
        let (b, l, d) = x.size3().expect("[B, L, D]");
        let f = e.size()[1];
        let m = (self.modulation.to_kind(Kind::Float).unsqueeze(0) + e.unsqueeze(2)).unsqueeze(2);
        let (shift, scale) = (m.select(3, 0), m.select(3, 1));
        let h = modulate(&layer_norm(x, None, self.eps).view([b, f, l / f, d]), &shift, &scale);
        self.head.forward(&h.view([b, l, d])).to_kind(Kind::Float)
    }
}

/// What conditions the DiT besides the latents and their timesteps.
pub struct DitInputs<'a> {
    /// [B, F, D], added to each latent frame's time embedding (BWM's actions).
    pub frame: Option<&'a Tensor>,
    /// [B, L, D], added to each token after the patch embedding (BWM's hand map).
    pub tokens: Option<&'a Tensor>,
    /// [B, Lc, D]: the cross-attention context.
    pub context: &'a Tensor,
}

/// Everything the blocks need besides the token stream.
pub struct Conditioning {
    /// Time embedding per latent frame [B, F, D] (fp32), after any per-frame additions.
    pub e: Tensor,
    /// Its 6-way projection [B, F, 6, D] (fp32).
    pub e0: Tensor,
    /// Cross-attention context [B, Lc, D] in the parameters' dtype.
    pub context: Tensor,
    pub rope: Rope,
    /// Token grid (f, h', w').
    pub grid: (i64, i64, i64),
}

pub struct WanDit {
    pub cfg: DitConfig,
    /// Conv3d(in_dim, dim, kernel = stride = patch) weight [D, C, pt, ph, pw], applied as a
    /// linear map over flattened patches (input index c*pt*ph*pw + (t*ph + h)*pw + w).
    pub patch_embedding_weight: Tensor,
    pub patch_embedding_bias: Tensor,
    /// Unused when actions replace the text context; present in official checkpoints.
    pub text_embedding: Option<Mlp2>,
    pub time_embedding: Mlp2,
    pub time_projection: Linear,
    pub blocks: Vec<Block>,
    pub head: Head,
    /// dtype of the token stream between blocks, its norms, modulation and gates: fp32 (the
    /// official Wan code) or the parameters' dtype (DiffSynth-Studio, which the BWM release trains
    /// with: half the memory traffic of the element-wise work). Set after building; fp32 by default.
    pub residual: Kind,
    /// The rotations of every token grid and device seen. They are computed on the host, so a
    /// forward that made them each time would copy them to the device and wait for it every step
    /// (nor could a CUDA graph record that); they are kept for the model's life, since a recorded
    /// graph reads them at their address.
    rope: std::sync::Mutex<Vec<((i64, i64, i64), Device, Rope)>>,
}

impl WanDit {
    pub fn new(vb: &Vb, cfg: &DitConfig) -> Result<Self> {
        cfg.validate()?;
        let [pt, ph, pw] = cfg.patch_size;
        let pe = vb.pp("patch_embedding");
        let bound = 1.0 / ((cfg.in_dim * pt * ph * pw) as f64).sqrt();
        let text_embedding = if vb.provides("text_embedding.0.weight") {
            Some(Mlp2::new(&vb.pp("text_embedding"), cfg.text_dim, cfg.dim, cfg.dim)?)
        } else {
            None
        };
        Ok(Self {
            cfg: cfg.clone(),
            patch_embedding_weight: pe.get(&[cfg.dim, cfg.in_dim, pt, ph, pw], "weight", Init::Uniform { bound })?,
            patch_embedding_bias: pe.get(&[cfg.dim], "bias", Init::Uniform { bound })?,
            text_embedding,
            time_embedding: Mlp2::new(&vb.pp("time_embedding"), cfg.freq_dim, cfg.dim, cfg.dim)?,
            time_projection: Linear::new(&vb.pp("time_projection").pp(1), cfg.dim, 6 * cfg.dim)?,
            blocks: (0..cfg.num_layers)
                .map(|i| Block::new(&vb.pp("blocks").pp(i), cfg))
                .collect::<Result<_, _>>()?,
            head: Head::new(&vb.pp("head"), cfg)?,
            residual: Kind::Float,
            rope: Default::default(),
        })
    }

    /// The rotary embedding of `grid` on `device` (made once per grid and device).
    fn rope_for(&self, grid: (i64, i64, i64), device: Device) -> Rope {
        let mut kept = self.rope.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        if let Some((_, _, rope)) = kept.iter().find(|(g, d, _)| *g == grid && *d == device) {
            return rope.shallow_clone();
        }
        let rope = Rope::new(grid, self.cfg.rope_axes(), self.cfg.rope_theta, device);
        kept.push((grid, device, rope.shallow_clone()));
        rope
    }

    /// Token grid of latents [B, C, F, H, W], or an error saying what was expected.
    pub fn token_grid(&self, latents: &Tensor) -> Result<(i64, i64, i64)> {
        let s = latents.size();
        let [pt, ph, pw] = self.cfg.patch_size;
        ensure!(s.len() == 5, "latents must be [B, {}, F, H, W], got shape {:?}", self.cfg.in_dim, s);
        ensure!(
            s[1] == self.cfg.in_dim,
            "latents have {} channels, the DiT expects in_dim = {}",
            s[1],
            self.cfg.in_dim
        );
        ensure!(
            s[2] % pt == 0 && s[3] % ph == 0 && s[4] % pw == 0 && s[2] > 0 && s[3] > 0 && s[4] > 0,
            "latent size F x H x W = {} x {} x {} must be a positive multiple of the patch size {:?}",
            s[2],
            s[3],
            s[4],
            self.cfg.patch_size
        );
        Ok((s[2] / pt, s[3] / ph, s[4] / pw))
    }

    /// Latents [B, C, F, H, W] -> tokens [B, L, D] (frame-major) in the residual stream's dtype.
    pub fn patchify(&self, latents: &Tensor) -> Result<Tensor> {
        let (f, h, w) = self.token_grid(latents)?;
        let b = latents.size()[0];
        let [pt, ph, pw] = self.cfg.patch_size;
        let c = self.cfg.in_dim;
        let patches = latents
            .to_kind(self.patch_embedding_weight.kind())
            .view(&[b, c, f, pt, h, ph, w, pw][..])
            .permute([0, 2, 4, 6, 1, 3, 5, 7])
            .reshape([b, f * h * w, c * pt * ph * pw]);
        let weight = self.patch_embedding_weight.reshape([self.cfg.dim, c * pt * ph * pw]);
        Ok(patches.linear(&weight, Some(&self.patch_embedding_bias)).to_kind(self.residual))
    }

    /// Tokens [B, L, pt*ph*pw*C] -> [B, C, F, H, W]; channels fastest within a patch.
    pub fn unpatchify(&self, y: &Tensor, grid: (i64, i64, i64)) -> Tensor {
        let (f, h, w) = grid;
        let b = y.size()[0];
        let [pt, ph, pw] = self.cfg.patch_size;
        let c = self.cfg.out_dim;
        y.view(&[b, f, h, w, pt, ph, pw, c][..])
            .permute([0, 7, 1, 4, 2, 5, 3, 6])
            .reshape([b, c, f * pt, h * ph, w * pw])
    }

    /// Sinusoidal embedding of timesteps [..] -> [.., freq_dim] in fp32: cos first, then sin,
    /// frequencies 10000^(-k/half), evaluated in f64.
    pub fn sinusoid(&self, t: &Tensor) -> Tensor {
        let half = self.cfg.freq_dim / 2;
        let k = Tensor::arange(half, (Kind::Double, t.device()));
        let freqs = (k * (-(10000f64).ln() / half as f64)).exp();
        let arg = t.to_kind(Kind::Double).unsqueeze(-1) * freqs;
        Tensor::cat(&[arg.cos(), arg.sin()], -1).to_kind(Kind::Float)
    }

    /// Builds the token stream and conditioning. `frame_timesteps` [B, F] (one per token frame,
    /// 0..1000 scale); `inputs` the per-frame and per-token additions and the context.
    pub fn prepare(&self, latents: &Tensor, frame_timesteps: &Tensor, inputs: &DitInputs) -> Result<(Tensor, Conditioning)> {
        let DitInputs { frame: frame_embedding, tokens, context } = *inputs;
        let grid = self.token_grid(latents)?;
        let b = latents.size()[0];
        ensure!(
            frame_timesteps.size() == [b, grid.0],
            "timesteps must be [B, F] = [{b}, {}] (one per latent frame), got {:?}",
            grid.0,
            frame_timesteps.size()
        );
        let cs = context.size();
        ensure!(
            cs.len() == 3 && cs[0] == b && cs[2] == self.cfg.dim,
            "context must be [{b}, L, {}], got {:?}",
            self.cfg.dim,
            cs
        );
        let mut x = self.patchify(latents)?;
        if let Some(add) = tokens {
            let l = grid.0 * grid.1 * grid.2;
            ensure!(add.size() == [b, l, self.cfg.dim], "per-token embedding must be [{b}, {l}, {}], got {:?}", self.cfg.dim, add.size());
            x = x + add.to_kind(self.residual);
        }
        let mut e = self.time_embedding.l2.forward_f32(&self.time_embedding.l0.forward_f32(&self.sinusoid(frame_timesteps)).silu());
        if let Some(add) = frame_embedding {
            ensure!(
                add.size() == [b, grid.0, self.cfg.dim],
                "per-frame embedding must be [{b}, {}, {}], got {:?}",
                grid.0,
                self.cfg.dim,
                add.size()
            );
            e = e + add.to_kind(Kind::Float);
        }
        let e0 = self.time_projection.forward_f32(&e.silu()).unflatten(2, [6, self.cfg.dim]);
        let rope = self.rope_for(grid, latents.device());
        let context = context.to_kind(self.patch_embedding_weight.kind());
        Ok((x, Conditioning { e, e0, context, rope, grid }))
    }

    /// The head and unpatchify: tokens -> fp32 prediction [B, out_dim, F, H, W].
    pub fn finish(&self, x: &Tensor, cond: &Conditioning) -> Tensor {
        self.unpatchify(&self.head.forward(x, &cond.e), cond.grid)
    }

    /// Full forward; `trace` sees named intermediates (`t_emb` and `t_mod` per frame, `tokens_in`,
    /// `block{i}_out`).
    pub fn forward_traced(
        &self,
        latents: &Tensor,
        frame_timesteps: &Tensor,
        inputs: &DitInputs,
        trace: &mut dyn FnMut(&str, &Tensor),
    ) -> Result<Tensor> {
        let (mut x, cond) = self.prepare(latents, frame_timesteps, inputs)?;
        trace("t_emb", &cond.e);
        trace("t_mod", &cond.e0);
        trace("tokens_in", &x);
        for (i, block) in self.blocks.iter().enumerate() {
            x = block.forward(&x, &cond);
            trace(&format!("block{i}_out"), &x);
        }
        Ok(self.finish(&x, &cond))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vb::{with_seed, ParamStore};
    use tch::Device;

    #[test]
    fn the_rotations_are_made_once_per_grid_and_kept() {
        let dit = with_seed(0, || WanDit::new(&ParamStore::random(Kind::Float, Device::Cpu).root(), &DitConfig::tiny())).unwrap();
        let first = dit.rope_for((3, 2, 2), Device::Cpu);
        assert!(first.same_tensor(&dit.rope_for((3, 2, 2), Device::Cpu)), "the same grid reuses its rotations");
        let other = dit.rope_for((2, 2, 2), Device::Cpu);
        assert!(!other.same_tensor(&first));
        assert!(first.same_tensor(&dit.rope_for((3, 2, 2), Device::Cpu)), "another grid does not evict the first");
        let fresh = Rope::new((3, 2, 2), dit.cfg.rope_axes(), dit.cfg.rope_theta, Device::Cpu);
        let x = Tensor::randn([1, 12, dit.cfg.num_heads, dit.cfg.dim / dit.cfg.num_heads], (Kind::Float, Device::Cpu));
        assert!(first.apply(&x).equal(&fresh.apply(&x)), "the kept rotations are the grid's");
    }
}
