#!/usr/bin/env python3
"""Reference for `bwm bench-vae` and for the encode rate of `bwm prepare`: DiffSynth's Wan2.2 VAE
(`WanVideoVAE38`, random weights, bf16, untiled, as the BWM release runs it) encoding a clip
[1, 3, 81, 480, 640] -> [1, 48, 21, 30, 40] and decoding those 21 latents -> 81 frames. Input
and output stay on the device (as in `bwm bench-vae`).

Prints per iteration and two summary lines:
  reference vae encode: A s per 81-frame clip, B frames/s, C clips/s, peak ...
  reference vae decode: A s per 21 latents, B frames/s, peak ...
"""

import argparse

import torch

import common


def parse():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_common_args(p, steps=3, warmup=1)
    common.add_vae_args(p)
    p.add_argument("--frames", type=int, default=81, help="pixel frames per clip (1 + 4k)")
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--width", type=int, default=640)
    a = p.parse_args()
    if a.tiny:
        a.frames, a.height, a.width = 9, 32, 32
    return a


def main():
    a = parse()
    _, vae_mod, _, _ = common.import_diffsynth()
    device, dtype = torch.device(a.device), common.DTYPES[a.dtype]
    common.header("reference vae", a)
    vae, desc = common.build_vae(vae_mod, a, device, dtype, a.seed)
    f_lat = 1 + (a.frames - 1) // 4
    print(f"reference vae: {desc}; clip [1, 3, {a.frames}, {a.height}, {a.width}] -> "
          f"[1, 48, {f_lat}, {a.height // 16}, {a.width // 16}]", flush=True)
    g = torch.Generator(device=device).manual_seed(a.seed + 2)
    video = (torch.rand([1, 3, a.frames, a.height, a.width], generator=g, device=device) * 2 - 1).to(dtype)

    enc_t, dec_t, enc_peak, dec_peak = [], [], "", ""
    for i in range(a.warmup + a.steps):
        timed = i >= a.warmup
        with torch.no_grad():
            common.reset_peak(device)
            with common.Timer(device) as te:
                z = vae.single_encode(video, device)
            ep = common.peak_text(device)
            common.reset_peak(device)
            with common.Timer(device) as td:
                x = vae.single_decode(z, device)
            dp = common.peak_text(device)
        assert list(z.shape) == [1, 48, f_lat, a.height // 16, a.width // 16], z.shape
        assert x.shape[2] == a.frames, x.shape
        if timed:
            enc_t.append(te.seconds)
            dec_t.append(td.seconds)
            enc_peak, dec_peak = ep, dp
        print(f"vae iter {i}{'' if timed else ' (warm-up)'}: encode {te.seconds:.3f} s, decode {td.seconds:.3f} s", flush=True)
        del z, x
    e, d = common.mean(enc_t), common.mean(dec_t)
    print(f"reference vae encode: {e:.3f} s per {a.frames}-frame clip (min {min(enc_t):.3f}), {a.frames / e:.1f} frames/s, "
          f"{1 / e:.3f} clips/s, {enc_peak} ({a.steps} iterations after {a.warmup} warm-up)", flush=True)
    print(f"reference vae decode: {d:.3f} s per {f_lat} latents (min {min(dec_t):.3f}), {a.frames / d:.1f} frames/s, "
          f"{dec_peak} ({a.steps} iterations after {a.warmup} warm-up)", flush=True)


if __name__ == "__main__":
    main()
