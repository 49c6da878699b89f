//! Model configuration: the DiT, the BWM action interface, and named presets.

use anyhow::{bail, ensure, Result};
use serde::{Deserialize, Serialize};

/// The Wan2.2 DiT (`WanModel` of the official code and DiffSynth-Studio).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DitConfig {
    pub dim: i64,
    pub in_dim: i64,
    pub out_dim: i64,
    pub ffn_dim: i64,
    pub freq_dim: i64,
    /// Width of the text-encoder embeddings `text_embedding` takes (umT5-XXL: 4096). The module is
    /// part of the checkpoint but unused when actions replace the text context.
    pub text_dim: i64,
    pub num_heads: i64,
    pub num_layers: i64,
    pub eps: f64,
    /// (t, h, w)
    pub patch_size: [i64; 3],
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
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ActionConfig {
    /// d_a: 14 for two arms' absolute end-effector poses (xyz, euler, gripper per arm).
    pub action_dim: i64,
    /// P: copies of the first action prepended before grouping, so that latent 0 (pixel frame 0
    /// alone) gets its own group.
    pub prepend: i64,
    /// G: actions per latent frame (the VAE's temporal stride).
    pub group: i64,
    /// B: when above 0, each normalized action value a also enters the encoder as sin(2^k*pi*a)
    /// and cos(2^k*pi*a) for k < B (Fourier features, Tancik et al. 2020), so that the
    /// encoder can resolve fine differences of a command; 0 is BWM's encoder.
    #[serde(skip_serializing_if = "is_zero")]
    pub fourier_bands: i64,
    /// The cross-attention to the action tokens told where each action lies in time: queries and
    /// action tokens rotated by the temporal part of the DiT's rotary embedding (each video token
    /// at its latent frame, each action at the latent frame its pixel frame falls in), so that a
    /// token can attend to the actions of its own frame. false is BWM's (no positions in the
    /// cross-attention); the option adds no parameters.
    #[serde(skip_serializing_if = "is_false")]
    pub temporal_rope: bool,
}

fn is_zero(v: &i64) -> bool {
    *v == 0
}

fn is_false(v: &bool) -> bool {
    !*v
}

/// The most octaves: at k = 11, sin(2^k*pi*a) turns over every 0.001 of a normalized command.
pub const MAX_FOURIER_BANDS: i64 = 12;

impl Default for ActionConfig {
    fn default() -> Self {
        Self { action_dim: 14, prepend: 3, group: 4, fourier_bands: 0, temporal_rope: false }
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
        ensure!(
            (0..=MAX_FOURIER_BANDS).contains(&self.fourier_bands),
            "action.fourier_bands must be in 0..={MAX_FOURIER_BANDS}, got {}",
            self.fourier_bands
        );
        Ok(())
    }

    /// The latent frame of each of `pixel_frames` actions: latent 0 holds pixel frame 0 (after P
    /// copies of it), latent k the G frames before it.
    pub fn action_latent_frames(&self, pixel_frames: i64) -> Vec<i64> {
        (0..pixel_frames).map(|i| (i + self.prepend) / self.group).collect()
    }

    /// Values per frame that the encoder's first layers see: d_a, times 1 + 2B with Fourier features.
    pub fn encoded_dim(&self) -> i64 {
        self.action_dim * (1 + 2 * self.fourier_bands)
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
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
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
        ensure!(
            !self.action.temporal_rope || self.dit.patch_size[0] == 1,
            "action.temporal_rope places each action at its latent frame, a token frame only with a temporal patch of 1; \
             dit.patch_size is {:?}",
            self.dit.patch_size
        );
        Ok(())
    }
}

/// dtype of the DiT's residual stream, its norms, modulation and gates (`model.residual` of a run
/// config, `--residual` of the world-model commands). Here beside the model's config, since the
/// trainer, the checkpoints' run record and inference all name it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
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

    #[test]
    fn fourier_bands_default_to_none_and_are_bounded() {
        let plain: ActionConfig = toml::from_str("action_dim = 4\nprepend = 3\ngroup = 4").unwrap();
        assert_eq!((plain.fourier_bands, plain.encoded_dim()), (0, 4));
        let only: ActionConfig = toml::from_str("fourier_bands = 2").unwrap();
        assert_eq!(only, ActionConfig { fourier_bands: 2, ..ActionConfig::default() });
        assert!(!toml::to_string(&plain).unwrap().contains("fourier"), "BWM's encoder writes its config as before");
        let f: ActionConfig = toml::from_str("action_dim = 4\nprepend = 3\ngroup = 4\nfourier_bands = 6").unwrap();
        f.validate().unwrap();
        assert_eq!(f.encoded_dim(), 4 * 13);
        assert_eq!(toml::from_str::<ActionConfig>(&toml::to_string(&f).unwrap()).unwrap(), f);
        for bad in [-1, MAX_FOURIER_BANDS + 1] {
            let e = ActionConfig { fourier_bands: bad, ..f.clone() }.validate().unwrap_err().to_string();
            assert!(e.contains("action.fourier_bands"), "{e}");
        }
    }

    #[test]
    fn each_action_has_the_latent_frame_of_its_group_and_the_rotation_is_opt_in() {
        let a = ActionConfig { action_dim: 4, ..ActionConfig::default() };
        // Pixel frame 0 alone in latent 0 (after P = 3 copies), then four frames per latent.
        assert_eq!(a.action_latent_frames(9), [0, 1, 1, 1, 1, 2, 2, 2, 2]);
        assert_eq!(a.action_latent_frames(9).last().map(|&l| l + 1), a.latent_frames(9).ok());
        assert!(!a.temporal_rope && !toml::to_string(&a).unwrap().contains("temporal"), "BWM's writes its config as before");
        let t: ActionConfig = toml::from_str("action_dim = 4\ntemporal_rope = true").unwrap();
        assert!(t.temporal_rope);
        let mut m = ModelConfig { dit: DitConfig::tiny(), action: t.clone() };
        m.validate().unwrap();
        m.dit.patch_size[0] = 2;
        let err = m.validate().unwrap_err().to_string();
        assert!(err.contains("temporal_rope") && err.contains("[2, "), "{err}");
        m.action.temporal_rope = false;
        m.validate().unwrap();
        assert_eq!(toml::from_str::<ActionConfig>(&toml::to_string(&t).unwrap()).unwrap(), t);
    }
}
