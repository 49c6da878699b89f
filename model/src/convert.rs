//! Conversions: steps applied to a built model from outside its code, each to the linear layers
//! whose module path (as in the checkpoint keys, `blocks.0.self_attn.q`) matches its patterns,
//! as PEFT injects adapters and torchtitan's `convert_to_float8_training` swaps modules. The
//! model's code stays the paper's: `nn::Linear` holds its weight and bias and computes
//! `x W^T + b` unless a conversion installed another product on it (`Linear::replace_forward`).
//!
//! - [`crate::lora`]: `add_adapters` puts a LoRA adapter on the chosen layers;
//! - [`crate::fp8`]: `quantize_linears` quantizes their weights for FP8 inference,
//!   `train_in_fp8` computes their products in FP8 while training.
//!
//! Design. A layer's product is a strategy (`nn::LinearForward`) that only conversions install;
//! the model's modules hold plain `Linear`s and call `forward` on them, so no model file names an
//! adapter or a float8 type and no branch of theirs asks whether one is there. A layer keeps its
//! place in the module tree (its `Vb`): its path is the name conversions select it by, the same
//! string as its checkpoint keys by construction, and a conversion that adds parameters (the
//! adapters' A and B) registers them under it with `Vb::add`, which lists them right after the
//! layer's own parameters: the store's order, and with it the optimizer's and a checkpoint's
//! trainable list, is the one a model built with the adapters had. The walk over the layers
//! (`Linears`) is written by hand per module next to the conversions, mirroring the modules'
//! fields; a test checks that it reaches every linear layer the store holds.
//!
//! The conversions stay modules of this crate rather than a crate of their own: they read the
//! model's module types and its parameter store, and the model's tests (rollouts in FP8, LoRA
//! numerics) exercise them with the model; no model module imports them.

use anyhow::{anyhow, Result};

use crate::action::ActionEncoder;
use crate::bwm::BwmModel;
use crate::dit::{Attention, Block, Head, Mlp2, WanDit};
use crate::nn::Linear;

/// Modules that hold linear layers: every one of them, in the order the module builds them.
pub trait Linears {
    fn linears_mut(&mut self) -> Vec<&mut Linear>;
}

/// The linear layers of `model` whose module path matches one of `patterns` (`*` matches
/// anything, dots included: `blocks.*.ffn.*`), in the model's order. An invalid pattern is an
/// error naming it.
pub fn select<'a, M: Linears + ?Sized>(model: &'a mut M, patterns: &[impl AsRef<str>]) -> Result<Vec<&'a mut Linear>> {
    let patterns = compile(patterns)?;
    Ok(model.linears_mut().into_iter().filter(|l| patterns.iter().any(|p| p.matches(l.path()))).collect())
}

/// Whether `path` matches one of `patterns` (as `select` matches them; invalid patterns match
/// nothing).
pub fn matches(patterns: &[impl AsRef<str>], path: &str) -> bool {
    patterns.iter().any(|p| glob::Pattern::new(p.as_ref()).is_ok_and(|p| p.matches(path)))
}

fn compile(patterns: &[impl AsRef<str>]) -> Result<Vec<glob::Pattern>> {
    patterns.iter().map(|p| glob::Pattern::new(p.as_ref()).map_err(|e| anyhow!("the layer pattern '{}' is invalid: {e}", p.as_ref()))).collect()
}

impl Linears for Linear {
    fn linears_mut(&mut self) -> Vec<&mut Linear> {
        vec![self]
    }
}

impl Linears for Mlp2 {
    fn linears_mut(&mut self) -> Vec<&mut Linear> {
        vec![&mut self.l0, &mut self.l2]
    }
}

impl Linears for Attention {
    fn linears_mut(&mut self) -> Vec<&mut Linear> {
        vec![&mut self.q, &mut self.k, &mut self.v, &mut self.o]
    }
}

impl Linears for Block {
    fn linears_mut(&mut self) -> Vec<&mut Linear> {
        let mut out = self.self_attn.linears_mut();
        out.extend(self.cross_attn.linears_mut());
        out.extend(self.ffn.linears_mut());
        out
    }
}

impl Linears for Head {
    fn linears_mut(&mut self) -> Vec<&mut Linear> {
        vec![&mut self.head]
    }
}

impl Linears for WanDit {
    fn linears_mut(&mut self) -> Vec<&mut Linear> {
        let mut out = self.text_embedding.as_mut().map(|m| m.linears_mut()).unwrap_or_default();
        out.extend(self.time_embedding.linears_mut());
        out.push(&mut self.time_projection);
        for block in &mut self.blocks {
            out.extend(block.linears_mut());
        }
        out.extend(self.head.linears_mut());
        out
    }
}

impl Linears for ActionEncoder {
    fn linears_mut(&mut self) -> Vec<&mut Linear> {
        let mut out = self.action_mlp1.linears_mut();
        out.extend(self.action_mlp2.linears_mut());
        if let Some(map) = &mut self.hand_map {
            out.extend(map.project.iter_mut());
            out.extend(map.mlp.linears_mut());
        }
        out
    }
}

