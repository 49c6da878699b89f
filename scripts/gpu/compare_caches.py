"""Compares the latents of two latent caches written by `bwm prepare` (same clips, same order):
prints the worst relative error per shard and exits 1 above the tolerance. Needs only torch (the
GPU machines have no safetensors package): the safetensors header is read by hand.

    python3 scripts/gpu/compare_caches.py DIR_A DIR_B [--tol 1e-2]
"""
import argparse
import json
import pathlib
import struct
import sys

import torch

DTYPES = {"BF16": torch.bfloat16, "F32": torch.float32, "F16": torch.float16, "F64": torch.float64, "I64": torch.int64, "I32": torch.int32, "U8": torch.uint8}


def tensors(path):
    raw = path.read_bytes()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8:8 + n])
    body = raw[8 + n:]
    out = {}
    for name, meta in header.items():
        if name == "__metadata__":
            continue
        start, end = meta["data_offsets"]
        t = torch.frombuffer(bytearray(body[start:end]), dtype=DTYPES[meta["dtype"]])
        out[name] = t.view(meta["shape"]) if meta["shape"] else t
    return out


def main():
    p = argparse.ArgumentParser()
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--tol", type=float, default=1e-2)
    a = p.parse_args()
    shards = sorted(pathlib.Path(a.a).glob("*.safetensors"))
    if not shards:
        sys.exit(f"no .safetensors files in {a.a}")
    worst = 0.0
    for sa in shards:
        ta, tb = tensors(sa), tensors(pathlib.Path(a.b) / sa.name)
        if sorted(ta) != sorted(tb):
            sys.exit(f"{sa.name}: different tensors")
        for name in ta:
            x, y = ta[name].float(), tb[name].float()
            err = ((x - y).abs().max() / y.abs().max().clamp_min(1e-12)).item()
            worst = max(worst, err)
        print(f"{sa.name}: {len(ta)} tensors, worst relative error so far {worst:.3e}")
    print(f"worst relative error {worst:.3e} (tolerance {a.tol})")
    sys.exit(0 if worst <= a.tol else 1)


if __name__ == "__main__":
    main()
