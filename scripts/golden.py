"""The golden files of the parity tests, computed with the reference implementation.

    python scripts/golden.py OUT_DIR            # both variants into OUT_DIR
    python scripts/golden.py OUT_DIR public     # one variant (public | public2)

The reference is DiffSynth-Studio (PyPI `diffsynth==2.0.11`, the framework the BWM release builds
on) on PyTorch 2.11.0, run on the CPU in float32. Every file is a function of this script and those
two versions alone: the random draws come from torch's CPU generator, seeded per variant, in a fixed
order. The script refuses other versions, so that the cache key (this file's bytes,
scripts/setup.sh --tests) names what computed the files.

What the files hold (docs/wan22-ti2v-5b.md, section "Golden files", lists every tensor):
- `dit_V.{json,weights,case}`: a Wan2.2-TI2V DiT at a tiny width with the BWM action encoder, its
  random weights, one batch of inputs, the velocity and the intermediates of batch item 0;
- `vae_V.{json,weights,case}`: a Wan2.2 VAE at a tiny width, its random weights, a random video,
  its normalized latents and their decoding;
- `flow_schedule` and `objective_public` (variant `public` only): the Wan flow-matching schedule,
  one training-loss evaluation and a 4-step Euler rollout on the `dit_public` model.

The weights are not the modules' default initialisation: every parameter (norm scales and biases
included) is redrawn, so that a transposed weight, a swapped name or a dropped modulation term
changes the output by far more than the tolerance of the tests.

`ActionEncoder` and `bwm_forward` are imported by checkpoints/tests/python/interop.py: importing
this module computes nothing.
"""
import json
import sys
from importlib.metadata import version

import torch
from einops import rearrange
from safetensors.torch import save_file

TORCH = "2.11.0"
DIFFSYNTH = "2.0.11"

# Per variant: the seed of torch's generator and the sizes. `public` is the main case (batch 2,
# two blocks, two timesteps); `public2` changes every size the parity code must read from the json.
VARIANTS = {
    "public": dict(seed=0, dim=96, heads=2, ffn=192, layers=2, lat_h=4, lat_w=6, future=8, batch=2,
                   timesteps=[875.0, 312.5], vae_dim=8, vae_dec_dim=8, vae_h=64, vae_w=96, vae_frames=9),
    "public2": dict(seed=7, dim=120, heads=2, ffn=240, layers=1, lat_h=2, lat_w=8, future=4, batch=1,
                    timesteps=[500.0], vae_dim=12, vae_dec_dim=16, vae_h=32, vae_w=48, vae_frames=5),
}
ACTION_DIM = 14
CONDITION_LATENTS = 3  # the x0 latent and two history latents (8 history frames / 4)
HISTORY_FRAMES = 8


