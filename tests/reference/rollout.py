#!/usr/bin/env python3
"""Reference for `bwm bench-rollout`: one autoregressive rollout chunk of the BWM world model with
DiffSynth's modules (random weights), as the BWM release's inference runs it:

1. VAE-encode the condition clip [x0, h1..h8] = [1, 3, 9, 480, 640] (one causal clip -> 3 latents),
2. 50 Euler steps (FlowMatchScheduler("Wan"), shift 5, no CFG) of the DiT on [1, 48, 21, 30, 40]
   latents (3 condition latents at t=0 + 18 generated), the condition latents re-imposed after
   every step, bf16, torch.no_grad,
3. VAE-decode the 21 latents (-> 81 frames) and copy them to the host in fp32.

Like the Rust rollout, the condition frames start on the host (fp32) and the decoded frames end
there. Prints per chunk and one summary line:
  reference rollout: T s per chunk = encode A s + DiT B s (C s/step) + decode D s, ..., peak ...
"""

import argparse

import torch

import common


def parse():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_common_args(p, steps=1, warmup=1)
    common.add_dit_args(p)
    common.add_vae_args(p)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--history", type=int, default=8, help="history pixel frames after x0")
    p.add_argument("--future", type=int, default=72, help="generated pixel frames per chunk")
    p.add_argument("--sample-steps", type=int, default=50)
    p.add_argument("--shift", type=float, default=5.0)
    a = p.parse_args()
    if a.tiny:
        a.height, a.width, a.history, a.future, a.sample_steps = 32, 32, 8, 8, 3
    return a


def main():
    a = parse()
    dit_mod, vae_mod, flow_mod, grad_mod = common.import_diffsynth()
    attention = common.set_attention(dit_mod, a.attention)
    device, dtype = torch.device(a.device), common.DTYPES[a.dtype]
    cfg = common.dit_config(a)
    common.header("reference rollout", a, f", attention {attention}")
    dit = common.build_dit(dit_mod, cfg, device, dtype, a.seed).eval().requires_grad_(False)
    enc = None
    if a.conditioning == "action":
        enc = common.build_action_encoder(cfg, a.action_dim, device, dtype, a.seed).eval().requires_grad_(False)
    vae, vae_desc = common.build_vae(vae_mod, a, device, dtype, a.seed)
    sched = flow_mod.FlowMatchScheduler("Wan")
    sched.set_timesteps(a.sample_steps, shift=a.shift)

    cond_frames = 1 + a.history
    pixel_frames = cond_frames + a.future
    p_lat = 1 + a.history // 4
    f_lat = p_lat + a.future // 4
    shape = [1, cfg["in_dim"], f_lat, a.height // 16, a.width // 16]
    n_ctx = pixel_frames if enc is not None else a.context_tokens
    print(f"reference rollout: WanModel {sum(p.numel() for p in dit.parameters()):,} parameters, {vae_desc}; "
          f"condition clip [1, 3, {cond_frames}, {a.height}, {a.width}] -> {p_lat} latents, latents {shape}, "
          f"{a.sample_steps} Euler steps (shift {a.shift}), context {n_ctx} tokens ({a.conditioning})", flush=True)

    g = torch.Generator(device=device).manual_seed(a.seed + 2)

    def chunk():
        cond_video = torch.rand([1, 3, cond_frames, a.height, a.width]) * 2 - 1  # host, fp32
        actions = torch.rand([1, pixel_frames, a.action_dim], generator=g, device=device) * 2 - 1
        text = torch.randn([1, a.context_tokens, cfg["text_dim"]], generator=g, device=device).to(dtype)
        noise = torch.randn(shape, generator=g, device=device).to(dtype)
        with torch.no_grad():
            with common.Timer(device) as te:
                cond = vae.single_encode(cond_video.to(device, dtype), device)  # [1, 48, p_lat, h, w]
            with common.Timer(device) as td:
                if enc is not None:
                    context, action_mod = enc(actions.to(dtype))
                else:
                    context, action_mod = text, None
                latents = noise.clone()
                latents[:, :, :p_lat] = cond
                for i, t in enumerate(sched.timesteps):
                    timestep = t.unsqueeze(0).to(dtype=dtype, device=device)
                    v = common.model_fn(dit, dit_mod, grad_mod, latents, timestep, context, p_lat, action_mod,
                                        checkpointing=False, text_context=enc is None)
                    latents = sched.step(v, sched.timesteps[i], latents)
                    latents[:, :, :p_lat] = cond
            with common.Timer(device) as tdec:
                video = vae.single_decode(latents, device).to("cpu", torch.float32)
        assert video.shape[2] == pixel_frames, video.shape
        return te.seconds, td.seconds, tdec.seconds

    rows = []
    for i in range(a.warmup + a.steps):
        if i == a.warmup:
            common.reset_peak(device)
        e, d, dec = chunk()
        timed = i >= a.warmup
        if timed:
            rows.append((e, d, dec))
        print(f"rollout chunk {i}{'' if timed else ' (warm-up)'}: {e + d + dec:.2f} s = encode {e:.3f} s + "
              f"DiT {d:.2f} s ({d / a.sample_steps:.4f} s/step) + decode {dec:.3f} s", flush=True)
    e, d, dec = (common.mean([r[k] for r in rows]) for k in range(3))
    print(f"reference rollout: {e + d + dec:.2f} s per chunk = encode {e:.3f} s + DiT {d:.2f} s "
          f"({d / a.sample_steps:.4f} s/step) + decode {dec:.3f} s, {a.future / (e + d + dec):.2f} generated frames/s, "
          f"{common.peak_text(device)} ({a.steps} chunks after {a.warmup} warm-up)", flush=True)


if __name__ == "__main__":
    main()
