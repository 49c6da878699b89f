"""FLOPs of the reference DiT (DiffSynth-Studio's `WanModel`, with the BWM action encoder of
scripts/golden.py), counted by PyTorch's `torch.utils.flop_counter.FlopCounterMode`:
one sample's forward as `bwm_forward` of scripts/golden.py runs it, each part under a counter of its
own, and forward + backward.

FlopCounterMode counts matrix products, convolutions and attention, 2 FLOPs per multiply-add, and
no element-wise work (norms, modulation, RoPE, softmax, activations). Attention runs on PyTorch's
math path (`SDPBackend.MATH`): its products are counted as the two batched matmuls they are (the
CPU's fused attention kernel is not in FlopCounterMode's table).

usage: flop_count.py CONFIGS_JSON
  CONFIGS_JSON: a list of {"dit": {WanModel's widths}, "action_dim", "frames", "height", "width",
  "action_frames"} (latent frames, latent height and width, action frames).
Prints one JSON line, per config {"forward": {group: flops}, "train": {group: flops}}. The forward
groups: patch_embedding, blocks, head, time (the timestep embedding and projection),
action_encoder, and total (everything counted in one run). The train groups: total (forward and
backward of the whole), and patch_embedding, blocks and head each differentiated alone from inputs
that all require gradients.
"""
import json, sys
import torch
from torch.nn.attention import sdpa_kernel, SDPBackend
from torch.utils.flop_counter import FlopCounterMode
from diffsynth.models.wan_video_dit import WanModel, sinusoidal_embedding_1d

CONDITION_LATENTS = 3


class ActionEncoder(torch.nn.Module):
    # scripts/golden.py's BWM WanVideoActionEncoder (ti2v2 path).
    def __init__(self, action_dim, dim):
        super().__init__()
        self.action_mlp1 = torch.nn.Sequential(torch.nn.Linear(action_dim, dim), torch.nn.GELU(), torch.nn.Linear(dim, dim))
        self.action_mlp2 = torch.nn.Sequential(torch.nn.Linear(action_dim * 4, dim * 4), torch.nn.SiLU(), torch.nn.Linear(dim * 4, dim))

    def forward(self, a):
        ctx = self.action_mlp1(a)
        g = torch.cat([a[:, 0:1].repeat(1, 3, 1), a], dim=1)
        g = g.reshape(a.shape[0], (a.shape[1] + 3) // 4, a.shape[2] * 4)
        return ctx, self.action_mlp2(g)


def flops(fn):
    # fn's result and the FLOPs counted while it ran.
    with FlopCounterMode(display=False) as fc:
        out = fn()
    return out, fc.get_total_flops()


def rope(dit, f, h, w):
    return torch.cat([dit.freqs[0][:f].view(f, 1, 1, -1).expand(f, h, w, -1),
                      dit.freqs[1][:h].view(1, h, 1, -1).expand(f, h, w, -1),
                      dit.freqs[2][:w].view(1, 1, w, -1).expand(f, h, w, -1)], dim=-1).reshape(f * h * w, 1, -1)


def count(cfg):
    d = cfg["dit"]
    dit = WanModel(dim=d["dim"], in_dim=d["in_dim"], ffn_dim=d["ffn_dim"], out_dim=d["out_dim"], text_dim=d["text_dim"],
                   freq_dim=d["freq_dim"], eps=d["eps"], patch_size=tuple(d["patch_size"]), num_heads=d["num_heads"],
                   num_layers=d["num_layers"], has_image_input=False, seperated_timestep=True, require_clip_embedding=False,
                   require_vae_embedding=False, fuse_vae_embedding_in_latents=True)
    enc = ActionEncoder(cfg["action_dim"], d["dim"])
    torch.manual_seed(0)
    F, H, W = cfg["frames"], cfg["height"], cfg["width"]
    _, ph, pw = d["patch_size"]
    latents = torch.randn(1, d["in_dim"], F, H, W, requires_grad=True)
    actions = torch.rand(1, cfg["action_frames"], cfg["action_dim"], requires_grad=True)

    def forward(groups):
        # scripts/golden.py's bwm_forward, each part's FLOPs added to its group.
        def part(name, fn):
            out, n = flops(fn)
            groups[name] = groups.get(name, 0) + n
            return out

        ctx, mod = part("action_encoder", lambda: enc(actions))
        S = H * W // (ph * pw)
        t = torch.concat([torch.zeros((CONDITION_LATENTS, S)), torch.ones((F - CONDITION_LATENTS, S)) * 500.0]).flatten()

        def time():
            e = dit.time_embedding(sinusoidal_embedding_1d(dit.freq_dim, t).unsqueeze(0))
            e = e + mod.unsqueeze(2).repeat(1, 1, e.shape[1] // mod.shape[1], 1).flatten(1, 2)
            return e, dit.time_projection(e).unflatten(2, (6, dit.dim))

        temb, t_mod = part("time", time)
        x = part("patch_embedding", lambda: dit.patchify(latents))
        f, h, w = x.shape[2:]
        x = x.flatten(2).transpose(1, 2).contiguous()
        freqs = rope(dit, f, h, w)
        for blk in dit.blocks:
            x = part("blocks", lambda: blk(x, ctx, t_mod, freqs))
        return part("head", lambda: dit.head(x, temb))

    fwd = {}
    forward(fwd)
    _, fwd["total"] = flops(lambda: forward({}))
    _, whole = flops(lambda: forward({}).square().mean().backward())
    train = {"total": whole}
    # The formula's parts, forward + backward, each alone from inputs that all require gradients
    # (inside the model every part's input does, but the first's).
    f, h, w = F, H // ph, W // pw
    tokens = torch.randn(1, f * h * w, d["dim"], requires_grad=True)
    ctx = torch.randn(1, cfg["action_frames"], d["dim"], requires_grad=True)
    t_mod = torch.randn(1, f * h * w, 6, d["dim"], requires_grad=True)
    temb = torch.randn(1, f * h * w, d["dim"], requires_grad=True)
    _, n = flops(lambda: dit.blocks[0](tokens, ctx, t_mod, rope(dit, f, h, w)).square().mean().backward())
    train["blocks"] = n * len(dit.blocks)
    _, train["patch_embedding"] = flops(lambda: dit.patchify(latents).square().mean().backward())
    _, train["head"] = flops(lambda: dit.head(tokens, temb).square().mean().backward())
    return {"forward": fwd, "train": train}


with sdpa_kernel(SDPBackend.MATH):
    print(json.dumps([count(cfg) for cfg in json.loads(sys.argv[1])]))
