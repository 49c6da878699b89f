//! LoRA adapters (Hu et al., 2021) on linear layers: `y = W x + b + (alpha / r) B A dropout(x)`
//! with A [r, in] and B [out, r], added to a built model by a conversion (`add_adapters`, see
//! `crate::convert`) as PEFT injects them. The adapter of the layer at `<path>` is named as PEFT
//! and diffusers name it, `<path>.lora_A.weight` and `<path>.lora_B.weight`; B starts at zero, so
//! a model with fresh adapters computes exactly what its base does.

use std::cell::Cell;
use std::rc::Rc;

use anyhow::{ensure, Context, Result};
use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use crate::convert::{self, Linears};
use crate::keyed_rng::Purpose;
use crate::nn::{Linear, LinearForward};
use crate::vb::Init;
use crate::weights::WeightsError;

/// Which linear layers get an adapter, and its shape.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LoraConfig {
    /// Rank of each adapter's update B A.
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
        convert::matches(&self.targets, module_path)
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

/// Puts an adapter on every linear layer of `model` that `cfg.targets` names (none when it names
/// none: the trainer then finds nothing to train and says so). Its tensors are registered under
/// the layer's path, listed right after the layer's own parameters (`Vb::add`), read from the
/// weight file the model was built from when it holds them and drawn fresh otherwise: A from a
/// stream keyed by `seed` and the layer, so that no other parameter's draw moves, B zeros.
/// Returns the adapters' shared state (the trainer turns their dropout on while it trains). A
/// layer whose product a conversion already replaced is refused, before any adapter is added.
pub fn add_adapters<M: Linears + ?Sized>(model: &mut M, cfg: LoraConfig, seed: u64) -> Result<Rc<LoraState>> {
    let state = LoraState::new(cfg, seed)?;
    let mut layers = convert::select(model, &state.cfg.targets)?;
    for layer in &layers {
        if let Some(other) = layer.replaced_forward() {
            anyhow::bail!("{} carries {}; a LoRA adapter goes on a plain linear layer", layer.path(), other.describe());
        }
    }
    for layer in &mut layers {
        let adapter = LoraAdapter::new(layer, state.clone()).with_context(|| format!("the LoRA adapter of {}", layer.path()))?;
        layer.replace_forward(Box::new(adapter));
    }
    Ok(state)
}

/// The adapter on `layer`, if it carries one.
pub fn adapter(layer: &Linear) -> Option<&LoraAdapter> {
    layer.replaced_forward_as::<LoraAdapter>()
}

/// One layer's adapter: its product is the layer's plus the scaled low-rank update.
pub struct LoraAdapter {
    /// `lora_A.weight` [r, in]: PyTorch's default Linear init, as PEFT draws it.
    pub a: Tensor,
    /// `lora_B.weight` [out, r]: zeros.
    pub b: Tensor,
    state: Rc<LoraState>,
}

impl LoraAdapter {
    /// The adapter of `layer`, its tensors added under the layer's path.
    fn new(layer: &Linear, state: Rc<LoraState>) -> Result<Self, WeightsError> {
        let (out_dim, in_dim) = (layer.weight.size()[0], layer.weight.size()[1]);
        let vb = layer.vb();
        let r = state.cfg.rank;
        let index = path_key(&vb.path("lora_A"));
        let a_init = Init::KeyedUniform { bound: 1.0 / (in_dim as f64).sqrt(), seed: state.seed, index, purpose: Purpose::LoraInit };
        Ok(Self { a: vb.add(&[r, in_dim], "lora_A.weight", a_init)?, b: vb.add(&[out_dim, r], "lora_B.weight", Init::Zeros)?, state })
    }

    /// The adapter's update for `x` (already in the adapter's dtype).
    pub fn update(&self, x: &Tensor) -> Tensor {
        let p = self.state.cfg.dropout;
        let x = if p > 0.0 && self.state.training.get() { x.dropout(p, true) } else { x.shallow_clone() };
        x.linear(&self.a, None::<Tensor>).linear(&self.b, None::<Tensor>) * self.state.cfg.scale()
    }

    /// `B A` scaled: what merging adds to the base weight [out, in].
    pub fn delta_weight(&self) -> Tensor {
        self.b.matmul(&self.a) * self.state.cfg.scale()
    }
}

impl LinearForward for LoraAdapter {
    fn forward(&self, layer: &Linear, x: &Tensor) -> Tensor {
        x.linear(&layer.weight, Some(&layer.bias)) + self.update(x)
    }

    fn forward_f32(&self, layer: &Linear, x: &Tensor) -> Tensor {
        layer.plain_f32(x) + self.update(&x.to_kind(self.a.kind())).to_kind(Kind::Float)
    }

