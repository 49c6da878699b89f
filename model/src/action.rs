//! The BWM action encoder (`WanVideoActionEncoder`, ti2v2 path). `action_mlp1` turns every pixel
//! frame's action into one cross-attention token; `action_mlp2` turns each group of G actions
//! (after prepending P copies of a_0) into one vector per latent frame, added to the time embedding;
//! `hand_map`, where the config asks for it, draws the commanded hands into the token grid
//! (`crate::hand_map`).

use anyhow::{ensure, Result};
use tch::Tensor;

use crate::config::ActionConfig;
use crate::dit::{DitInputs, Mlp2};
use crate::hand_map::HandMap;
use crate::vb::Vb;

pub struct ActionEncoder {
    pub cfg: ActionConfig,
    /// Linear(d_a, D) -> GELU (exact) -> Linear(D, D)
    pub action_mlp1: Mlp2,
    /// Linear(G*d_a, G*D) -> SiLU -> Linear(G*D, D)
    pub action_mlp2: Mlp2,
    pub hand_map: Option<HandMap>,
}

/// What the encoder gives the DiT.
pub struct ActionEmbedding {
    /// [B, F_pixel, D]: the cross-attention context.
    pub context: Tensor,
    /// [B, F_latent, D]: added to the time embedding of each latent frame.
    pub frame: Tensor,
    /// [B, L, D]: added to each token (the hand map), where the model has one.
    pub tokens: Option<Tensor>,
}

impl ActionEmbedding {
    /// What the DiT takes of it.
    pub fn dit_inputs(&self) -> DitInputs<'_> {
        DitInputs { frame: Some(&self.frame), tokens: self.tokens.as_ref(), context: &self.context }
    }

    /// The embedding with every sample whose `keep` `[B]` entry is 0 given the null condition: no
    /// action tokens to attend to (zero context) and no per-frame action term. Training on it for a
    /// share of samples (`objective.action_dropout`) teaches the model the action-free prediction that
    /// classifier-free guidance contrasts with.
    pub fn keep(&self, keep: &Tensor) -> Result<ActionEmbedding> {
        let b = self.context.size()[0];
        ensure!(keep.size() == [b], "the action keep mask must be [{b}], got {:?}", keep.size());
        let mask = |t: &Tensor| t * keep.to_device(t.device()).to_kind(t.kind()).view([b, 1, 1]);
        Ok(ActionEmbedding { context: mask(&self.context), frame: mask(&self.frame), tokens: self.tokens.as_ref().map(mask) })
    }
}

impl ActionEncoder {
    pub fn new(vb: &Vb, cfg: &ActionConfig, dim: i64) -> Result<Self> {
        cfg.validate()?;
        let (da, g) = (cfg.action_dim, cfg.group);
        Ok(Self {
            cfg: cfg.clone(),
            action_mlp1: Mlp2::new(&vb.pp("action_mlp1"), da, dim, dim)?,
            action_mlp2: Mlp2::new(&vb.pp("action_mlp2"), g * da, g * dim, dim)?,
            hand_map: cfg.hand_map.as_ref().map(|map| HandMap::new(&vb.pp("hand_map"), map, da, g, dim)).transpose()?,
        })
    }

    /// actions [B, F, d_a], normalized, with F = G*k + (G - P), for the DiT's token grid `grid`
    /// (f, h', w'), with f = k + 1.
    pub fn forward(&self, actions: &Tensor, grid: (i64, i64, i64)) -> Result<ActionEmbedding> {
        let s = actions.size();
        ensure!(
            s.len() == 3 && s[2] == self.cfg.action_dim,
            "actions must be [B, F, {}], got shape {:?}",
            self.cfg.action_dim,
            s
        );
        let latent_frames = self.cfg.latent_frames(s[1])?;
        ensure!(
            latent_frames == grid.0,
            "actions for {} pixel frames cover {latent_frames} latent frames, but the latents have {}",
            s[1],
            grid.0
        );
        let actions = actions.to_kind(self.action_mlp1.l0.weight.kind());
        let context = self.action_mlp1.l2.forward(&self.action_mlp1.l0.forward(&actions).gelu("none"));
        let first = actions.narrow(1, 0, 1).repeat([1, self.cfg.prepend, 1]);
        let grouped = Tensor::cat(&[first, actions], 1).reshape([s[0], latent_frames, self.cfg.group * s[2]]);
        let frame = self.action_mlp2.l2.forward(&self.action_mlp2.l0.forward(&grouped).silu());
        let tokens = match &self.hand_map {
            Some(map) => Some(map.forward(&grouped.view([s[0], latent_frames, self.cfg.group, s[2]]), grid)?),
            None => None,
        };
        Ok(ActionEmbedding { context, frame, tokens })
    }
}