impl Linears for BwmModel {
    fn linears_mut(&mut self) -> Vec<&mut Linear> {
        let mut out = self.dit.linears_mut();
        out.extend(self.action_encoder.linears_mut());
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{DitConfig, ModelConfig};
    use crate::vb::{with_seed, ParamStore};
    use crate::weights::{WeightSource, WeightsError};
    use std::collections::BTreeMap;
    use tch::{Device, Kind, Tensor};

    struct Tensors(BTreeMap<String, Tensor>);

    impl WeightSource for Tensors {
        fn describe(&self) -> String {
            "test weights".into()
        }
        fn names(&self) -> Vec<String> {
            self.0.keys().cloned().collect()
        }
        fn shape(&self, name: &str) -> Option<Vec<i64>> {
            self.0.get(name).map(|t| t.size())
        }
        fn load(&self, name: &str, kind: Kind, device: Device) -> Result<Tensor, WeightsError> {
            Ok(self.0.get(name).ok_or_else(|| WeightsError::missing(self.describe(), name))?.to_device(device).to_kind(kind))
        }
    }

    fn tiny_cfg() -> ModelConfig {
        ModelConfig { dit: DitConfig::tiny(), action: Default::default() }
    }

    /// Every 2-D weight of the store (the linear layers'; the patch embedding is 5-D, the norms and
    /// modulations are not 2-D) belongs to a layer of the walk, under the layer's path, and is
    /// that layer's tensor: a conversion by path sees every linear layer by its checkpoint name.
    #[test]
    fn the_walk_reaches_every_linear_layer_under_its_checkpoint_name() {
        // With the text embedding, which official checkpoints hold and a random model builds.
        let mut model = BwmModel::random(&tiny_cfg(), Kind::Float, Device::Cpu, 0).unwrap();
        let stored: Vec<(String, Tensor)> = model.store.named_parameters().into_iter().filter(|(_, t)| t.dim() == 2).collect();
        let layers = model.linears_mut();
        assert_eq!(layers.len(), stored.len(), "layers of the walk against 2-D weights in the store");
        for (layer, (name, weight)) in layers.iter().zip(&stored) {
            assert_eq!(format!("{}.weight", layer.path()), *name, "the walk follows the order of construction");
            assert!(layer.weight.is_set_to(weight), "{name} is another tensor than the layer's weight");
        }
        let paths: Vec<&str> = layers.iter().map(|l| l.path()).collect();
        for expected in ["text_embedding.0", "time_embedding.2", "time_projection.1", "blocks.0.self_attn.q", "blocks.1.ffn.2", "head.head", "action_encoder.action_mlp2.2"] {
            assert!(paths.contains(&expected), "{expected} missing from {paths:?}");
        }
    }

    #[test]
    fn layers_are_selected_by_path_pattern() {
        let mut model = BwmModel::random(&tiny_cfg(), Kind::Float, Device::Cpu, 0).unwrap();
        let blocks = model.cfg.dit.num_layers as usize;
        let paths = |ls: Vec<&mut Linear>| ls.iter().map(|l| l.path().to_string()).collect::<Vec<_>>();
        assert_eq!(paths(select(&mut model, &["blocks.*"]).unwrap()).len(), 10 * blocks);
        assert_eq!(paths(select(&mut model, &["blocks.*.self_attn.q", "head.head"]).unwrap()).len(), blocks + 1);
        assert_eq!(paths(select(&mut model.dit.blocks[0], &["*.ffn.*"]).unwrap()), ["blocks.0.ffn.0", "blocks.0.ffn.2"]);
        assert!(select(&mut model, &["no_such_layer"]).unwrap().is_empty());
        let e = select(&mut model, &["["]).err().unwrap().to_string();
        assert!(e.contains("'['"), "{e}");
        assert!(matches(&["blocks.*.q"], "blocks.3.cross_attn.q") && !matches(&["blocks.*.q"], "blocks.3.cross_attn.k"));
    }

    /// A parameter added to a built module is listed after the module's own, and read from the
    /// weight file where it holds it, drawn otherwise.
    #[test]
    fn added_parameters_follow_their_module_and_come_from_the_file_when_it_holds_them() {
        let build = |store: &std::rc::Rc<ParamStore>| {
            let root = store.root();
            let a = Linear::new(&root.pp("a"), 2, 2).unwrap();
            let _ab = Linear::new(&root.pp("ab"), 2, 2).unwrap();
            let b = Linear::new(&root.pp("b"), 2, 2).unwrap();
            (a, b)
        };
        let store = ParamStore::random(Kind::Float, Device::Cpu);
        let (a, b) = with_seed(0, || build(&store));
        let _ = a.vb().add(&[3], "extra.weight", crate::vb::Init::Ones).unwrap();
        let _ = b.vb().add(&[3], "extra.weight", crate::vb::Init::Ones).unwrap();
        let names: Vec<String> = store.named_parameters().into_iter().map(|(n, _)| n).collect();
        assert_eq!(names, ["a.weight", "a.bias", "a.extra.weight", "ab.weight", "ab.bias", "b.weight", "b.bias", "b.extra.weight"]);

        let mut file = store.named_parameters();
        file.retain(|(n, _)| n != "b.extra.weight");
        let _ = file.iter().find(|(n, _)| n == "a.extra.weight").unwrap().1.shallow_clone().fill_(7.0);
        let loaded = ParamStore::from_weights(Box::new(Tensors(file.into_iter().collect())), &[], Kind::Float, Device::Cpu);
        let (a, b) = build(&loaded);
        assert_eq!(a.vb().add(&[3], "extra.weight", crate::vb::Init::Zeros).unwrap().double_value(&[0]), 7.0, "read from the file");
        assert_eq!(b.vb().add(&[3], "extra.weight", crate::vb::Init::Zeros).unwrap().double_value(&[0]), 0.0, "drawn by its init");
        loaded.check_all_consumed().unwrap();
    }
}