    fn describe(&self) -> String {
        "a LoRA adapter".into()
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

    /// The layers at `blocks.{0,1}.{q,k}` of a store, built under the generator lock; with
    /// adapters added by `cfg` when given.
    fn layers(seed: i64, cfg: Option<LoraConfig>) -> (Option<Rc<LoraState>>, Vec<Linear>, Rc<ParamStore>) {
        crate::vb::with_seed(seed, || {
            let store = ParamStore::random(Kind::Float, Device::Cpu);
            let root = store.root();
            let mut layers: Vec<Linear> = [(0, "q"), (0, "k"), (1, "q")].iter().map(|(b, n)| Linear::new(&root.pp("blocks").pp(b).pp(n), 6, 5).unwrap()).collect();
            let state = cfg.map(|c| add_adapters(&mut layers, c, 7).unwrap());
            (state, layers, store)
        })
    }

    impl Linears for Vec<Linear> {
        fn linears_mut(&mut self) -> Vec<&mut Linear> {
            self.iter_mut().collect()
        }
    }

    #[test]
    fn a_targeted_linear_adds_the_scaled_low_rank_update_with_dropout_only_in_training() {
        let (state, layers, _) = layers(1, Some(cfg(0.5)));
        let state = state.unwrap();
        let (l, plain) = (&layers[0], &layers[1]);
        let x = crate::vb::with_seed(1, || Tensor::randn([3, 6], (Kind::Float, Device::Cpu)));
        assert!(adapter(plain).is_none() && plain.replaced_forward().is_none());
        let adapter = adapter(l).expect("blocks.0.q is targeted");
        assert_eq!((adapter.a.size(), adapter.b.size()), (vec![2, 6], vec![5, 2]));
        let base = x.linear(&l.weight, Some(&l.bias));
        // B starts at zero: the layer computes its base.
        assert!(l.forward(&x).equal(&base));
        let _ = tch::no_grad(|| adapter.b.shallow_clone().fill_(0.1));
        let expected = &base + x.matmul(&adapter.a.tr()).matmul(&adapter.b.tr()) * 2.0;
        assert!(l.forward(&x).allclose(&expected, 1e-6, 1e-6, false));
        assert!(l.forward_f32(&x).allclose(&expected, 1e-6, 1e-6, false), "the fp32 product carries the update too");
        assert!(l.forward(&x).equal(&l.forward(&x)), "inference draws no dropout");
        let merged = &l.weight + adapter.delta_weight();
        assert!(x.linear(&merged, Some(&l.bias)).allclose(&expected, 1e-5, 1e-5, false));
        state.set_training(true);
        let dropped = crate::vb::with_seed(2, || l.forward(&x));
        assert!(!dropped.allclose(&expected, 1e-6, 1e-6, false), "dropout 0.5 while training changes the update");
    }

    #[test]
    fn fresh_adapters_do_not_move_other_draws_and_depend_on_the_layer() {
        let (_, plain, _) = layers(3, None);
        let (_, adapted, store) = layers(3, Some(LoraConfig { targets: vec!["blocks.*".into()], ..cfg(0.0) }));
        for (a, b) in plain.iter().zip(&adapted) {
            assert!(a.weight.equal(&b.weight) && a.bias.equal(&b.bias));
        }
        let (l0, l1) = (adapter(&adapted[0]).unwrap(), adapter(&adapted[2]).unwrap());
        assert!(!l0.a.equal(&l1.a), "two layers drew the same A");
        assert!(l0.a.abs().max().double_value(&[]) <= 1.0 / 6f64.sqrt(), "A is drawn within 1/sqrt(in)");
        // A from the stream keyed by the run's seed and the layer's path, whenever it is added.
        let expected = crate::keyed_rng::uniform_tensor(&[2, 6], 1.0 / 6f64.sqrt(), 7, path_key("blocks.0.q.lora_A"), Purpose::LoraInit);
        assert!(l0.a.equal(&expected));
        // Each adapter listed right after its layer, as a model built with it listed it.
        let names: Vec<String> = store.named_parameters().into_iter().map(|(n, _)| n).collect();
        let layer = |p: &str| [format!("{p}.weight"), format!("{p}.bias"), format!("{p}.lora_A.weight"), format!("{p}.lora_B.weight")];
        assert_eq!(names, [layer("blocks.0.q"), layer("blocks.0.k"), layer("blocks.1.q")].concat());
    }

    #[test]
    fn a_layer_another_conversion_replaced_is_refused() {
        struct Doubled;
        impl LinearForward for Doubled {
            fn forward(&self, layer: &Linear, x: &Tensor) -> Tensor {
                x.linear(&layer.weight, Some(&layer.bias)) * 2.0
            }
            fn describe(&self) -> String {
                "a doubled product".into()
            }
        }
        let (_, mut layers, store) = layers(4, None);
        layers[2].replace_forward(Box::new(Doubled));
        let e = add_adapters(&mut layers, cfg(0.0), 1).unwrap_err().to_string();
        assert_eq!(e, "blocks.1.q carries a doubled product; a LoRA adapter goes on a plain linear layer");
        assert!(adapter(&layers[0]).is_none() && store.named_parameters().len() == 6, "no adapter added");
    }
}
