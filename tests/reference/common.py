"""Shared helpers of the reference benchmarks (PyPI `diffsynth`, torch).

`diffsynth/__init__.py` imports the whole package (pipelines, transformers, modelscope, pandas,
imageio, ...). The benchmarks need only three of its modules, so `import_diffsynth` registers
empty parent packages pointing at the installed folders and imports just those modules; what
they execute needs nothing beyond torch, einops, numpy, tqdm and typing_extensions.
"""

import argparse
import importlib
import importlib.util
import math
import sys
import time
import types

import torch

# The Wan2.2-TI2V-5B DiT as DiffSynth builds it (diffsynth/configs/model_configs.py, the entry
# whose comment names "Wan-AI/Wan2.2-TI2V-5B").
DIT_5B = dict(
    has_image_input=False, patch_size=[1, 2, 2], in_dim=48, dim=3072, ffn_dim=14336, freq_dim=256,
    text_dim=4096, out_dim=48, num_heads=24, num_layers=30, eps=1e-6, seperated_timestep=True,
    require_clip_embedding=False, require_vae_embedding=False, fuse_vae_embedding_in_latents=True,
)
# A DiT small enough for CPU tests (head dim 48 keeps the 3-axis RoPE split even: 16/16/16).
DIT_TINY = dict(DIT_5B, dim=96, ffn_dim=256, text_dim=64, num_heads=2, num_layers=2)

_MODULES = {}


def import_diffsynth():
    """Returns (wan_video_dit, wan_video_vae, flow_match, gradient) modules of the installed diffsynth."""
    if _MODULES:
        return _MODULES["dit"], _MODULES["vae"], _MODULES["flow"], _MODULES["grad"]
    if "diffsynth" not in sys.modules:
        spec = importlib.util.find_spec("diffsynth")  # locates the package without running it
        if spec is None or not spec.submodule_search_locations:
            raise SystemExit("diffsynth is not installed (see tests/reference/README.md)")
        root = list(spec.submodule_search_locations)[0]
        for name, sub in [("diffsynth", ""), ("diffsynth.core", "/core"), ("diffsynth.diffusion", "/diffusion")]:
            m = types.ModuleType(name)
            m.__path__ = [root + sub]
            m.__package__ = name
            sys.modules[name] = m
    _MODULES["dit"] = importlib.import_module("diffsynth.models.wan_video_dit")
    _MODULES["vae"] = importlib.import_module("diffsynth.models.wan_video_vae")
    _MODULES["flow"] = importlib.import_module("diffsynth.diffusion.flow_match")
    _MODULES["grad"] = importlib.import_module("diffsynth.core.gradient.gradient_checkpoint")
    return _MODULES["dit"], _MODULES["vae"], _MODULES["flow"], _MODULES["grad"]


def diffsynth_version():
    try:
        from importlib.metadata import version
        return version("diffsynth")
    except Exception:  # pragma: no cover - metadata missing in an unpacked tree
        return "unknown"


DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16, "fp32": torch.float32}


def add_common_args(p: argparse.ArgumentParser, steps: int, warmup: int):
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--dtype", default="bf16", choices=sorted(DTYPES))
    p.add_argument("--steps", type=int, default=steps, help="timed iterations after warm-up")
    p.add_argument("--warmup", type=int, default=warmup, help="untimed iterations first")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tiny", action="store_true",
                   help="tiny model and shapes, for a CPU smoke test (overrides the shape flags)")
    p.add_argument("--attention", default="sdpa", choices=["sdpa", "auto"],
                   help="sdpa: force torch scaled_dot_product_attention in DiffSynth's attention; "
                        "auto: DiffSynth's own choice (flash-attn 3/2, sage, else SDPA)")


def add_dit_args(p: argparse.ArgumentParser):
    g = p.add_argument_group("DiT (defaults: Wan2.2-TI2V-5B)")
    for k in ["dim", "ffn_dim", "num_heads", "num_layers", "text_dim", "freq_dim"]:
        g.add_argument("--" + k.replace("_", "-"), dest=k, type=int, default=None)
    g.add_argument("--conditioning", default="action", choices=["action", "text"],
                   help="action: the BWM release's action encoder (context = one token per pixel frame "
                        "through action_mlp1, action_mlp2 added to the time embedding per latent frame, "
                        "text_embedding unused and frozen); text: a random [1, N, text_dim] context "
                        "through the DiT's text_embedding (trained)")
    g.add_argument("--context-tokens", type=int, default=20, help="N of --conditioning text")
    g.add_argument("--action-dim", type=int, default=14)


