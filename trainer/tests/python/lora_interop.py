"""Loads a BWM LoRA adapter export onto the base WanTransformer3DModel with diffusers' own loader
(load_lora_adapter, PEFT underneath) and checks every adapted layer's effective weight, base +
PEFT's delta, against the merged export (`bwm export --merge-lora`).

usage: lora_interop.py BASE_DIFFUSERS_DIR ADAPTER_DIR MERGED_DIFFUSERS_DIR EXPECTED_LAYERS
"""
import os, sys
import torch
from diffusers import WanTransformer3DModel
from safetensors.torch import load_file

base_dir, adapter_dir, merged_dir, expected = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
model = WanTransformer3DModel.from_pretrained(os.path.join(base_dir, "transformer"), torch_dtype=torch.float32)
adapter = load_file(os.path.join(adapter_dir, "pytorch_lora_weights.safetensors"))
model.load_lora_adapter(adapter, prefix="transformer", adapter_name="bwm")
merged = WanTransformer3DModel.from_pretrained(os.path.join(merged_dir, "transformer"), torch_dtype=torch.float32).state_dict()
layers, worst = 0, 0.0
for name, module in model.named_modules():
    if hasattr(module, "get_delta_weight") and "bwm" in getattr(module, "lora_A", {}):
        effective = module.base_layer.weight + module.get_delta_weight("bwm")
        worst = max(worst, (effective - merged[name + ".weight"]).abs().max().item())
        layers += 1
print(f"adapted layers {layers}, largest difference from the merged export {worst:.3g}")
assert layers == expected, f"diffusers adapted {layers} layers, the export holds {expected}"
assert worst < 1e-5, worst
