//! Model configuration: the DiT, the BWM action interface, and named presets.

use anyhow::{bail, ensure, Result};
use serde::{Deserialize, Serialize};

/// The Wan2.2 DiT (`WanModel` of the official code and DiffSynth-Studio).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DitConfig {
    /// Hidden width of the transformer blocks (the 5B: 3072).
    pub dim: i64,
    /// Latent channels in (the VAE's z_dim: 48 for Wan2.2's VAE).
    pub in_dim: i64,
    /// Latent channels out (as `in_dim`).
    pub out_dim: i64,
    /// Hidden width of each block's feed-forward network (the 5B: 14336).
    pub ffn_dim: i64,
    /// Width of the sinusoidal timestep embedding (256).
    pub freq_dim: i64,
    /// Width of the text-encoder embeddings `text_embedding` takes (umT5-XXL: 4096). The module is
    /// part of the checkpoint but unused when actions replace the text context.
    pub text_dim: i64,
    /// Attention heads per block; `dim / num_heads` is the head width, which the 3-D rotary
    /// embedding splits three ways.
    pub num_heads: i64,
    /// Transformer blocks (the 5B: 30).
    pub num_layers: i64,
    /// Epsilon of the layer and RMS norms (1e-6).
    pub eps: f64,
    /// Latent cells per token along (t, h, w): `[1, 2, 2]` in the 5B; `[1, 1, 1]` gives a token
    /// per latent cell.
    pub patch_size: [i64; 3],
    /// Base of the rotary position embedding's frequencies.
    #[serde(default = "default_rope_theta")]
    pub rope_theta: f64,
}

fn default_rope_theta() -> f64 {
    10000.0
}

impl DitConfig {
    /// Wan2.2-TI2V-5B (`config.json` of `Wan-AI/Wan2.2-TI2V-5B`).
    pub fn wan22_ti2v_5b() -> Self {
        Self {
            dim: 3072,
            in_dim: 48,
            out_dim: 48,
            ffn_dim: 14336,
            freq_dim: 256,
            text_dim: 4096,
            num_heads: 24,
            num_layers: 30,
            eps: 1e-6,
            patch_size: [1, 2, 2],
            rope_theta: 10000.0,
        }
    }

    /// A few-million-parameter model of the same family for CPU runs and tests.
    pub fn tiny() -> Self {
        Self {
            dim: 96,
            in_dim: 48,
            out_dim: 48,
            ffn_dim: 192,
            freq_dim: 256,
            text_dim: 64,
            num_heads: 2,
            num_layers: 2,
            eps: 1e-6,
            patch_size: [1, 2, 2],
            rope_theta: 10000.0,
        }
    }

    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "wan22_ti2v_5b" => Ok(Self::wan22_ti2v_5b()),
            "tiny" => Ok(Self::tiny()),
            _ => bail!("unknown DiT preset '{name}' (allowed: wan22_ti2v_5b, tiny)"),
        }
    }

    pub fn head_dim(&self) -> i64 {
        self.dim / self.num_heads
    }

    /// RoPE channels per axis (t, h, w) within one head, as DiffSynth-Studio and the official code
    /// split them (44/42/42 for head_dim 128).
    pub fn rope_axes(&self) -> [i64; 3] {
        let d = self.head_dim();
        [d - 2 * (d / 3), d / 3, d / 3]
    }

    pub fn patch_volume(&self) -> i64 {
        self.patch_size.iter().product()
    }

    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("dim", self.dim),
            ("in_dim", self.in_dim),
            ("out_dim", self.out_dim),
            ("ffn_dim", self.ffn_dim),
            ("freq_dim", self.freq_dim),
            ("text_dim", self.text_dim),
            ("num_heads", self.num_heads),
            ("num_layers", self.num_layers),
        ] {
            ensure!(v > 0, "dit.{name} must be positive, got {v}");
        }
        ensure!(self.patch_size.iter().all(|&p| p > 0), "dit.patch_size must be positive, got {:?}", self.patch_size);
        ensure!(
            self.dim % self.num_heads == 0,
            "dit.dim ({}) must be a multiple of dit.num_heads ({})",
            self.dim,
            self.num_heads
        );
        ensure!(self.freq_dim % 2 == 0, "dit.freq_dim must be even, got {}", self.freq_dim);
        let axes = self.rope_axes();
        ensure!(
            axes.iter().all(|a| a % 2 == 0),
            "head_dim {} splits into RoPE axes {:?}; each must be even (pick dim/num_heads so that head_dim/3 is even)",
            self.head_dim(),
            axes
        );
        ensure!(self.eps > 0.0, "dit.eps must be positive");
        Ok(())
    }
}

