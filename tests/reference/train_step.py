#!/usr/bin/env python3
"""Reference for `bwm bench-train`: one optimizer step of the Wan2.2-TI2V-5B DiT (DiffSynth's
WanModel, random weights) on one clip of 1 + 8 + 72 frames at 640x480 (latents [1, 48, 21, 30, 40],
6,300 tokens), bf16, per-block activation checkpointing, the BWM flow-matching objective.

--mode master (default) mirrors the Rust trainer: bf16 weights run forward and backward; bf16
gradients are added into fp32 accumulators; the accumulated gradient is clipped by its global norm
(1.0) and AdamW (fp32 moments, torch fused kernel) updates fp32 master weights, which are copied
back into the bf16 weights. --mode plain is what DiffSynth's own trainer does (accelerate bf16,
AdamW directly on the bf16 parameters, no clipping).

--lora-rank R is DiffSynth's LoRA training (`DiffusionTrainingModule.add_lora_to_model`): PEFT's
`inject_adapter_in_model` with `LoraConfig(r=R, lora_alpha=R, target_modules=--lora-targets)` on the
frozen bf16 DiT, the adapters cast to bf16 as DiffSynth does (`upcast_dtype=pipe.torch_dtype`);
only the adapters (and the action encoder) train. Needs `peft` (the GPU image has it).

Prints per step `train step i: ...` and one summary line:
  reference train: X s/step, Y samples/s, Z tokens/s, W TFLOP/s, peak A MiB allocated, B MiB reserved (...)
"""

import argparse

import torch

import common


def parse():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_common_args(p, steps=4, warmup=1)
    common.add_dit_args(p)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--history", type=int, default=8, help="history pixel frames after x0")
    p.add_argument("--future", type=int, default=72, help="future pixel frames")
    p.add_argument("--condition-latents", type=int, default=3, help="latent frames at t=0 (x0 + history)")
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--grad-accum", type=int, default=1,
                   help="micro-steps per optimizer step (configs/bwm-wan22-ti2v-5b.toml says 4; "
                        "docs/performance.md at abaed68 measured 1 and 2)")
    p.add_argument("--mode", default="master", choices=["master", "plain"])
    p.add_argument("--no-checkpointing", dest="checkpointing", action="store_false",
                   help="keep every block's activations (DiffSynth's training default is checkpointing on)")
    p.add_argument("--adamw", default="fused", choices=["fused", "foreach", "for-loop"],
                   help="torch.optim.AdamW implementation (fused falls back to foreach where unsupported)")
    p.add_argument("--lr", type=float, default=1e-5)
    p.add_argument("--weight-decay", type=float, default=0.01)
    p.add_argument("--grad-clip", type=float, default=None,
                   help="global-norm clip; default 1.0 in master mode (the Rust config), 0 = off in plain mode (DiffSynth)")
    p.add_argument("--history-sigma", type=float, default=0.2083)
    p.add_argument("--profile", default=None, metavar="TRACE",
                   help="record the timed steps with torch.profiler into this Chrome trace and print the kernels with the most GPU time")
    p.add_argument("--lora-rank", type=int, default=0, help="LoRA rank on --lora-targets (0 = full fine-tuning)")
    p.add_argument("--lora-targets", default="q,k,v,o,ffn.0,ffn.2",
                   help="DiffSynth's --lora_target_modules default: every attention and FFN linear of the blocks")
    a = p.parse_args()
    if a.tiny:
        a.height, a.width, a.history, a.future = 64, 64, 8, 8
    if a.grad_clip is None:
        a.grad_clip = 1.0 if a.mode == "master" else 0.0
    return a


