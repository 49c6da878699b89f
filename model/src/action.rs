//! The BWM action encoder (`WanVideoActionEncoder`, ti2v2 path). `action_mlp1` turns every pixel
//! frame's action into one cross-attention token; `action_mlp2` turns each group of G actions
//! (after prepending P copies of a_0) into one vector per latent frame, added to the time embedding.
//! With `fourier_bands` B > 0 both see each action value with its Fourier features.

use anyhow::{ensure, Result};
use tch::Tensor;

use crate::config::ActionConfig;
use crate::dit::Mlp2;
use crate::vb::Vb;

pub struct ActionEncoder {
    pub cfg: ActionConfig,
    /// Linear(e, D) -> GELU (exact) -> Linear(D, D), e = d_a * (1 + 2B)
    pub action_mlp1: Mlp2,
    /// Linear(G*e, G*D) -> SiLU -> Linear(G*D, D)
    pub action_mlp2: Mlp2,
}

/// What the encoder gives the DiT.
pub struct ActionEmbedding {
    /// [B, F_pixel, D]: the cross-attention context.
    pub context: Tensor,
    /// [B, F_latent, D]: added to the time embedding of each latent frame.
    pub frame: Tensor,
    /// The latent frame of each context token, for the cross-attention's temporal rotation
    /// (`ActionConfig::temporal_rope`); None: the context has no positions (BWM).
    pub context_frames: Option<Vec<i64>>,
}

impl ActionEmbedding {
    /// The embedding with every sample whose `keep` `[B]` entry is 0 given the null condition: no
    /// action tokens to attend to (zero context) and no per-frame action term. Training on it for a
    /// share of samples (`objective.action_dropout`) teaches the model the action-free prediction that
    /// classifier-free guidance contrasts with.
    pub fn keep(&self, keep: &Tensor) -> Result<ActionEmbedding> {
        let b = self.context.size()[0];
        ensure!(keep.size() == [b], "the action keep mask must be [{b}], got {:?}", keep.size());
        let mask = |t: &Tensor| t * keep.to_device(t.device()).to_kind(t.kind()).view([b, 1, 1]);
        Ok(ActionEmbedding { context: mask(&self.context), frame: mask(&self.frame), context_frames: self.context_frames.clone() })
    }
}

impl ActionEncoder {
    pub fn new(vb: &Vb, cfg: &ActionConfig, dim: i64) -> Result<Self> {
        cfg.validate()?;
        let (da, g) = (cfg.encoded_dim(), cfg.group);
        Ok(Self {
            cfg: cfg.clone(),
            action_mlp1: Mlp2::new(&vb.pp("action_mlp1"), da, dim, dim)?,
            action_mlp2: Mlp2::new(&vb.pp("action_mlp2"), g * da, g * dim, dim)?,
        })
    }

    /// actions [B, F, d_a], normalized, with F = G*k + (G - P).
    pub fn forward(&self, actions: &Tensor) -> Result<ActionEmbedding> {
        let s = actions.size();
        ensure!(
            s.len() == 3 && s[2] == self.cfg.action_dim,
            "actions must be [B, F, {}], got shape {:?}",
            self.cfg.action_dim,
            s
        );
        let latent_frames = self.cfg.latent_frames(s[1])?;
        let actions = fourier_features(actions, self.cfg.fourier_bands).to_kind(self.action_mlp1.l0.weight.kind());
        let e = self.cfg.encoded_dim();
        let context = self.action_mlp1.l2.forward(&self.action_mlp1.l0.forward(&actions).gelu("none"));
        let first = actions.narrow(1, 0, 1).repeat([1, self.cfg.prepend, 1]);
        let grouped = Tensor::cat(&[first, actions], 1).reshape([s[0], latent_frames, self.cfg.group * e]);
        let frame = self.action_mlp2.l2.forward(&self.action_mlp2.l0.forward(&grouped).silu());
        let context_frames = self.cfg.temporal_rope.then(|| self.cfg.action_latent_frames(s[1]));
        Ok(ActionEmbedding { context, frame, context_frames })
    }
}

