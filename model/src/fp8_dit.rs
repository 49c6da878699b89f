//! FP8 applied to the DiT from outside the model code, as the trainer and the inference loader
//! choose: the blocks' linear layers quantized for inference (`fp8::Fp8Weight`), or trained with
//! their products in FP8 (`bwm_fp8_autograd`).

use anyhow::{ensure, Result};
use tch::Tensor;

use crate::dit::WanDit;
use crate::fp8::{Fp8Scaling, Fp8Weight};
use crate::nn::Linear;

/// The linear layers of every DiT block (self- and cross-attention q, k, v, o and the FFN) by
/// name: the embeddings, time projection and head are left out, as torchao's float8 recipe leaves
/// the first and last layers.
fn block_linears(dit: &mut WanDit) -> Vec<(String, &mut Linear)> {
    let mut out = Vec::new();
    for (i, block) in dit.blocks.iter_mut().enumerate() {
        let linears = [
            ("self_attn.q", &mut block.self_attn.q),
            ("self_attn.k", &mut block.self_attn.k),
            ("self_attn.v", &mut block.self_attn.v),
            ("self_attn.o", &mut block.self_attn.o),
            ("cross_attn.q", &mut block.cross_attn.q),
            ("cross_attn.k", &mut block.cross_attn.k),
            ("cross_attn.v", &mut block.cross_attn.v),
            ("cross_attn.o", &mut block.cross_attn.o),
            ("ffn.0", &mut block.ffn.l0),
            ("ffn.2", &mut block.ffn.l2),
        ];
        out.extend(linears.into_iter().map(|(name, l)| (format!("blocks.{i}.{name}"), l)));
    }
    out
}

/// Quantizes the DiT blocks' linear layers (`block_linears`) to FP8 for inference. Returns how
/// many layers were quantized.
pub fn quantize_dit_blocks(dit: &mut WanDit, scaling: Fp8Scaling) -> Result<usize> {
    let mut n = 0;
    for (name, linear) in block_linears(dit) {
        ensure!(linear.lora.is_none(), "{name} carries a LoRA adapter; merge it before quantizing to FP8");
        let weight = tch::no_grad(|| Fp8Weight::new(&linear.weight, scaling)).map_err(|e| e.context(name))?;
        linear.fp8 = Some(weight);
        n += 1;
    }
    Ok(n)
}

/// Trains the DiT blocks' linear layers (`block_linears`) with their three products in FP8
/// (`bwm_fp8_autograd`: per-tensor dynamic scales, e4m3 forward, e5m2 gradients); the weights,
/// and whatever masters and optimizer state the trainer keeps, stay as they are. Checks every
/// layer's shape and, with one small product, that the device has FP8 matmuls; an error leaves
/// the model as it was. Products of fewer than `min_rows` rows stay in the weights' dtype (where
/// scaling the weight costs more than FP8 saves). Returns how many layers train so.
pub fn train_dit_blocks_in_fp8(dit: &mut WanDit, min_rows: i64) -> Result<usize> {
    let mut linears = block_linears(dit);
    for (name, linear) in &linears {
        ensure!(linear.lora.is_none(), "{name} carries a LoRA adapter; FP8 training covers full weights only");
        bwm_fp8_autograd::check_weight(&linear.weight, &linear.bias).map_err(|e| e.context(format!("{name} cannot train in FP8")))?;
    }
    // The blocks share one device and dtype: one product says whether it has FP8 matmuls.
    if let Some((name, linear)) = linears.first() {
        let w = &linear.weight;
        let x = Tensor::zeros([1, w.size()[1]], (w.kind(), w.device()));
        tch::no_grad(|| bwm_fp8_autograd::linear(&x, w, &linear.bias).map(drop))
            .map_err(|e| e.context(format!("{name} cannot train in FP8 on {:?}", w.device())))?;
    }
    for (_, linear) in &mut linears {
        linear.fp8_training = Some(min_rows);
    }
    Ok(linears.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DitConfig;
    use crate::lora::LoraConfig;
    use crate::vb::{with_seed, ParamStore};
    use tch::{Device, Kind};

    fn tiny(lora: Option<LoraConfig>) -> WanDit {
        with_seed(0, || {
            let store = ParamStore::random(Kind::Float, Device::Cpu);
            if let Some(cfg) = lora {
                store.enable_lora(cfg, 0).unwrap();
            }
            WanDit::new(&store.root(), &DitConfig::tiny())
        })
        .unwrap()
    }

    #[test]
    fn every_block_linear_is_named_and_switched() {
        let mut dit = tiny(None);
        let names: Vec<String> = block_linears(&mut dit).into_iter().map(|(n, _)| n).collect();
        assert_eq!(names.len(), 10 * dit.blocks.len());
        assert_eq!((names[0].as_str(), names[9].as_str()), ("blocks.0.self_attn.q", "blocks.0.ffn.2"));
        assert_eq!(train_dit_blocks_in_fp8(&mut dit, 0).unwrap(), names.len());
        assert!(block_linears(&mut dit).iter().all(|(_, l)| l.fp8_training == Some(0) && l.fp8.is_none()));
    }

    #[test]
    fn layers_with_lora_adapters_are_refused() {
        let lora = LoraConfig { rank: 2, alpha: None, dropout: 0.0, targets: vec!["blocks.*.ffn.*".into()] };
        let mut dit = tiny(Some(lora));
        let e = train_dit_blocks_in_fp8(&mut dit, 0).unwrap_err().to_string();
        assert!(e.contains("blocks.0.ffn.0 carries a LoRA adapter"), "{e}");
        assert!(block_linears(&mut dit).iter().all(|(_, l)| l.fp8_training.is_none()), "no layer switched");
    }

    /// Products of at least `min_rows` rows go through float8, smaller ones are the exact linear.
    #[test]
    fn products_under_the_row_threshold_stay_exact() {
        let mut dit = tiny(None);
        train_dit_blocks_in_fp8(&mut dit, 8).unwrap();
        let linear = &dit.blocks[0].ffn.l0;
        let w = &linear.weight;
        for rows in [1, 3, 4, 40] {
            let x = Tensor::randn([2, rows, w.size()[1]], (w.kind(), w.device()));
            let exact = x.linear(w, Some(&linear.bias));
            let y = linear.forward(&x);
            assert_eq!(y.equal(&exact), 2 * rows < 8, "a product of {} rows", 2 * rows);
        }
    }
}