def main():
    a = parse()
    dit_mod, _, flow_mod, grad_mod = common.import_diffsynth()
    attention = common.set_attention(dit_mod, a.attention)
    device, dtype = torch.device(a.device), common.DTYPES[a.dtype]
    cfg = common.dit_config(a)
    common.header("reference train", a, f", attention {attention}")

    dit = common.build_dit(dit_mod, cfg, device, dtype, a.seed)
    if a.lora_rank > 0:
        from peft import LoraConfig, inject_adapter_in_model

        dit.requires_grad_(False)
        dit = inject_adapter_in_model(
            LoraConfig(r=a.lora_rank, lora_alpha=a.lora_rank, target_modules=a.lora_targets.split(",")), dit)
        for p in dit.parameters():
            if p.requires_grad:
                p.data = p.to(dtype)
    dit.train()
    params = [p for p in dit.parameters()]
    pixel_frames = 1 + a.history + a.future
    enc = None
    if a.conditioning == "action":
        enc = common.build_action_encoder(cfg, a.action_dim, device, dtype, a.seed).train()
        # The BWM model never runs text_embedding: it stays frozen (the Rust trainer's `frozen`).
        dit.text_embedding.requires_grad_(False)
        params += list(enc.parameters())
    trained = [p for p in params if p.requires_grad]
    n_all = sum(p.numel() for p in params)
    n_trained = sum(p.numel() for p in trained)

    if a.mode == "master":
        masters = [p.detach().float().clone() for p in trained]
        accum = [torch.zeros_like(m) for m in masters]
        for m, g in zip(masters, accum):
            m.grad = g
        opt_params = masters
    else:
        opt_params = trained
    kw = dict(lr=a.lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=a.weight_decay)
    impl = a.adamw
    if impl == "fused":
        try:
            opt = torch.optim.AdamW(opt_params, fused=True, **kw)
        except (RuntimeError, ValueError) as e:  # e.g. an old CPU build without the fused kernel
            print(f"fused AdamW unavailable ({e}); using foreach")
            impl = "foreach"
    if impl == "foreach":
        opt = torch.optim.AdamW(opt_params, foreach=True, **kw)
    elif impl == "for-loop":
        opt = torch.optim.AdamW(opt_params, foreach=False, **kw)

    # DiffSynth's training schedule: FlowMatchScheduler("Wan"), 1000 steps, shift 5, with the
    # Gaussian ("bsmntw") loss weight of FlowMatchSFTLoss.
    sched = flow_mod.FlowMatchScheduler("Wan")
    sched.set_timesteps(1000, training=True)

    f_lat = 1 + (a.history + a.future) // 4
    shape = [a.batch, cfg["in_dim"], f_lat, a.height // 16, a.width // 16]
    tokens = a.batch * f_lat * (a.height // 32) * (a.width // 32)
    p_lat = a.condition_latents
    g = torch.Generator(device=device).manual_seed(a.seed + 2)
    clean = torch.randn(shape, generator=g, device=device)  # the one-clip latent "cache", fp32
    actions = torch.rand([a.batch, pixel_frames, a.action_dim], generator=g, device=device) * 2 - 1
    text = torch.randn([a.batch, a.context_tokens, cfg["text_dim"]], generator=g, device=device).to(dtype)
    n_ctx = pixel_frames if a.conditioning == "action" else a.context_tokens
    step_flops = 3 * common.forward_flops(cfg, tokens // a.batch, n_ctx) * a.batch * a.grad_accum
    print(f"reference train: WanModel {n_all:,} parameters ({n_trained:,} trained), latents {shape} "
          f"({tokens} tokens), {p_lat} condition latents at t=0, context {n_ctx} tokens ({a.conditioning}), "
          f"mode {a.mode}, LoRA rank {a.lora_rank or 'off'}, AdamW {impl}, grad clip {a.grad_clip}, checkpointing {'on' if a.checkpointing else 'off'}, "
          f"accumulation {a.grad_accum}", flush=True)

    def micro_step():
        tid = int(torch.randint(0, len(sched.timesteps), (1,)))
        sigma, t = float(sched.sigmas[tid]), sched.timesteps[tid].to(dtype=dtype, device=device)
        noise = torch.randn(shape, generator=g, device=device)
        hist_noise = torch.randn(shape, generator=g, device=device)
        sh = a.history_sigma
        x = torch.cat([
            clean[:, :, :1],
            (1 - sh) * clean[:, :, 1:p_lat] + sh * hist_noise[:, :, 1:p_lat],
            (1 - sigma) * clean[:, :, p_lat:] + sigma * noise[:, :, p_lat:],
        ], dim=2).to(dtype)
        target = noise[:, :, p_lat:] - clean[:, :, p_lat:]
        if enc is not None:
            context, action_mod = enc(actions.to(dtype))
        else:
            context, action_mod = text, None
        pred = common.model_fn(dit, dit_mod, grad_mod, x, t, context, p_lat, action_mod,
                               checkpointing=a.checkpointing, text_context=enc is None)
        loss = torch.nn.functional.mse_loss(pred[:, :, p_lat:].float(), target) * sched.training_weight(t.float().cpu())
        if a.mode == "plain":
            (loss / a.grad_accum).backward()
        else:
            loss.backward()
            grads = [p.grad for p in trained]
            torch._foreach_add_(accum, grads)
            for p in trained:
                p.grad = None
        return loss.item()

    def optimizer_step():
        if a.mode == "master":
            if a.grad_accum > 1:
                torch._foreach_mul_(accum, 1.0 / a.grad_accum)
            norm = torch.nn.utils.clip_grad_norm_(masters, a.grad_clip if a.grad_clip > 0 else float("inf"), foreach=True)
            opt.step()
            with torch.no_grad():
                torch._foreach_copy_(trained, masters)
            torch._foreach_zero_(accum)
        else:
            norm = (torch.nn.utils.clip_grad_norm_(trained, a.grad_clip, foreach=True) if a.grad_clip > 0
                    else torch.nn.utils.get_total_norm([p.grad for p in trained], foreach=True))
            opt.step()
            opt.zero_grad(set_to_none=True)
        return float(norm)

    times = []
    prof = None
    for i in range(a.warmup + a.steps):
        if i == a.warmup:
            common.reset_peak(device)
            if a.profile:
                torch.cuda.synchronize(device)
                prof = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA])
                prof.__enter__()
        with common.Timer(device) as tm:
            losses = [micro_step() for _ in range(a.grad_accum)]
            norm = optimizer_step()
        timed = i >= a.warmup
        if timed:
            times.append(tm.seconds)
        print(f"train step {i}{'' if timed else ' (warm-up)'}: {tm.seconds:.3f} s, loss {sum(losses) / len(losses):.5f}, "
              f"grad norm {norm:.3f}", flush=True)
    if prof is not None:
        torch.cuda.synchronize(device)
        prof.__exit__(None, None, None)
        prof.export_chrome_trace(a.profile)
        print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=25, max_name_column_width=110), flush=True)
        print(f"reference train: trace of the {a.steps} timed steps in {a.profile}", flush=True)
    s = common.mean(times)
    print(f"reference train: {s:.3f} s/step (min {min(times):.3f}), {a.batch * a.grad_accum / s:.3f} samples/s, "
          f"{tokens * a.grad_accum / s:.0f} tokens/s, {step_flops / s / 1e12:.1f} TFLOP/s, {common.peak_text(device)} "
          f"(mode {a.mode}, LoRA rank {a.lora_rank or 'off'}, checkpointing {'on' if a.checkpointing else 'off'}, accumulation {a.grad_accum}, "
          f"{a.steps} steps after {a.warmup} warm-up)", flush=True)


if __name__ == "__main__":
    main()
