"""Loads a BWM LoRA adapter export onto the base WanTransformer3DModel with diffusers' own loader
(load_lora_adapter, PEFT underneath) and checks every adapted layer's effective weight, base +
PEFT's delta, against the merged export (`bwm export --merge-lora`), then diffusers' forward of
the adapted model against its forward of the merged export on the same inputs (the merged export's
forward is checked against ours by checkpoints/tests/python/interop.py).

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
merged_model = WanTransformer3DModel.from_pretrained(os.path.join(merged_dir, "transformer"), torch_dtype=torch.float32)
merged = merged_model.state_dict()
layers, worst = 0, 0.0
for name, module in model.named_modules():
    if hasattr(module, "get_delta_weight") and "bwm" in getattr(module, "lora_A", {}):
        effective = module.base_layer.weight + module.get_delta_weight("bwm")
        worst = max(worst, (effective - merged[name + ".weight"]).abs().max().item())
        layers += 1
print(f"adapted layers {layers}, largest difference from the merged export {worst:.3g}")
assert layers == expected, f"diffusers adapted {layers} layers, the export holds {expected}"
assert worst < 1e-5, worst

# The exports leave out the text embedder (the action model never runs it): both models get the
# same one, drawn here.
torch.manual_seed(0)
for p in model.condition_embedder.text_embedder.parameters():
    torch.nn.init.normal_(p, std=0.02)
merged_model.condition_embedder.text_embedder.load_state_dict(model.condition_embedder.text_embedder.state_dict())
cfg = model.config
g = torch.Generator().manual_seed(0)
p_t, p_h, p_w = cfg.patch_size
x = torch.randn(1, cfg.in_channels, 2 * p_t, 2 * p_h, 2 * p_w, generator=g)
context = torch.randn(1, 5, cfg.text_dim, generator=g)
t = torch.tensor([437.0])
with torch.no_grad():
    adapted_out = model(x, t, context, return_dict=False)[0]
    merged_out = merged_model(x, t, context, return_dict=False)[0]
scale = merged_out.abs().max().item()
diff = (adapted_out - merged_out).abs().max().item()
print(f"forward: adapted vs merged largest difference {diff:.3g} (output scale {scale:.3g})")
assert scale > 0 and diff <= 1e-4 * max(1.0, scale), diff
