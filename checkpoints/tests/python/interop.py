"""Loads the three exports of one tiny BWM model with the Python reference stack and runs the
reference forward on each.

usage: interop.py GOLDEN_PY WAN_DIR DIFFUSERS_DIR RELEASE_DIR CASE OUT

- wan:       DiffSynth-Studio's WanModel (diffsynth==2.0.11, the BWM release's framework), strict=False:
             the missing keys must be exactly the ones config.json declares (text_embedding.*).
- diffusers: WanTransformer3DModel.from_pretrained(<dir>/transformer); missing keys must be exactly
             condition_embedder.text_embedder.*; its state dict, renamed with DiffSynth's own
             diffusers->Wan converter (an independent key map), runs the reference forward.
- release:   split on `pipe.action_encoder.` as the BWM release loader does, strict=False.

The reference forward is `bwm_forward` (and the `ActionEncoder` it uses) of scripts/golden.py, the
generator of the golden files (importing it computes nothing).
"""
import importlib.util, json, sys, os
import torch
from safetensors.torch import load_file, save_file
from diffsynth.models.wan_video_dit import WanModel
from diffsynth.utils.state_dict_converters.wan_video_dit import WanVideoDiTFromDiffusers
from diffusers import WanTransformer3DModel

golden_py, wan_dir, diff_dir, rel_dir, case_path, out_path = sys.argv[1:7]

spec = importlib.util.spec_from_file_location("bwm_golden", golden_py)
golden = importlib.util.module_from_spec(spec)
spec.loader.exec_module(golden)

def load_sharded(index_path):
    index = json.load(open(index_path))
    sd = {}
    for f in sorted(set(index["weight_map"].values())):
        sd.update(load_file(os.path.join(os.path.dirname(index_path), f)))
    assert set(sd) == set(index["weight_map"]), "index and shards disagree"
    return sd

cfg = json.load(open(os.path.join(wan_dir, "config.json")))
d = cfg["dit"]
def new_dit():
    return WanModel(dim=d["dim"], in_dim=d["in_dim"], ffn_dim=d["ffn_dim"], out_dim=d["out_dim"], text_dim=d["text_dim"],
                    freq_dim=d["freq_dim"], eps=d["eps"], patch_size=tuple(d["patch_size"]), num_heads=d["num_heads"],
                    num_layers=d["num_layers"], has_image_input=False, seperated_timestep=True, require_clip_embedding=False,
                    require_vae_embedding=False, fuse_vae_embedding_in_latents=True).eval()

case = load_file(case_path)
latents, timestep, actions = case["latents"], case["timestep"][0], case["actions"]
report = {}

def run(dit_sd, enc_sd, tag):
    dit = new_dit()
    missing, unexpected = dit.load_state_dict(dit_sd, strict=False)
    enc = golden.ActionEncoder(cfg["action"]["action_dim"], d["dim"]).eval()
    enc.load_state_dict(enc_sd, strict=True)
    with torch.no_grad():
        v, _ = golden.bwm_forward(dit, enc, latents, timestep, actions, cond_t=3)
    report[tag] = {"missing": sorted(missing), "unexpected": sorted(unexpected)}
    return v.contiguous()

out = {}
# Wan-native export.
sd = load_sharded(os.path.join(wan_dir, cfg["weights"]["index_files"][0]))
p = cfg["weights"]["action_encoder_prefix"]
out["wan"] = run({k: v for k, v in sd.items() if not k.startswith(p)}, {k[len(p):]: v for k, v in sd.items() if k.startswith(p)}, "wan")
report["wan"]["declared_missing"] = sorted(cfg["weights"]["missing_keys"])
wan_sd = sd

# diffusers export.
model, info = WanTransformer3DModel.from_pretrained(os.path.join(diff_dir, "transformer"), output_loading_info=True,
                                                    torch_dtype=torch.float32)
dsd = {k: v for k, v in model.state_dict().items() if not k.startswith("condition_embedder.text_embedder.")}
converted = WanVideoDiTFromDiffusers(dsd)
enc_sd = load_sharded(os.path.join(diff_dir, "action_encoder", "model.safetensors.index.json"))
out["diffusers"] = run(converted, enc_sd, "diffusers")
report["diffusers"]["from_pretrained"] = {k: sorted(v) if isinstance(v, list) else str(v) for k, v in info.items()}
# The same tensors as the Wan-native export, by DiffSynth's independent diffusers->Wan key map.
report["diffusers"]["differs_from_wan_export"] = sorted(k for k, v in converted.items() if not torch.equal(v, wan_sd[k]))
report["diffusers"]["converted_keys"] = len(converted)

# BWM-release export: the release loader splits on the prefix.
rcfg = json.load(open(os.path.join(rel_dir, "config.json")))
sd = load_sharded(os.path.join(rel_dir, rcfg["weights"]["index_files"][0]))
pre = "pipe.action_encoder."
out["release"] = run({k: v for k, v in sd.items() if not k.startswith(pre)}, {k[len(pre):]: v for k, v in sd.items() if k.startswith(pre)}, "release")

save_file(out, out_path)
print(json.dumps(report))
