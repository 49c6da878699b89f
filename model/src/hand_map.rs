//! The commanded hand drawn into the token grid: an addition to the BWM action encoder (`hand_map`
//! under `action_encoder.`; the BWM release has none). The cross-attention and the per-frame term
//! give every token the actions alike, as numbers; to draw contact, a token has to know where the
//! hand is commanded *relative to itself*, to within a fraction of its width. Here each hand's
//! commanded position is mapped onto the image plane by a projection learned with the model (the
//! camera is not given), its offset from every token's centre is written as sines and cosines at
//! periods of 1/2, 1, 2, ... tokens and a Gaussian of the distance, and a small MLP turns those,
//! with the latent frame's actions, into a vector added to the token (IRASim and Cosmos-Predict2's
//! action model condition per frame, as the per-frame term does; iMaC and EA-WM draw the projected
//! end effector into the frame, which this learns instead of being given).
//!
//! The MLP's output layer starts at zero, so at step 0 the model computes what it computes without
//! the map.

use anyhow::{ensure, Result};
use tch::{Kind, Tensor};

use crate::config::HandMapConfig;
use crate::dit::Mlp2;
use crate::nn::Linear;
use crate::vb::Vb;

pub struct HandMap {
    pub cfg: HandMapConfig,
    /// One `Linear(3, 2)` per hand at `project.{n}`: its commanded position (normalized as the
    /// actions are) to the image plane, -1..1 across the token grid's width (first) and height.
    pub project: Vec<Linear>,
    /// `Linear(features, D) -> GELU (exact) -> Linear(D, D)`, the last zero at init.
    pub mlp: Mlp2,
    action_dim: i64,
    group: i64,
}

impl HandMap {
    /// The map of a model of width `dim` whose actions have `action_dim` entries, `group` per
    /// latent frame.
    pub fn new(vb: &Vb, cfg: &HandMapConfig, action_dim: i64, group: i64, dim: i64) -> Result<Self> {
        cfg.validate(action_dim)?;
        let features = Self::features(cfg, action_dim, group);
        let project = (0..cfg.hands.len()).map(|n| Linear::new(&vb.pp("project").pp(n), 3, 2)).collect::<Result<_, _>>()?;
        let mlp = Mlp2 { l0: Linear::new(&vb.pp("mlp").pp(0), features, dim)?, l2: Linear::zeros(&vb.pp("mlp").pp(2), dim, dim)? };
        Ok(Self { cfg: cfg.clone(), project, mlp, action_dim, group })
    }

    /// Inputs of the MLP per token: per hand and action of the group, 4 per period (sine and cosine
    /// of each axis) and the Gaussian; then the group's actions.
    fn features(cfg: &HandMapConfig, action_dim: i64, group: i64) -> i64 {
        cfg.hands.len() as i64 * group * (4 * cfg.periods + 1) + group * action_dim
    }

    /// `grouped` actions [B, F, G, d_a] (a latent frame's G actions, normalized) and the token grid
    /// `(f, h, w)` -> [B, f*h*w, D] in the parameters' dtype, frame-major as the DiT's tokens.
    pub fn forward(&self, grouped: &Tensor, grid: (i64, i64, i64)) -> Result<Tensor> {
        let x = self.inputs(grouped, grid)?;
        Ok(self.mlp.l2.forward(&self.mlp.l0.forward(&x).gelu("none")))
    }

