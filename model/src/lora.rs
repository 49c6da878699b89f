//! LoRA adapters (Hu et al., 2021) on linear layers: `y = W x + b + (alpha / r) B A dropout(x)`
//! with A [r, in] and B [out, r]. The adapter of the layer at `<path>` is named as PEFT and
//! diffusers name it, `<path>.lora_A.weight` and `<path>.lora_B.weight`; B starts at zero, so a
//! model with fresh adapters computes exactly what its base does.

use std::cell::Cell;
use std::rc::Rc;

use anyhow::{ensure, Result};
use serde::{Deserialize, Serialize};
use tch::Tensor;

use crate::vb::{Init, Vb};
use crate::weights::WeightsError;

/// Which linear layers get an adapter, and its shape.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoraConfig {
    pub rank: i64,
    /// The update is scaled by alpha / rank (default: alpha = rank, a scale of 1).
    #[serde(default)]
    pub alpha: Option<f64>,
    /// Dropout on the adapter's input while training (0 = none).
    #[serde(default)]
    pub dropout: f64,
    /// Module-path patterns (`*` matches anything, dots included) of the linear layers that get
    /// an adapter, e.g. `blocks.*.self_attn.*` or `blocks.*.ffn.*`.
    pub targets: Vec<String>,
}

/// Parameter-name patterns of every adapter tensor (the trainable set of a LoRA run).
pub const ADAPTER_PATTERNS: [&str; 2] = ["*.lora_A.weight", "*.lora_B.weight"];

/// An adapter tensor's name split into its layer's module path and `lora_A` or `lora_B`; None
/// for any other name.
pub fn split_adapter_key(name: &str) -> Option<(&str, &'static str)> {
    ["lora_A", "lora_B"].into_iter().find_map(|part| name.strip_suffix(".weight")?.strip_suffix(part)?.strip_suffix('.').map(|m| (m, part)))
}

/// Whether `name` is an adapter tensor's.
pub fn is_adapter_key(name: &str) -> bool {
    split_adapter_key(name).is_some()
}

impl LoraConfig {
    pub fn validate(&self) -> Result<()> {
        ensure!(self.rank > 0, "lora.rank must be positive, got {}", self.rank);
        ensure!(self.alpha.is_none_or(|a| a.is_finite() && a > 0.0), "lora.alpha must be positive, got {:?}", self.alpha);
        ensure!((0.0..1.0).contains(&self.dropout), "lora.dropout must be in [0, 1), got {}", self.dropout);
        ensure!(!self.targets.is_empty(), "lora.targets is empty: name the linear layers that get an adapter");
        for p in &self.targets {
            glob::Pattern::new(p).map_err(|e| anyhow::anyhow!("lora.targets pattern '{p}' is invalid: {e}"))?;
        }
        Ok(())
    }

    pub fn scale(&self) -> f64 {
        self.alpha.unwrap_or(self.rank as f64) / self.rank as f64
    }

    /// Whether the linear layer at `module_path` gets an adapter.
    pub fn targets(&self, module_path: &str) -> bool {
        self.targets.iter().any(|p| glob::Pattern::new(p).is_ok_and(|p| p.matches(module_path)))
    }
}

/// The adapters of one model: their config and whether they train (dropout on) or infer.
#[derive(Debug)]
pub struct LoraState {
    pub cfg: LoraConfig,
    /// Keys the fresh A matrices' draws.
    pub seed: u64,
    training: Cell<bool>,
}

impl LoraState {
    pub fn new(cfg: LoraConfig, seed: u64) -> Result<Rc<Self>> {
        cfg.validate()?;
        Ok(Rc::new(Self { cfg, seed, training: Cell::new(false) }))
    }

    /// Dropout applies while training; inference (the default) is deterministic.
    pub fn set_training(&self, training: bool) {
        self.training.set(training);
    }
}

/// One layer's adapter.
pub struct LoraAdapter {
    /// `lora_A.weight` [r, in]: PyTorch's default Linear init, as PEFT draws it.
    pub a: Tensor,
    /// `lora_B.weight` [out, r]: zeros.
    pub b: Tensor,
    state: Rc<LoraState>,
}

impl LoraAdapter {
    pub fn new(vb: &Vb, state: Rc<LoraState>, in_dim: i64, out_dim: i64) -> Result<Self, WeightsError> {
        let r = state.cfg.rank;
        let a_init = Init::KeyedUniform { bound: 1.0 / (in_dim as f64).sqrt(), seed: state.seed, index: path_key(&vb.path("lora_A")) };
        Ok(Self {
            a: vb.pp("lora_A").get(&[r, in_dim], "weight", a_init)?,
            b: vb.pp("lora_B").get(&[out_dim, r], "weight", Init::Zeros)?,
            state,
        })
    }

    /// The adapter's update for `x` (already in the adapter's dtype).
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let p = self.state.cfg.dropout;
        let x = if p > 0.0 && self.state.training.get() { x.dropout(p, true) } else { x.shallow_clone() };
        x.linear(&self.a, None::<Tensor>).linear(&self.b, None::<Tensor>) * self.state.cfg.scale()
    }

    /// `B A` scaled: what merging adds to the base weight [out, in].
    pub fn delta_weight(&self) -> Tensor {
        self.b.matmul(&self.a) * self.state.cfg.scale()
    }
}

