#!/usr/bin/env python3
"""Times libtorch's scaled-dot-product-attention kernels (flash, cuDNN, memory-efficient, math) on
the 5B DiT's attention shapes, forward and forward + backward, as `bwm --sdp-backend` can force
them: self-attention over the 6,300 tokens of a 640x480 clip of 1 + 8 + 72 frames and
cross-attention to the 81 action tokens, 24 heads of 128, bf16. Which kernel libtorch picks on
its own (`auto`) is printed too. Python's torch is the same libtorch 2.11 the bwm binary links.

usage: python3 scripts/gpu/sdpa_backends.py [--tokens 6300] [--context 81] [--iters 20]
"""
import argparse

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.nn.functional import scaled_dot_product_attention as sdpa

p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
p.add_argument("--tokens", type=int, default=6300)
p.add_argument("--context", type=int, default=81)
p.add_argument("--heads", type=int, default=24)
p.add_argument("--head-dim", type=int, default=128)
p.add_argument("--iters", type=int, default=20)
a = p.parse_args()

dev = torch.device("cuda")
print(f"sdpa: torch {torch.__version__}, {torch.cuda.get_device_name()}, cuDNN {torch.backends.cudnn.version()}")
BACKENDS = {"flash": SDPBackend.FLASH_ATTENTION, "cudnn": SDPBackend.CUDNN_ATTENTION,
            "efficient": SDPBackend.EFFICIENT_ATTENTION, "math": SDPBackend.MATH}


def timed(fn, iters):
    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    for _ in range(iters):
        fn()
    end.record()
    torch.cuda.synchronize()
    return start.elapsed_time(end) / iters


for name, kv_tokens in (("self-attention", a.tokens), ("cross-attention", a.context)):
    g = torch.Generator(device=dev).manual_seed(0)
    shape_q, shape_kv = (1, a.heads, a.tokens, a.head_dim), (1, a.heads, kv_tokens, a.head_dim)
    q = torch.randn(shape_q, device=dev, dtype=torch.bfloat16, generator=g, requires_grad=True)
    k = torch.randn(shape_kv, device=dev, dtype=torch.bfloat16, generator=g, requires_grad=True)
    v = torch.randn(shape_kv, device=dev, dtype=torch.bfloat16, generator=g, requires_grad=True)
    grad = torch.randn(shape_q, device=dev, dtype=torch.bfloat16, generator=g)
    choice = {-1: "none", 0: "math", 1: "flash", 2: "efficient", 3: "cudnn", 4: "overrideable"}[int(torch._fused_sdp_choice(q, k, v))]
    print(f"{name}: q {list(shape_q)}, kv {list(shape_kv)}; libtorch's own choice: {choice}")
    with torch.no_grad():
        reference = sdpa(q.float(), k.float(), v.float())
    flops = 4 * a.heads * a.tokens * kv_tokens * a.head_dim
    for label, backend in BACKENDS.items():
        with sdpa_kernel([backend]):
            try:
                with torch.no_grad():
                    err = (sdpa(q, k, v).float() - reference).abs().max().item()
                    fwd = timed(lambda: sdpa(q, k, v), a.iters)
                both = timed(lambda: torch.autograd.grad(sdpa(q, k, v), (q, k, v), grad), a.iters)
            except RuntimeError as e:
                print(f"  {label:9s}: not available ({str(e).splitlines()[0][:120]})")
                continue
        print(f"  {label:9s}: forward {fwd:.3f} ms ({flops / fwd / 1e9:.0f} TFLOP/s), forward + backward {both:.3f} ms, "
              f"max |diff| from fp32 {err:.2e}")