def dit_config(args):
    cfg = dict(DIT_TINY if args.tiny else DIT_5B)
    for k in ["dim", "ffn_dim", "num_heads", "num_layers", "text_dim", "freq_dim"]:
        v = getattr(args, k, None)
        if v is not None:
            cfg[k] = v
    return cfg


def set_attention(dit_mod, mode):
    """Makes DiffSynth's `flash_attention` fall through to torch SDPA (its last branch)."""
    if mode == "sdpa":
        dit_mod.FLASH_ATTN_3_AVAILABLE = False
        dit_mod.FLASH_ATTN_2_AVAILABLE = False
        dit_mod.SAGE_ATTN_AVAILABLE = False
    if dit_mod.FLASH_ATTN_3_AVAILABLE:
        return "flash-attn 3"
    if dit_mod.FLASH_ATTN_2_AVAILABLE:
        return "flash-attn 2"
    if dit_mod.SAGE_ATTN_AVAILABLE:
        return "sageattention"
    return "torch SDPA"


def build_dit(dit_mod, cfg, device, dtype, seed):
    """Random-weight WanModel (PyTorch default init) built directly on `device`, cast to `dtype`."""
    torch.manual_seed(seed)
    with torch.device(device):
        dit = dit_mod.WanModel(**cfg)
    return dit.to(dtype)


class ActionEncoder(torch.nn.Module):
    """The BWM release's `WanVideoActionEncoder` (ti2v2 path; docs/architecture.md, The BWM release).

    It is not part of diffsynth; it is two small MLPs. action_mlp1: Linear(d_a, D) -> GELU ->
    Linear(D, D), one cross-attention token per pixel frame; action_mlp2: Linear(4 d_a, 4 D) ->
    SiLU -> Linear(4 D, D) over groups of G=4 actions after prepending P=3 copies of a_0, one
    vector per latent frame.
    """

    def __init__(self, action_dim, dim, group=4, prepend=3):
        super().__init__()
        self.group, self.prepend = group, prepend
        self.action_mlp1 = torch.nn.Sequential(
            torch.nn.Linear(action_dim, dim), torch.nn.GELU(), torch.nn.Linear(dim, dim))
        self.action_mlp2 = torch.nn.Sequential(
            torch.nn.Linear(action_dim * group, dim * group), torch.nn.SiLU(), torch.nn.Linear(dim * group, dim))

    def forward(self, action):  # [B, F, d_a], F = 1 + 4k
        context = self.action_mlp1(action)
        grouped = torch.cat([action[:, 0:1].repeat(1, self.prepend, 1), action], dim=1)
        grouped = grouped.reshape(action.shape[0], (action.shape[1] + self.prepend) // self.group,
                                  action.shape[2] * self.group)
        return context, self.action_mlp2(grouped)  # [B, F, D], [B, F_latent, D]


def build_action_encoder(cfg, action_dim, device, dtype, seed):
    torch.manual_seed(seed + 1)
    with torch.device(device):
        enc = ActionEncoder(action_dim, cfg["dim"])
    return enc.to(dtype)


def model_fn(dit, dit_mod, grad_mod, latents, timestep, context, condition_latents, action_mod=None,
             checkpointing=False, text_context=True):
    """One DiT forward, as DiffSynth's `model_fn_wan_video` runs the TI2V-5B
    (`seperated_timestep and fuse_vae_embedding_in_latents`) with the BWM release's change
    (`model_fn_wan_video_action`): per-token timesteps, 0 on the first `condition_latents` latent
    frames (DiffSynth itself pins only 1), `timestep` on the rest; the time embedding is computed
    for every token; the action vector of each latent frame is added to it before
    `time_projection`; blocks through DiffSynth's `gradient_checkpoint_forward` (per-block
    `torch.utils.checkpoint`, use_reentrant=False, when `checkpointing`)."""
    b, _, f_lat, h_lat, w_lat = latents.shape
    s = h_lat * w_lat // 4  # tokens per latent frame after the 1x2x2 patch
    t = torch.concat([
        torch.zeros((condition_latents, s), dtype=latents.dtype, device=latents.device),
        torch.ones((f_lat - condition_latents, s), dtype=latents.dtype, device=latents.device) * timestep,
    ]).flatten()
    t = dit.time_embedding(dit_mod.sinusoidal_embedding_1d(dit.freq_dim, t).unsqueeze(0))
    if action_mod is not None:
        t = t + action_mod.unsqueeze(2).repeat(1, 1, s, 1).flatten(1, 2)
    t_mod = dit.time_projection(t).unflatten(2, (6, dit.dim))
    if text_context:
        context = dit.text_embedding(context)
    x = dit.patchify(latents)
    f, h, w = x.shape[2:]
    x = dit_mod.rearrange(x, "b c f h w -> b (f h w) c").contiguous()
    freqs = torch.cat([
        dit.freqs[0][:f].view(f, 1, 1, -1).expand(f, h, w, -1),
        dit.freqs[1][:h].view(1, h, 1, -1).expand(f, h, w, -1),
        dit.freqs[2][:w].view(1, 1, w, -1).expand(f, h, w, -1),
    ], dim=-1).reshape(f * h * w, 1, -1).to(x.device)
    for block in dit.blocks:
        x = grad_mod.gradient_checkpoint_forward(block, checkpointing, False, x, context, t_mod, freqs)
    x = dit.head(x, t)
    return dit.unpatchify(x, (f, h, w))


def sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def reset_peak(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)


def peak_text(device):
    if torch.device(device).type != "cuda":
        return "peak n/a (cpu)"
    alloc = torch.cuda.max_memory_allocated(device) / 2**20
    reserved = torch.cuda.max_memory_reserved(device) / 2**20
    return f"peak {alloc:.0f} MiB allocated, {reserved:.0f} MiB reserved"


class Timer:
    def __init__(self, device):
        self.device = device

    def __enter__(self):
        sync(self.device)
        self.start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        sync(self.device)
        self.seconds = time.perf_counter() - self.start


def mean(xs):
    return sum(xs) / len(xs) if xs else math.nan


def header(name, args, extra=""):
    dev = torch.device(args.device)
    what = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"
    print(f"{name}: torch {torch.__version__}, diffsynth {diffsynth_version()}, device {args.device} ({what}), "
          f"dtype {args.dtype}{', TINY' if args.tiny else ''}{extra}", flush=True)


def forward_flops(cfg, tokens, context):
    """Model FLOPs of one DiT forward, the same count as the Rust trainer's `trainer/src/flops.rs`
    (matmuls and attention, 2 FLOPs per multiply-add; the time MLP and norms not counted)."""
    d, l, c, ffn = float(cfg["dim"]), float(tokens), float(context), float(cfg["ffn_dim"])
    self_attn = 2 * 4 * l * d * d + 2 * 2 * l * l * d
    cross_attn = 2 * 2 * l * d * d + 2 * 2 * c * d * d + 2 * 2 * l * c * d
    mlp = 2 * 2 * l * d * ffn
    patch = math.prod(cfg["patch_size"])
    embed = 2 * l * (cfg["in_dim"] * patch) * d
    head = 2 * l * d * (cfg["out_dim"] * patch)
    return cfg["num_layers"] * (self_attn + cross_attn + mlp) + embed + head


VAE_FULL = dict(dim=160, dec_dim=256)  # Wan2.2_VAE.pth: WanVideoVAE38 (z_dim 48, 704.7 M parameters)
VAE_TINY = dict(dim=16, dec_dim=16)


def add_vae_args(p: argparse.ArgumentParser):
    g = p.add_argument_group("VAE (defaults: the Wan2.2 VAE)")
    g.add_argument("--vae-dim", type=int, default=None)
    g.add_argument("--vae-dec-dim", type=int, default=None)


def build_vae(vae_mod, args, device, dtype, seed):
    """Random-weight `WanVideoVAE38` (DiffSynth's class for Wan2.2_VAE.pth, z_dim 48), built on
    `device`. Its constructor fixes dec_dim at 256; other widths (--tiny) are passed through."""
    base = VAE_TINY if args.tiny else VAE_FULL
    dim = args.vae_dim or base["dim"]
    dec_dim = args.vae_dec_dim or base["dec_dim"]
    torch.manual_seed(seed + 3)
    orig = vae_mod.VideoVAE38_
    if dec_dim != 256:
        vae_mod.VideoVAE38_ = lambda **kw: orig(dec_dim=dec_dim, **kw)
    try:
        with torch.device(device):
            vae = vae_mod.WanVideoVAE38(z_dim=48, dim=dim)
    finally:
        vae_mod.VideoVAE38_ = orig
    vae = vae.to(dtype).eval().requires_grad_(False)
    n = sum(p.numel() for p in vae.parameters())
    return vae, f"WanVideoVAE38 dim {dim}, dec_dim {dec_dim}, z_dim 48, {n:,} parameters"