/// The BWM action interface (`WanVideoActionEncoder`, ti2v2 path); keys left out take the
/// defaults (BWM's 14-D actions).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ActionConfig {
    /// d_a: 14 for two arms' absolute end-effector poses (xyz, euler, gripper per arm).
    pub action_dim: i64,
    /// P: copies of the first action prepended before grouping, so that latent 0 (pixel frame 0
    /// alone) gets its own group.
    pub prepend: i64,
    /// G: actions per latent frame (the VAE's temporal stride).
    pub group: i64,
    /// The commanded hands drawn into the DiT's token grid (docs/training.md, "The hand map"); none
    /// in the BWM release.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hand_map: Option<HandMapConfig>,
    /// Removed: Fourier features of the actions (`removed::FOURIER_BANDS`).
    #[serde(skip_serializing, deserialize_with = "removed::fourier_bands")]
    #[schemars(skip)]
    pub fourier_bands: Removed,
    /// Removed: the actions timed in the cross-attention (`removed::TEMPORAL_ROPE`).
    #[serde(skip_serializing, deserialize_with = "removed::temporal_rope")]
    #[schemars(skip)]
    pub temporal_rope: Removed,
}

/// A config key that measurements rejected and that was removed with what it switched on
/// (issue 69). Files written before hold it, at its old default where the run did not use it
/// (a run config writes every key), so the key stays known to deserialization as a field of this
/// type: it accepts the old default alone and refuses any other value, naming the key and saying
/// why it went (`removed::check`). It holds nothing and is never written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Removed;

/// The config keys that were removed, what measured them, and their checks: the model's, and the
/// run config's `objective.motion_weight` (`bwm_run_config::ObjectiveSection`, which the trainer
/// and the checkpoints' reader of a run config share).
pub mod removed {
    use super::Removed;
    use serde::de::{Deserialize, Deserializer, Error};

    /// A removed key's name, its old default (the value that left it off) and why it went.
    pub struct Key<T: 'static> {
        pub name: &'static str,
        pub default: T,
        pub why: &'static str,
    }

    pub const FOURIER_BANDS: Key<i64> = Key {
        name: "action.fourier_bands",
        default: 0,
        why: "Fourier features of the actions measured worse (run 28 in docs/fidelity.md at abaed68: closed-loop Pearson r 0.805 / 0.638 \
              against 0.836 / 0.669 from the same two seeds without them)",
    };

    pub const TEMPORAL_ROPE: Key<bool> = Key {
        name: "action.temporal_rope",
        default: false,
        why: "the actions timed in the cross-attention changed nothing measurable (run 39 in docs/fidelity.md at abaed68: r 0.904 against \
              0.899 from the same seeds without it, the 16 estimates closer than two trainings of one recipe, at 12% more DiT time)",
    };

    pub const MOTION_WEIGHT: Key<f64> = Key {
        name: "objective.motion_weight",
        default: 0.0,
        why: "weighting the DiT's loss towards the latent cells that move changed nothing the seeds do not (run 33 in \
              docs/fidelity.md at abaed68: r 0.850 / 0.816, each training's 16 estimates 0.017-0.031 from the same seed's plain-loss \
              trainings, as close as those lie to each other)",
    };

    /// `value` of the removed `key`: accepted at its old default, an error naming the key and why
    /// it was removed otherwise.
    pub fn check<T: PartialEq + std::fmt::Display>(key: &Key<T>, value: T) -> Result<Removed, String> {
        if value == key.default {
            return Ok(Removed);
        }
        Err(format!(
            "{} = {value}: the key was removed because {}; a config may hold it only at its old default, {} (issue 69)",
            key.name, key.why, key.default
        ))
    }

    /// Reads a removed key's value and `check`s it.
    pub fn deserialize<'de, D: Deserializer<'de>, T: Deserialize<'de> + PartialEq + std::fmt::Display>(d: D, key: &Key<T>) -> Result<Removed, D::Error> {
        check(key, T::deserialize(d)?).map_err(D::Error::custom)
    }

    pub fn fourier_bands<'de, D: Deserializer<'de>>(d: D) -> Result<Removed, D::Error> {
        deserialize(d, &FOURIER_BANDS)
    }

    pub fn temporal_rope<'de, D: Deserializer<'de>>(d: D) -> Result<Removed, D::Error> {
        deserialize(d, &TEMPORAL_ROPE)
    }

    pub fn motion_weight<'de, D: Deserializer<'de>>(d: D) -> Result<Removed, D::Error> {
        deserialize(d, &MOTION_WEIGHT)
    }
}