/// [..., d] -> [..., d * (1 + 2B)]: each value a, then sin(2^k*pi*a) for k < B, then cos(2^k*pi*a),
/// computed in fp32 whatever the input's kind; the input unchanged when B = 0.
pub fn fourier_features(actions: &Tensor, bands: i64) -> Tensor {
    if bands == 0 {
        return actions.shallow_clone();
    }
    let a = actions.to_kind(tch::Kind::Float);
    let freqs = Tensor::arange(bands, (tch::Kind::Float, a.device())).exp2() * std::f64::consts::PI;
    let mut shape = a.size();
    let d = shape.pop().unwrap_or(1);
    shape.push(d * bands);
    let phase = (a.unsqueeze(-1) * freqs).reshape(&shape[..]);
    Tensor::cat(&[a, phase.sin(), phase.cos()], -1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vb::{with_seed, ParamStore};
    use tch::{Device, Kind};

    #[test]
    fn fourier_features_are_each_value_then_its_sines_then_cosines() {
        let a = Tensor::from_slice(&[0.5f32, -0.25]).view([1, 1, 2]);
        let f = fourier_features(&a, 2);
        assert_eq!(f.size(), [1, 1, 10]);
        let got: Vec<f32> = f.flatten(0, -1).try_into().unwrap();
        let pi = std::f32::consts::PI;
        let want = [
            0.5,
            -0.25,
            (0.5 * pi).sin(),
            (pi).sin(),
            (-0.25 * pi).sin(),
            (-0.5 * pi).sin(),
            (0.5 * pi).cos(),
            (pi).cos(),
            (-0.25 * pi).cos(),
            (-0.5 * pi).cos(),
        ];
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{got:?} != {want:?}");
        }
        assert!(fourier_features(&a, 0).equal(&a));
    }

    fn encoder(bands: i64) -> ActionEncoder {
        let cfg = ActionConfig { action_dim: 2, prepend: 3, group: 4, fourier_bands: bands, temporal_rope: false };
        ActionEncoder::new(&ParamStore::random(Kind::Float, Device::Cpu).root(), &cfg, 16).unwrap()
    }

    #[test]
    fn the_encoder_takes_fourier_features_of_each_action() {
        let enc = encoder(3);
        assert_eq!(enc.action_mlp1.l0.weight.size(), [16, 2 * 7]);
        assert_eq!(enc.action_mlp2.l0.weight.size(), [64, 4 * 2 * 7]);
        let out = enc.forward(&Tensor::rand([2, 9, 2], (Kind::Float, Device::Cpu))).unwrap();
        assert_eq!((out.context.size(), out.frame.size()), (vec![2, 9, 16], vec![2, 3, 16]));
    }

    /// Why the features exist: the outcome of a command can flip within a centimetre (a hand in
    /// front of a handle, or on it), a step in one normalized action value. Fitting such a step
    /// through the encoder's first MLP, the plain input leaves a ramp where the features give
    /// the step.
    #[test]
    fn fourier_features_let_the_encoder_fit_a_sharp_step_in_one_command() {
        let x = Tensor::linspace(-1.0, 1.0, 401, (Kind::Float, Device::Cpu)).view([401, 1, 1]);
        let target = x.gt(0.3).to_kind(Kind::Float).expand([401, 1, 16], false);
        // Adam (lr 1e-2) on the encoder's parameters, the same seed for both inputs.
        let fit = |bands: i64| -> f64 {
            let store = ParamStore::random(Kind::Float, Device::Cpu);
            let cfg = ActionConfig { action_dim: 1, prepend: 0, group: 1, fourier_bands: bands, temporal_rope: false };
            let enc = with_seed(0, || ActionEncoder::new(&store.root(), &cfg, 16)).unwrap();
            let params: Vec<Tensor> = store.named_parameters().into_iter().map(|(_, t)| t.set_requires_grad(true)).collect();
            let mut moments: Vec<(Tensor, Tensor)> = params.iter().map(|p| (p.zeros_like(), p.zeros_like())).collect();
            let mut loss = f64::NAN;
            for step in 1..=300 {
                for p in &params {
                    let mut g = p.grad();
                    if g.defined() {
                        let _ = g.zero_();
                    }
                }
                let l = (enc.forward(&x).unwrap().context - &target).square().mean(None);
                l.backward();
                loss = l.double_value(&[]);
                tch::no_grad(|| {
                    for (p, (m, v)) in params.iter().zip(moments.iter_mut()) {
                        let g = p.grad();
                        if !g.defined() {
                            continue; // action_mlp2: not on the path to the context
                        }
                        *m = &*m * 0.9 + &g * 0.1;
                        *v = &*v * 0.999 + g.square() * 0.001;
                        let m_hat = &*m / (1.0 - 0.9f64.powi(step));
                        let v_hat = &*v / (1.0 - 0.999f64.powi(step));
                        let _ = p.shallow_clone().f_sub_(&(m_hat / (v_hat.sqrt() + 1e-8) * 1e-2)).unwrap();
                    }
                });
            }
            loss
        };
        let (plain, fourier) = (fit(0), fit(6));
        assert!(fourier < plain / 4.0, "the step's MSE after 300 steps: plain {plain:.5}, Fourier {fourier:.5}");
    }
}