    /// What the MLP reads per token, [B, f*h*w, features] (fp32): per hand, per action of the
    /// group, by period the sines of the x and y offsets then their cosines, and the Gaussian of the
    /// distance; then the group's actions.
    pub fn inputs(&self, grouped: &Tensor, grid: (i64, i64, i64)) -> Result<Tensor> {
        let s = grouped.size();
        let (f, h, w) = grid;
        ensure!(
            s == [s[0], f, self.group, self.action_dim],
            "the hand map needs grouped actions [B, {f}, {}, {}] for a token grid of {f} frames, got {:?}",
            self.group,
            self.action_dim,
            s
        );
        let b = s[0];
        let device = grouped.device();
        let actions = grouped.to_kind(Kind::Float);
        // Token centres, -1..1 across the grid, as [1, 1, 1, h, w] (x) and (y). Made on the device
        // (no copy from the host, which a recorded CUDA graph could not hold).
        let centre = |n: i64| (Tensor::arange(n, (Kind::Float, device)) * 2.0 + 1.0) / n as f64 - 1.0;
        let (cx, cy) = (centre(w).view([1, 1, 1, 1, w]), centre(h).view([1, 1, 1, h, 1]));
        let periods: Vec<f64> = (0..self.cfg.periods).map(|k| 0.5 * 2f64.powi(k as i32)).collect();
        let mut parts = Vec::with_capacity(self.project.len() + 1);
        for (hand, project) in self.cfg.hands.iter().zip(&self.project) {
            let position = Tensor::stack(&hand.map(|i| actions.select(3, i)), -1);
            // [B, f, G, 2]: where the hand is commanded, on the image plane.
            let at = project.forward_f32(&position).view([b, f, self.group, 1, 1, 2]);
            // Offsets in tokens, [B, f, G, h, w, 2].
            let size = [b, f, self.group, h, w];
            let (ox, oy) = ((at.select(5, 0) - &cx) * (w as f64 / 2.0), (at.select(5, 1) - &cy) * (h as f64 / 2.0));
            let offset = Tensor::stack(&[ox.expand(size, false), oy.expand(size, false)], -1);
            let gauss = (offset.square().sum_dim_intlist(-1, true, Kind::Float) * -0.5).exp();
            let mut waves = Vec::with_capacity(2 * periods.len());
            for p in &periods {
                let arg = &offset * (2.0 * std::f64::consts::PI / p);
                waves.push(arg.sin());
                waves.push(arg.cos());
            }
            // [B, f, h, w, G * (4 * periods + 1)]
            let one = Tensor::cat(&[Tensor::cat(&waves, -1), gauss], -1).permute([0, 1, 3, 4, 2, 5]).reshape([b, f, h, w, -1]);
            parts.push(one);
        }
        parts.push(actions.reshape([b, f, 1, 1, self.group * self.action_dim]).expand([b, f, h, w, self.group * self.action_dim], false));
        Ok(Tensor::cat(&parts, -1).reshape([b, f * h * w, -1]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{ActionConfig, DitConfig, ModelConfig};
    use crate::vb::ParamStore;
    use crate::weights::TensorSource;
    use crate::BwmModel;
    use tch::Device;

    fn config(hand_map: Option<HandMapConfig>) -> ModelConfig {
        ModelConfig { dit: DitConfig::tiny(), action: ActionConfig { action_dim: 4, hand_map, ..ActionConfig::default() } }
    }

    fn one_hand() -> Option<HandMapConfig> {
        Some(HandMapConfig { hands: vec![[0, 1, 2]], periods: 3 })
    }

    /// Latents of 3 latent frames (9 pixel frames of actions) on a 2 x 3 token grid of the tiny DiT.
    fn inputs(cfg: &ModelConfig) -> (Tensor, Tensor, Tensor) {
        let [_, ph, pw] = cfg.dit.patch_size;
        let latents = Tensor::randn([2, cfg.dit.in_dim, 3, 2 * ph, 3 * pw], (Kind::Float, Device::Cpu));
        let t = Tensor::from_slice(&[0f32, 500., 500., 0., 900., 900.]).view([2, 3]);
        (latents, t, Tensor::randn([2, 9, 4], (Kind::Float, Device::Cpu)))
    }

    #[test]
    fn a_new_hand_map_leaves_the_prediction_as_it_was() {
        let mapped = BwmModel::random(&config(one_hand()), Kind::Float, Device::Cpu, 5).unwrap();
        // The same model without the map, its weights copied rather than drawn again (a parallel
        // test's draws from libtorch's generator could fall between two draws of one seed).
        let rest = mapped.store.named_parameters().into_iter().filter(|(k, _)| !k.starts_with("action_encoder.hand_map."));
        let store = ParamStore::from_weights(Box::new(TensorSource::new(rest, "the mapped model")), &[], Kind::Float, Device::Cpu);
        let plain = BwmModel::build(&store, &config(None)).unwrap();
        store.check_all_consumed().unwrap();
        let (x, t, a) = inputs(&mapped.cfg);
        let tokens = mapped.embed_actions(&x, &a, None).unwrap().tokens.expect("the map adds a term per token");
        assert_eq!(tokens.size(), [2, 3 * 2 * 3, mapped.cfg.dit.dim]);
        assert_eq!(tokens.abs().max().double_value(&[]), 0.0, "its output layer starts at zero");
        let (p, m) = (plain.forward(&x, &t, &a).unwrap(), mapped.forward(&x, &t, &a).unwrap());
        // Within float rounding rather than bit for bit: libtorch's CPU kernels may split a sum
        // otherwise when other tests keep its threads busy.
        let diff = (&p - &m).abs().max().double_value(&[]);
        assert!(diff < 1e-5, "the same weights and a zero term: the same prediction, not one {diff} away");
    }

    #[test]
    fn the_hand_is_drawn_at_the_token_it_projects_to() {
        let model = BwmModel::random(&config(one_hand()), Kind::Float, Device::Cpu, 1).unwrap();
        let map = model.action_encoder.hand_map.as_ref().unwrap();
        // The projection: image x = action 0, image y = action 1 (z ignored).
        tch::no_grad(|| {
            let w = Tensor::from_slice(&[1f32, 0., 0., 0., 1., 0.]).view([2, 3]);
            let _ = map.project[0].weight.shallow_clone().copy_(&w);
            let _ = map.project[0].bias.shallow_clone().zero_();
        });
        // On a 4 x 5 grid, the hand at the centre of row 2, column 3: x = (2*3+1)/5 - 1, y = (2*2+1)/4 - 1.
        let (x, y) = (7.0 / 5.0 - 1.0, 5.0 / 4.0 - 1.0);
        let grouped = Tensor::from_slice(&[x as f32, y as f32, 0.3, 1.0]).view([1, 1, 1, 4]).repeat([1, 2, 4, 1]);
        let features = map.inputs(&grouped, (2, 4, 5)).unwrap();
        let per_hand = 4 * map.cfg.periods + 1;
        assert_eq!(features.size(), [1, 2 * 4 * 5, 4 * per_hand + 4 * 4]);
        // The Gaussian of the first action of the group, per token of each frame.
        let gauss = features.select(2, per_hand - 1).view([2, 4, 5]);
        for frame in 0..2 {
            let g = gauss.get(frame);
            assert!((g.double_value(&[2, 3]) - 1.0).abs() < 1e-6, "the hand's own token: distance 0");
            assert!((g.double_value(&[2, 4]) - (-0.5f64).exp()).abs() < 1e-6, "one token to the right");
            assert!((g.double_value(&[0, 0]) - (-(9.0 + 4.0) / 2f64).exp()).abs() < 1e-6, "three across and two up");
        }
        // The shortest period's sine and cosine: half a token, so a whole token's offset is a whole turn.
        let (sin_x, cos_x) = (features.select(2, 0).view([2, 4, 5]), features.select(2, 2).view([2, 4, 5]));
        assert!(sin_x.get(0).double_value(&[1, 1]).abs() < 1e-5 && (cos_x.get(0).double_value(&[1, 1]) - 1.0).abs() < 1e-5);
        // The group's actions follow, the same at every token.
        let actions = features.narrow(2, 4 * per_hand, 16);
        assert!(actions.get(0).get(0).allclose(&actions.get(0).get(13), 0.0, 0.0, false));
        assert!((actions.double_value(&[0, 7, 2]) - 0.3).abs() < 1e-6);
    }

    #[test]
    fn the_null_condition_removes_the_map_too() {
        let model = BwmModel::random(&config(one_hand()), Kind::Float, Device::Cpu, 2).unwrap();
        let map = model.action_encoder.hand_map.as_ref().unwrap();
        tch::no_grad(|| {
            let _ = map.mlp.l2.weight.shallow_clone().normal_(0.0, 0.1);
        });
        let (x, _, a) = inputs(&model.cfg);
        let keep = Tensor::from_slice(&[1f32, 0.]);
        let tokens = model.embed_actions(&x, &a, Some(&keep)).unwrap().tokens.unwrap();
        assert!(tokens.get(0).abs().max().double_value(&[]) > 0.0);
        assert_eq!(tokens.get(1).abs().max().double_value(&[]), 0.0);
    }

    #[test]
    fn a_hand_outside_the_actions_is_refused() {
        let cfg = config(Some(HandMapConfig { hands: vec![[0, 1, 4]], periods: 6 }));
        let err = BwmModel::random(&cfg, Kind::Float, Device::Cpu, 0).err().unwrap();
        assert!(format!("{err:#}").contains("not three indices of the 4-entry action vector"), "{err:#}");
        let none = config(Some(HandMapConfig { hands: vec![], periods: 6 }));
        assert!(BwmModel::random(&none, Kind::Float, Device::Cpu, 0).is_err());
    }

    #[test]
    fn a_model_config_reads_and_writes_the_map_and_leaves_it_out_when_off() {
        let text = "action_dim = 4\nhand_map = { hands = [[0, 1, 2]] }\n";
        let cfg: ActionConfig = toml::from_str(text).unwrap();
        assert_eq!(cfg.hand_map, Some(HandMapConfig { hands: vec![[0, 1, 2]], periods: 6 }));
        let back: ActionConfig = toml::from_str(&toml::to_string(&cfg).unwrap()).unwrap();
        assert_eq!(back, cfg);
        assert!(!toml::to_string(&ActionConfig::default()).unwrap().contains("hand_map"));
        assert!(toml::from_str::<ActionConfig>("hand_map = { hands = [[0, 1, 2]], scale = 2 }").is_err(), "unknown keys refused");
    }
}