impl Default for ActionConfig {
    fn default() -> Self {
        Self { action_dim: 14, prepend: 3, group: 4, hand_map: None, fourier_bands: Removed, temporal_rope: Removed }
    }
}

/// Where the hands are in the action vector, for the hand map (`crate::hand_map`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct HandMapConfig {
    /// Per hand, the indices of its commanded x, y and z in the action vector (`[[0, 1, 2]]` for
    /// one arm whose actions start with its end effector's position).
    pub hands: Vec<[i64; 3]>,
    /// How many periods the offsets from each token are written at: 1/2, 1, 2, ... tokens.
    #[serde(default = "HandMapConfig::default_periods")]
    pub periods: i64,
}

impl HandMapConfig {
    fn default_periods() -> i64 {
        6
    }

    pub fn validate(&self, action_dim: i64) -> Result<()> {
        ensure!(!self.hands.is_empty(), "action.hand_map.hands names no hand (give each hand's x, y, z indices, e.g. [[0, 1, 2]])");
        for hand in &self.hands {
            ensure!(
                hand.iter().all(|&i| (0..action_dim).contains(&i)),
                "action.hand_map.hands: {hand:?} is not three indices of the {action_dim}-entry action vector"
            );
        }
        ensure!((1..=16).contains(&self.periods), "action.hand_map.periods must be in 1..=16, got {}", self.periods);
        Ok(())
    }
}

impl ActionConfig {
    pub fn validate(&self) -> Result<()> {
        ensure!(self.action_dim > 0, "action.action_dim must be positive, got {}", self.action_dim);
        ensure!(self.group > 0, "action.group must be positive, got {}", self.group);
        ensure!(
            self.prepend >= 0 && self.prepend < self.group,
            "action.prepend must be in 0..group, got {}",
            self.prepend
        );
        if let Some(map) = &self.hand_map {
            map.validate(self.action_dim)?;
        }
        Ok(())
    }

    /// Latent frames the actions of `frames` pixel frames describe; an error unless
    /// `frames + prepend` is a whole number of groups (1 + 4k frames for P=3, G=4).
    pub fn latent_frames(&self, frames: i64) -> Result<i64> {
        ensure!(
            frames > 0 && (frames + self.prepend) % self.group == 0,
            "got actions for {frames} frames; expected {}k+{} frames (k >= 0) so that they group into latent frames",
            self.group,
            self.group - self.prepend
        );
        Ok((frames + self.prepend) / self.group)
    }
}

/// The whole BWM model: DiT + action encoder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    pub dit: DitConfig,
    #[serde(default)]
    pub action: ActionConfig,
}

impl ModelConfig {
    pub fn preset(name: &str) -> Result<Self> {
        Ok(Self { dit: DitConfig::preset(name)?, action: ActionConfig::default() })
    }

    pub fn validate(&self) -> Result<()> {
        self.dit.validate()?;
        self.action.validate()?;
        Ok(())
    }
}