/// A stable 64-bit key of a module path (FNV-1a), so that a layer's fresh adapter is the same
/// whatever else the model holds.
fn path_key(path: &str) -> u64 {
    path.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::Linear;
    use crate::vb::ParamStore;
    use tch::{Device, Kind};

    fn cfg(dropout: f64) -> LoraConfig {
        LoraConfig { rank: 2, alpha: Some(4.0), dropout, targets: vec!["blocks.*.q".into()] }
    }

    #[test]
    fn adapter_keys_split_into_module_and_part() {
        assert_eq!(split_adapter_key("blocks.0.ffn.2.lora_B.weight"), Some(("blocks.0.ffn.2", "lora_B")));
        assert_eq!(split_adapter_key("transformer.blocks.0.attn1.to_q.lora_A.weight"), Some(("transformer.blocks.0.attn1.to_q", "lora_A")));
        assert_eq!(split_adapter_key("blocks.0.ffn.2.weight"), None);
        assert_eq!(split_adapter_key("blocks.0.xlora_A.weight"), None);
        assert!(is_adapter_key("a.lora_A.weight") && !is_adapter_key("a.lora_A.bias"));
    }

    #[test]
    fn targets_scale_and_validation() {
        let c = cfg(0.0);
        assert!(c.targets("blocks.0.self_attn.q") && c.targets("blocks.11.cross_attn.q"));
        assert!(!c.targets("blocks.0.self_attn.k") && !c.targets("head.head"));
        assert_eq!(c.scale(), 2.0);
        assert_eq!(LoraConfig { alpha: None, ..cfg(0.0) }.scale(), 1.0);
        assert!(LoraConfig { rank: 0, ..cfg(0.0) }.validate().is_err());
        assert!(cfg(1.0).validate().is_err());
        assert!(LoraConfig { targets: vec!["[".into()], ..cfg(0.0) }.validate().is_err());
    }

    #[test]
    fn a_targeted_linear_adds_the_scaled_low_rank_update_with_dropout_only_in_training() {
        // Under the generator lock, as every draw from libtorch's generator in these tests.
        let (state, l, plain, x) = crate::vb::with_seed(1, || {
            let store = ParamStore::random(Kind::Float, Device::Cpu);
            let state = store.enable_lora(cfg(0.5), 7).unwrap();
            let root = store.root();
            let l = Linear::new(&root.pp("blocks").pp(0).pp("q"), 6, 5).unwrap();
            let plain = Linear::new(&root.pp("blocks").pp(0).pp("k"), 6, 5).unwrap();
            (state, l, plain, Tensor::randn([3, 6], (Kind::Float, Device::Cpu)))
        });
        assert!(plain.lora.is_none());
        let adapter = l.lora.as_ref().expect("blocks.0.q is targeted");
        assert_eq!((adapter.a.size(), adapter.b.size()), (vec![2, 6], vec![5, 2]));
        let base = x.linear(&l.weight, Some(&l.bias));
        // B starts at zero: the layer computes its base.
        assert!(l.forward(&x).equal(&base));
        let _ = tch::no_grad(|| adapter.b.shallow_clone().fill_(0.1));
        let expected = &base + x.matmul(&adapter.a.tr()).matmul(&adapter.b.tr()) * 2.0;
        assert!(l.forward(&x).allclose(&expected, 1e-6, 1e-6, false));
        assert!(l.forward(&x).equal(&l.forward(&x)), "inference draws no dropout");
        let merged = &l.weight + adapter.delta_weight();
        assert!(x.linear(&merged, Some(&l.bias)).allclose(&expected, 1e-5, 1e-5, false));
        state.set_training(true);
        let dropped = crate::vb::with_seed(2, || l.forward(&x));
        assert!(!dropped.allclose(&expected, 1e-6, 1e-6, false), "dropout 0.5 while training changes the update");
    }

    #[test]
    fn fresh_adapters_do_not_move_other_draws_and_depend_on_the_layer() {
        let build = |lora: bool| {
            crate::vb::with_seed(3, || {
                let store = ParamStore::random(Kind::Float, Device::Cpu);
                if lora {
                    store.enable_lora(cfg(0.0), 9).unwrap();
                }
                let root = store.root();
                let q0 = Linear::new(&root.pp("blocks").pp(0).pp("q"), 4, 4).unwrap();
                let q1 = Linear::new(&root.pp("blocks").pp(1).pp("q"), 4, 4).unwrap();
                (q0, q1)
            })
        };
        let (a0, a1) = build(false);
        let (b0, b1) = build(true);
        assert!(a0.weight.equal(&b0.weight) && a1.weight.equal(&b1.weight) && a1.bias.equal(&b1.bias));
        let (l0, l1) = (b0.lora.unwrap(), b1.lora.unwrap());
        assert!(!l0.a.equal(&l1.a), "two layers drew the same A");
        assert!(l0.a.abs().max().double_value(&[]) <= 0.5, "A is drawn within 1/sqrt(in)");
    }
}
