//! The BWM world model: the Wan2.2 DiT driven by the action encoder instead of text.

use std::path::Path;
use std::rc::Rc;

use anyhow::Result;
use tch::{Device, Kind, Tensor};

use crate::action::{ActionEmbedding, ActionEncoder};
use crate::config::ModelConfig;
use crate::dit::WanDit;
use crate::vb::ParamStore;
use crate::weights::{RenamedSource, SafetensorsSource, WeightSource};

/// Key layouts of checkpoints this model loads directly.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// Wan-native DiT names at the root, the action encoder under `action_encoder.`.
    WanNative,
    /// The public BWM release (`step-12000.safetensors`): Wan-native DiT names without
    /// `text_embedding`, the action encoder under `pipe.action_encoder.`.
    BwmRelease,
}

/// Keys the action-conditioned model may find absent or leave unused.
pub const ACTION_MODE_OPTIONAL: &[&str] = &["text_embedding."];

pub struct BwmModel {
    pub cfg: ModelConfig,
    pub dit: WanDit,
    pub action_encoder: ActionEncoder,
    pub store: Rc<ParamStore>,
}

impl BwmModel {
    /// Builds the module tree from `store` (random, shape-only, or a weight file).
    pub fn build(store: &Rc<ParamStore>, cfg: &ModelConfig) -> Result<Self> {
        Self::build_converted(store, cfg, |_| Ok(()))
    }

    /// As `build`, applying `convert` (conversions from outside the model, `crate::convert`) to the
    /// built tree before the weight file's keys are checked: parameters a conversion adds may come
    /// from the file.
    pub fn build_converted(store: &Rc<ParamStore>, cfg: &ModelConfig, convert: impl FnOnce(&mut Self) -> Result<()>) -> Result<Self> {
        cfg.validate()?;
        let root = store.root();
        let dit = WanDit::new(&root, &cfg.dit)?;
        let action_encoder = ActionEncoder::new(&root.pp("action_encoder"), &cfg.action, cfg.dit.dim)?;
        let mut model = Self { cfg: cfg.clone(), dit, action_encoder, store: store.clone() };
        convert(&mut model)?;
        store.check_all_consumed()?;
        Ok(model)
    }

    /// Random weights drawn after seeding libtorch's generator with `seed` (`vb::with_seed`).
    pub fn random(cfg: &ModelConfig, kind: Kind, device: Device, seed: i64) -> Result<Self> {
        crate::vb::with_seed(seed, || Self::build(&ParamStore::random(kind, device), cfg))
    }

    /// Weights read by name from a safetensors file, shard index or directory.
    pub fn load(path: &Path, layout: Layout, cfg: &ModelConfig, kind: Kind, device: Device) -> Result<Self> {
        let file = SafetensorsSource::open(path)?;
        let source: Box<dyn WeightSource> = match layout {
            Layout::WanNative => Box::new(file),
            Layout::BwmRelease => Box::new(RenamedSource::new(file, |k| {
                Some(k.strip_prefix("pipe.").unwrap_or(k).to_string())
            })),
        };
        let store = ParamStore::from_weights(source, ACTION_MODE_OPTIONAL, kind, device);
        Self::build(&store, cfg)
    }

    /// Velocity prediction [B, C, F, H, W] (fp32) from latents [B, C, F, H, W], per-latent-frame
    /// timesteps [B, F] and normalized actions [B, 1+4k, d_a].
    pub fn forward(&self, latents: &Tensor, frame_timesteps: &Tensor, actions: &Tensor) -> Result<Tensor> {
        self.forward_traced(latents, frame_timesteps, actions, &mut |_, _| {})
    }

    /// As `forward`, the samples whose `keep` `[B]` entry is 0 given the null action condition
    /// (`ActionEmbedding::keep`); `keep` None conditions every sample.
    pub fn forward_keeping(&self, latents: &Tensor, frame_timesteps: &Tensor, actions: &Tensor, keep: Option<&Tensor>) -> Result<Tensor> {
        self.forward_with(latents, frame_timesteps, actions, keep, &mut |_, _| {})
    }

    /// The action embedding of `actions` for `latents`, checked to cover its latent frames, with
    /// the null condition where `keep` is 0.
    pub fn embed_actions(&self, latents: &Tensor, actions: &Tensor, keep: Option<&Tensor>) -> Result<ActionEmbedding> {
        let emb = self.action_encoder.forward(actions, self.dit.token_grid(latents)?)?;
        match keep {
            Some(k) => emb.keep(k),
            None => Ok(emb),
        }
    }

    /// As `forward`, showing intermediates to `trace` (`action_context`, `action_mod`, then the
    /// DiT's).
    pub fn forward_traced(
        &self,
        latents: &Tensor,
        frame_timesteps: &Tensor,
        actions: &Tensor,
        trace: &mut dyn FnMut(&str, &Tensor),
    ) -> Result<Tensor> {
        self.forward_with(latents, frame_timesteps, actions, None, trace)
    }

    fn forward_with(
        &self,
        latents: &Tensor,
        frame_timesteps: &Tensor,
        actions: &Tensor,
        keep: Option<&Tensor>,
        trace: &mut dyn FnMut(&str, &Tensor),
    ) -> Result<Tensor> {
        let emb = self.embed_actions(latents, actions, keep)?;
        trace("action_context", &emb.context);
        trace("action_mod", &emb.frame);
        if let Some(tokens) = &emb.tokens {
            trace("action_tokens", tokens);
        }
        self.dit.forward_traced(latents, frame_timesteps, &emb.dit_inputs(), trace)
    }
}

/// Per-latent-frame timesteps [B, F]: 0 on the first `condition_frames` frames, `t[b]` after.
pub fn frame_timesteps(t: &Tensor, frames: i64, condition_frames: i64) -> Tensor {
    let b = t.size()[0];
    let mask = Tensor::cat(
        &[
            Tensor::zeros([condition_frames], (Kind::Float, t.device())),
            Tensor::ones([frames - condition_frames], (Kind::Float, t.device())),
        ],
        0,
    );
    t.to_kind(Kind::Float).view([b, 1]) * mask.view([1, frames])
}