class ActionEncoder(torch.nn.Module):
    """The BWM release's action encoder (ti2v2 path). `action_mlp1` maps each pixel frame's action
    to one cross-attention token; `action_mlp2` maps groups of 4 actions (the first action repeated
    3 times in front, so that latent 0 sees a_0 alone, as the VAE's first latent sees frame 0) to
    one vector per latent frame, added to the timestep embedding of that frame's tokens."""

    def __init__(self, action_dim, dim):
        super().__init__()
        self.action_mlp1 = torch.nn.Sequential(
            torch.nn.Linear(action_dim, dim), torch.nn.GELU(), torch.nn.Linear(dim, dim))
        self.action_mlp2 = torch.nn.Sequential(
            torch.nn.Linear(action_dim * 4, dim * 4), torch.nn.SiLU(), torch.nn.Linear(dim * 4, dim))

    def forward(self, actions):
        context = self.action_mlp1(actions)
        padded = torch.cat([actions[:, 0:1].repeat(1, 3, 1), actions], dim=1)
        n, frames, d = actions.shape
        grouped = padded.reshape(n, (frames + 3) // 4, d * 4)
        return context, self.action_mlp2(grouped)


def bwm_forward(dit, enc, latents, timestep, actions, cond_t=CONDITION_LATENTS):
    """One sample (batch 1) through the DiT as the BWM release conditions it: timestep 0 on the
    `cond_t` condition latents and `timestep` on the others, each token's timestep embedding plus
    its latent frame's action vector, the action tokens as the cross-attention context (no text).
    Returns the velocity [1,48,T,H,W] and the intermediates the golden case stores."""
    from diffsynth.models.wan_video_dit import sinusoidal_embedding_1d

    context, action_vectors = enc(actions)
    frames = latents.shape[2]
    per_frame = latents.shape[3] * latents.shape[4] // 4  # tokens per latent frame (2x2 patches)
    t_tokens = torch.concat([torch.zeros((cond_t, per_frame)),
                             torch.ones((frames - cond_t, per_frame)) * timestep]).flatten()
    t_emb = dit.time_embedding(sinusoidal_embedding_1d(dit.freq_dim, t_tokens).unsqueeze(0))
    repeat = t_emb.shape[1] // action_vectors.shape[1]
    t_emb = t_emb + action_vectors.unsqueeze(2).repeat(1, 1, repeat, 1).flatten(1, 2)
    t_mod = dit.time_projection(t_emb).unflatten(2, (6, dit.dim))

    x = dit.patchify(latents)
    f, h, w = x.shape[2:]
    x = rearrange(x, "b c f h w -> b (f h w) c").contiguous()
    # 3-axis RoPE: the frame, row and column tables side by side for every token.
    rope = torch.cat([dit.freqs[0][:f].view(f, 1, 1, -1).expand(f, h, w, -1),
                      dit.freqs[1][:h].view(1, h, 1, -1).expand(f, h, w, -1),
                      dit.freqs[2][:w].view(1, 1, w, -1).expand(f, h, w, -1)], dim=-1).reshape(f * h * w, 1, -1)

    seen = {"t_emb": t_emb[0].clone(), "t_mod": t_mod[0].clone(), "action_context": context[0].clone(),
            "action_mod": action_vectors[0].clone(), "tokens_in": x[0].clone()}
    for i, block in enumerate(dit.blocks):
        x = block(x, context, t_mod, rope)
        seen[f"block{i}_out"] = x[0].clone()
    x = dit.head(x, t_emb)
    return dit.unpatchify(x, (f, h, w)), seen


def randomize(module, scale):
    """Redraws every parameter, in `named_parameters` order, as N(0, scale^2), around 1 for the
    multiplicative norm scales (q/k RMSNorms, the cross-attention LayerNorm, the VAE's `gamma`s)."""
    with torch.no_grad():
        for name, p in module.named_parameters():
            centre = 1.0 if name.endswith(("norm_q.weight", "norm_k.weight", "norm3.weight")) or "gamma" in name else 0.0
            p.copy_(torch.randn_like(p) * scale + centre)


def state(module, prefix=""):
    return {prefix + k: v.contiguous() for k, v in module.state_dict().items()}


def write_json(path, value):
    with open(path, "w") as f:
        json.dump(value, f, indent=1)


def generate(out, name):
    from diffsynth.diffusion.flow_match import FlowMatchScheduler
    from diffsynth.models.wan_video_dit import WanModel
    from diffsynth.models.wan_video_vae import VideoVAE38_, WanVideoVAE38

    v = VARIANTS[name]
    torch.manual_seed(v["seed"])
    # The order below is the order of the draws: module construction (default initialisation)
    # draws too, so nothing may be constructed, drawn or skipped out of turn.

    # --- the DiT and the action encoder ---
    dit_cfg = dict(dim=v["dim"], in_dim=48, ffn_dim=v["ffn"], out_dim=48, text_dim=64, freq_dim=256, eps=1e-6,
                   patch_size=(1, 2, 2), num_heads=v["heads"], num_layers=v["layers"], has_image_input=False,
                   seperated_timestep=True, require_clip_embedding=False, require_vae_embedding=False,
                   fuse_vae_embedding_in_latents=True)
    dit = WanModel(**dit_cfg).eval()
    randomize(dit, 0.2)
    enc = ActionEncoder(ACTION_DIM, v["dim"]).eval()
    randomize(enc, 0.2)

    latent_frames = CONDITION_LATENTS + v["future"] // 4
    action_frames = 1 + HISTORY_FRAMES + v["future"]
    n = v["batch"]
    latents = torch.randn(n, 48, latent_frames, v["lat_h"], v["lat_w"])
    actions = torch.rand(n, action_frames, ACTION_DIM) * 2 - 1
    timesteps = torch.tensor(v["timesteps"])
    with torch.no_grad():
        runs = [bwm_forward(dit, enc, latents[i:i + 1], timesteps[i], actions[i:i + 1]) for i in range(n)]
    velocity = torch.cat([r[0] for r in runs])

    save_file({**state(dit), **state(enc, "action_encoder.")}, f"{out}/dit_{name}.weights.safetensors")
    case = {"latents": latents, "timesteps": timesteps, "actions": actions, "velocity": velocity.contiguous()}
    case.update({f"sample0.{k}": t.contiguous() for k, t in runs[0][1].items()})
    save_file(case, f"{out}/dit_{name}.case.safetensors")
    write_json(f"{out}/dit_{name}.json", {
        "dit": {k: list(x) if isinstance(x, tuple) else x for k, x in dit_cfg.items()},
        "action_dim": ACTION_DIM, "condition_latent_frames": CONDITION_LATENTS, "history_frames": HISTORY_FRAMES,
        "future_frames": v["future"], "action_frames": action_frames,
        "notes": "latents [B,48,T,H,W]; timesteps [B], one per sample, for its future latents (the condition "
                 "latents run at t=0); actions [B,F,14] in [-1,1]; velocity = the DiT's output [B,48,T,H,W]; "
                 "sample0.* = batch item 0's intermediates (t_emb and t_mod per token, after the action vectors "
                 "are added; the tokens entering block 0 and each block's output)."})

    # --- the Wan2.2 VAE ---
    vae_cfg = dict(dim=v["vae_dim"], z_dim=48, dec_dim=v["vae_dec_dim"], dim_mult=[1, 2, 4, 4], num_res_blocks=2,
                   attn_scales=[], temperal_downsample=[False, True, True])
    vae = VideoVAE38_(**vae_cfg).eval()
    randomize(vae, 0.1)
    # The published per-channel latent mean and std live in the wrapper; building it draws as well.
    wrapper = WanVideoVAE38(z_dim=48, dim=8)
    mean, std = wrapper.mean.clone(), wrapper.std.clone()
    del wrapper
    video = torch.rand(1, 3, v["vae_frames"], v["vae_h"], v["vae_w"]) * 2 - 1
    with torch.no_grad():
        z = vae.encode(video, [mean, 1.0 / std])
        decoded = vae.decode(z, [mean, 1.0 / std])
    save_file(state(vae), f"{out}/vae_{name}.weights.safetensors")
    save_file({"video": video, "latents": z.contiguous(), "decoded": decoded.contiguous(),
               "latents_mean": mean, "latents_std": std}, f"{out}/vae_{name}.case.safetensors")
    write_json(f"{out}/vae_{name}.json", {
        "vae": vae_cfg,
        "notes": "video [1,3,F,H,W] in [-1,1] with F = 1+4k; latents = the encoder's mean, normalized per channel "
                 "as (mu-mean)/std; decoded = decode(latents), not clamped; the weights carry the names of "
                 "Wan2.2_VAE.pth."})

    if name != "public":
        return

    # --- the flow-matching schedule: training grid (1000 steps), inference grid (50 steps, shift 5) ---
    sched = FlowMatchScheduler("Wan")
    sched.set_timesteps(1000, training=True)
    train_sigmas, train_timesteps = sched.sigmas.clone(), sched.timesteps.clone()
    train_weights = sched.linear_timesteps_weights.clone()
    # The history latents' noise level: the training grid's sigma 50 steps from its end.
    history_sigma = train_sigmas[max(0, len(train_sigmas) - 50)]
    sched.set_timesteps(50, shift=5.0)
    save_file({"train_sigmas": train_sigmas.float(), "train_timesteps": train_timesteps.float(),
               "train_weights": train_weights.float(), "infer50_sigmas": sched.sigmas.float(),
               "infer50_timesteps": sched.timesteps.float(), "history_sigma": history_sigma.reshape(1).float().clone()},
              f"{out}/flow_schedule.safetensors")

    # --- one evaluation of the training objective on the dit_public model, sample 0's actions ---
    sched = FlowMatchScheduler("Wan")
    sched.set_timesteps(1000, training=True)
    s_hist = float(sched.sigmas[max(0, len(sched.sigmas) - 50)])
    shape = (1, 48, latent_frames, v["lat_h"], v["lat_w"])
    clean = torch.randn(*shape)  # latent 0 = x0, 1-2 = history, the rest = future
    noise = torch.randn_like(clean)
    history_noise = torch.randn_like(clean)
    index = 700
    sigma, t = float(sched.sigmas[index]), float(sched.timesteps[index])
    model_input = clean.clone()
    model_input[:, :, 1:3] = (1 - s_hist) * clean[:, :, 1:3] + s_hist * history_noise[:, :, 1:3]
    model_input[:, :, 3:] = (1 - sigma) * clean[:, :, 3:] + sigma * noise[:, :, 3:]
    act0 = actions[0:1]
    with torch.no_grad():
        pred, _ = bwm_forward(dit, enc, model_input, torch.tensor(t), act0)
    target = noise[:, :, 3:] - clean[:, :, 3:]
    loss = torch.nn.functional.mse_loss(pred[:, :, 3:].float(), target.float()) * sched.linear_timesteps_weights[index]

    # --- a 4-step Euler rollout (shift 5): the prefix (clean x0, noised history) is put back before
    # every step and after the last ---
    sched.set_timesteps(4, shift=5.0)
    prefix = model_input[:, :, :CONDITION_LATENTS].clone()
    x = torch.randn(*shape)
    start = x.clone()
    with torch.no_grad():
        for step_t in sched.timesteps:
            x[:, :, :CONDITION_LATENTS] = prefix
            step_v, _ = bwm_forward(dit, enc, x, step_t, act0)
            x = sched.step(step_v, step_t, x)
        x[:, :, :CONDITION_LATENTS] = prefix
    save_file({"clean_latents": clean, "noise": noise, "history_noise": history_noise,
               "timestep_index": torch.tensor([index]), "history_sigma": torch.tensor([s_hist]),
               "model_input": model_input, "velocity": pred.contiguous(), "loss": loss.reshape(1).float(),
               "actions": act0.contiguous(), "sampler_init_noise": start, "sampler_prefix": prefix,
               "sampler_steps": torch.tensor([4]), "sampler_sigmas": sched.sigmas.float().clone(),
               "sampler_timesteps": sched.timesteps.float().clone(), "sampler_out": x.contiguous()},
              f"{out}/objective_{name}.safetensors")


def main(argv):
    if len(argv) not in (2, 3) or (len(argv) == 3 and argv[2] not in VARIANTS):
        sys.exit(f"usage: {argv[0]} OUT_DIR [{' | '.join(VARIANTS)}]")
    have = (torch.__version__.split("+")[0], version("diffsynth"))
    if have != (TORCH, DIFFSYNTH):
        sys.exit(f"golden.py: needs torch=={TORCH} and diffsynth=={DIFFSYNTH} (scripts/setup.sh --tests), "
                 f"found torch {have[0]} and diffsynth {have[1]}")
    for name in argv[2:] or list(VARIANTS):
        generate(argv[1], name)
        print(f"golden.py: {name} written to {argv[1]}")


if __name__ == "__main__":
    main(sys.argv)