/// dtype of the DiT's residual stream, its norms, modulation and gates (`model.residual` of a run
/// config, `--residual` of the world-model commands). Here beside the model's config, since the
/// trainer, the checkpoints' run record and inference all name it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Residual {
    /// fp32, as the official Wan code.
    #[default]
    F32,
    /// `model.dtype`, as DiffSynth-Studio (which the BWM release trains with) runs it: half the
    /// memory traffic of the element-wise work between the matmuls.
    Model,
}

impl std::str::FromStr for Residual {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "f32" => Ok(Residual::F32),
            "model" => Ok(Residual::Model),
            _ => Err(format!("'{s}': expected f32 or model")),
        }
    }
}

impl Residual {
    /// The residual stream's dtype for a model whose weights are in `model`.
    pub fn kind(self, model: tch::Kind) -> tch::Kind {
        match self {
            Residual::F32 => tch::Kind::Float,
            Residual::Model => model,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_validate_and_5b_rope_split_is_44_42_42() {
        let c = DitConfig::wan22_ti2v_5b();
        c.validate().unwrap();
        assert_eq!(c.rope_axes(), [44, 42, 42]);
        DitConfig::tiny().validate().unwrap();
    }

    #[test]
    fn bad_configs_are_rejected_with_the_key() {
        let mut c = DitConfig::tiny();
        c.num_heads = 5;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("num_heads"), "{e}");
        assert!(DitConfig::preset("huge").unwrap_err().to_string().contains("allowed"));
        let text = r#"dim = 8
bogus = 1"#;
        assert!(toml::from_str::<DitConfig>(text).is_err());
    }

    #[test]
    fn action_frames_must_be_1_plus_4k() {
        let a = ActionConfig::default();
        assert_eq!(a.latent_frames(81).unwrap(), 21);
        assert_eq!(a.latent_frames(1).unwrap(), 1);
        let e = a.latent_frames(80).unwrap_err().to_string();
        assert!(e.contains("4k+1"), "{e}");
    }

    /// Keys removed after measurements rejected what they switched on (issue 69): a file written
    /// before, which holds one at its old default, loads as before (in TOML as the run config
    /// keeps it, in JSON as an export's config.json does); one that switched it on is refused by
    /// the key's name, saying that it was removed and why. Other unknown keys are still refused.
    #[test]
    fn removed_action_keys_load_at_their_old_defaults_and_are_refused_otherwise() {
        let old: ActionConfig = toml::from_str("action_dim = 4\nfourier_bands = 0\ntemporal_rope = false").unwrap();
        assert_eq!(old, ActionConfig { action_dim: 4, ..ActionConfig::default() });
        let exported = r#"{"dit": DIT, "action": {"action_dim": 4, "prepend": 3, "group": 4, "fourier_bands": 0, "temporal_rope": false}}"#;
        let exported = exported.replace("DIT", &serde_json::to_string(&DitConfig::tiny()).unwrap());
        let model: ModelConfig = serde_json::from_str(&exported).unwrap();
        assert_eq!(model, ModelConfig { dit: DitConfig::tiny(), action: old.clone() });
        let written = format!("{}{}", toml::to_string(&old).unwrap(), serde_json::to_string(&model).unwrap());
        assert!(!written.contains("fourier") && !written.contains("temporal"), "nothing removed is written: {written}");
        for (key, off, on, why) in [("fourier_bands", "0", "6", "run 28"), ("temporal_rope", "false", "true", "run 39")] {
            let e = toml::from_str::<ActionConfig>(&format!("{key} = {on}")).unwrap_err().to_string();
            assert!(e.contains(&format!("action.{key} = {on}")) && e.contains("was removed") && e.contains(why) && e.contains("docs/fidelity.md"), "{e}");
            let json = exported.replace(&format!(r#""{key}": {off}"#), &format!(r#""{key}": {on}"#));
            let e = serde_json::from_str::<ModelConfig>(&json).unwrap_err().to_string();
            assert!(e.contains(&format!("action.{key} = {on}")) && e.contains("was removed") && e.contains(why), "{e}");
        }
        assert!(toml::from_str::<ActionConfig>("fourier_band = 0").unwrap_err().to_string().contains("unknown field"));
    }
}
