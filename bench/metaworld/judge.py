"""A success judge for `bwm evaluate`: a small CNN per Meta-World task that tells, from one 64x64
frame, whether the simulator's success flag is raised, trained on real frames of generate.py's
datasets and served over evaluate's HTTP judge protocol.

train: judge.py train --data TRAIN_DATASET [...] [--reconstructed REC [...]] --val VAL_DATASET [...] --out judge.pt
  Frames are sampled per task (up to --max-frames), classes balanced in every batch, lightly
  augmented (shifts of a few pixels, brightness/contrast, blur standing in for generated frames'
  softness, noise). With --reconstructed (`bwm reconstruct` of the training datasets through the
  VAE a world model decodes with, one file per --data dataset), the sampled frames of the episodes
  a file holds are also learned as that VAE draws them, with the simulator's flags: a judge that
  has seen only real frames may read the decoder's softened open drawer as closed
  (docs/fidelity.md, run 25). Writes judge.pt (weights + normalisation per task) and judge.json:
  accuracy, balanced accuracy and confusion counts on the held-out datasets' real frames, and
  the same per episode under the serving rule.
score: judge.py score --model judge.pt --val VAL_DATASET [...] --reconstructed REC [...] --out FILE
  The trained judge on every held-out frame and on the same frames after a round trip through the
  world model's VAE (`bwm reconstruct`, one file per dataset): what it concludes from a perfect
  world model's frames, beside the real ones.
serve: judge.py serve --model judge.pt --port 9000 [--ready FILE]
  POST (any path) msgpack-numpy {"frames": uint8 [T, H, W, 3], "task", "prompt", "policy",
  "episode"} -> JSON {"success_probability": p, ...}; GET /healthz -> OK.

Serving rule: p = max over t of min(p_t, ..., p_t+w-1), w = --window (default 3), over all frames
sent. bwm evaluate sends every frame generated so far after each chunk and stops at the first
success, so "at any frame" matches the simulator's measure (success at any step). The flag, once
raised, holds for many frames (the drawer stays open, the expert keeps the button down), so asking
for w consecutive frames costs little recall, while a single blurry generated frame that happens
to look open or pressed no longer decides the episode.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np

FORMAT = "bwm-metaworld-judge/1"


# --- datasets ------------------------------------------------------------------------------------
def read_jsonl(path: str) -> list[dict]:
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def task_name(text: str, known) -> str:
    """The Meta-World task a task text names (the text itself when it names none or several)."""
    named = [t for t in known if t in text]
    return named[0] if len(named) == 1 else text


def success_column(names: list[str]) -> str:
    if "success" in names:
        return "success"
    found = [n for n in names if "success" in n.lower()]
    if len(found) != 1:
        raise ValueError(f"expected one per-frame success column, found {found or 'none'} among {', '.join(names)}")
    return found[0]


def image_column(info: dict) -> str:
    found = [k for k, f in info["features"].items() if f.get("dtype") == "image"]
    if len(found) != 1:
        raise ValueError(f"expected one image feature, found {found or 'none'} (video datasets are not read here)")
    return found[0]


def image_size(info: dict) -> tuple[int, int]:
    """(height, width) of the frames of a LeRobot v2.x dataset with meta/info.json `info`."""
    height, width = info["features"][image_column(info)]["shape"][:2]
    return int(height), int(width)


def episode_file(root: str, info: dict, i: int) -> str:
    """The parquet file of episode `i` of a LeRobot v2.x dataset with meta/info.json `info`."""
    return os.path.join(root, info["data_path"].format(episode_chunk=i // info.get("chunks_size", 1000), episode_index=i))


def load_frames(root: str, max_frames: int, rng: np.random.Generator, known=()) -> dict[str, dict]:
    """Per task: frames uint8 [N, H, W, 3], success flags, episode indices and frame positions in
    their episode (at most max_frames, drawn evenly across episodes)."""
    import pyarrow.parquet as pq
    from PIL import Image

    if not os.path.isfile(os.path.join(root, "meta", "info.json")):
        raise ValueError(f"{root} is not a LeRobot dataset (no meta/info.json)")
    with open(os.path.join(root, "meta", "info.json")) as f:
        info = json.load(f)
    if not str(info.get("codebase_version", "")).startswith("v2"):
        raise ValueError(f"{root}: LeRobot {info.get('codebase_version')} dataset; v2.x is read here")
    key = image_column(info)
    by_task: dict[str, list[dict]] = {}
    for ep in read_jsonl(os.path.join(root, "meta", "episodes.jsonl")):
        by_task.setdefault(task_name("; ".join(ep.get("tasks", [])), known), []).append(ep)
    out = {}
    for task, eps in by_task.items():
        total = sum(ep["length"] for ep in eps)
        keep = min(1.0, max_frames / total)
        frames, flags, episodes, positions = [], [], [], []
        for ep in eps:
            i = ep["episode_index"]
            path = episode_file(root, info, i)
            table = pq.read_table(path)
            flag = success_column(table.column_names)
            rows = np.flatnonzero(rng.random(table.num_rows) < keep)
            cells = table.column(key).combine_chunks().field("bytes").to_pylist()
            frames += [np.asarray(Image.open(io.BytesIO(cells[r])).convert("RGB")) for r in rows]
            flags.append(np.asarray(table.column(flag).to_numpy(zero_copy_only=False), bool)[rows])
            episodes.append(np.full(len(rows), i))
            positions.append(rows)
        out[task] = {"frames": np.stack(frames), "success": np.concatenate(flags), "episode": np.concatenate(episodes),
                     "row": np.concatenate(positions)}
    return out


def merge(parts: list[dict[str, dict]]) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for part in parts:
        for task, d in part.items():
            out.setdefault(task, []).append(d)
    return {t: {k: np.concatenate([d[k] for d in ds]) for k in ds[0]} for t, ds in out.items()}


# --- model ---------------------------------------------------------------------------------------
def make_net():
    import torch.nn as nn

    def conv(i, o, stride):
        return [nn.Conv2d(i, o, 3, stride, 1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True)]

    # Flattened 4x4 features, not a global pool: where the handle or the hand is matters.
    return nn.Sequential(*conv(3, 16, 1), *conv(16, 32, 2), *conv(32, 32, 2), *conv(32, 64, 2), *conv(64, 64, 2),
                         nn.AdaptiveAvgPool2d(4), nn.Flatten(), nn.Dropout(0.3), nn.Linear(64 * 16, 1))


def to_input(frames, mean, std, device):
    import torch

    x = frames if isinstance(frames, torch.Tensor) else torch.from_numpy(np.array(frames))
    x = x.to(device).permute(0, 3, 1, 2).float() / 255
    return (x - mean.view(1, 3, 1, 1)) / std.view(1, 3, 1, 1)


def augment(x):
    import torch
    import torch.nn.functional as F

    n, _, h, w = x.shape
    theta = torch.zeros(n, 2, 3, device=x.device)
    scale = 1 + (torch.rand(n, device=x.device) - 0.5) * 0.06
    theta[:, 0, 0] = theta[:, 1, 1] = scale
    theta[:, :, 2] = (torch.rand(n, 2, device=x.device) - 0.5) * (6 / w)  # up to 3 pixels
    x = F.grid_sample(x, F.affine_grid(theta, x.shape, align_corners=False), padding_mode="border", align_corners=False)
    blur = torch.rand(n, device=x.device) < 0.5
    if blur.any():
        size = int(torch.randint(h // 3, h - 4, ()).item())
        small = F.interpolate(x[blur], size=size, mode="bilinear", antialias=True, align_corners=False)
        x[blur] = F.interpolate(small, size=(h, w), mode="bilinear", align_corners=False)
    x = x * (1 + (torch.rand(n, 1, 1, 1, device=x.device) - 0.5) * 0.2) + (torch.rand(n, 1, 1, 1, device=x.device) - 0.5) * 0.2
    return x + torch.randn_like(x) * 0.03


def train_task(frames, success, steps, batch, lr, device, seed, log):
    import torch
    import torch.nn.functional as F

    torch.manual_seed(seed)
    pos, neg = np.flatnonzero(success), np.flatnonzero(~success)
    if len(pos) == 0 or len(neg) == 0:
        raise ValueError(f"the training frames hold {len(pos)} success and {len(neg)} other frames; both are needed")
    pixels = frames.reshape(-1, 3).astype(np.float64) / 255
    mean = torch.tensor(pixels.mean(0), dtype=torch.float32, device=device)
    std = torch.tensor(pixels.std(0) + 1e-3, dtype=torch.float32, device=device)
    data = torch.as_tensor(frames, device=device)
    net = make_net().to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps, pct_start=0.1)
    rng = np.random.default_rng(seed)
    half = batch // 2
    target = torch.cat([torch.ones(half), torch.zeros(batch - half)]).to(device)
    t0 = time.time()
    for step in range(steps):
        idx = np.concatenate([rng.choice(pos, half), rng.choice(neg, batch - half)])
        x = augment(to_input(data[torch.as_tensor(idx, device=device)], mean, std, device))
        loss = F.binary_cross_entropy_with_logits(net(x).squeeze(1), target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if (step + 1) % max(steps // 5, 1) == 0:
            log(f"  step {step + 1}/{steps}: loss {loss.item():.4f} ({time.time() - t0:.0f} s)")
    net.eval()
    return net, mean, std


def predict(net, mean, std, frames, device, batch=512):
    import torch

    with torch.no_grad():
        return np.concatenate([torch.sigmoid(net(to_input(frames[i:i + batch], mean, std, device))).squeeze(1).cpu().numpy()
                               for i in range(0, len(frames), batch)]) if len(frames) else np.zeros(0)


def aggregate(probs: np.ndarray, window: int) -> float:
    """max over t of min(p_t .. p_t+w-1): success held for `window` consecutive frames."""
    w = min(window, len(probs))
    return float(np.lib.stride_tricks.sliding_window_view(probs, w).min(1).max())


def scores(truth: np.ndarray, predicted: np.ndarray) -> dict:
    tp, tn = int((truth & predicted).sum()), int((~truth & ~predicted).sum())
    fp, fn = int((~truth & predicted).sum()), int((truth & ~predicted).sum())
    recall = tp / (tp + fn) if tp + fn else None
    specificity = tn / (tn + fp) if tn + fp else None
    parts = [v for v in (recall, specificity) if v is not None]
    return {"n": len(truth), "accuracy": (tp + tn) / max(len(truth), 1), "balanced_accuracy": sum(parts) / len(parts) if parts else None,
            "recall": recall, "specificity": specificity, "tp": tp, "fp": fp, "tn": tn, "fn": fn}


def held_out_scores(h: dict, probs: np.ndarray, window: int) -> tuple[dict, dict]:
    """Frame scores and episode scores (success held `window` frames, the serving rule) of
    per-frame probabilities over held-out frames `h` (load_frames' layout)."""
    eps = np.unique(h["episode"])
    truth = np.array([h["success"][h["episode"] == e].any() for e in eps])
    guess = np.array([aggregate(probs[h["episode"] == e], window) >= 0.5 for e in eps])
    return scores(h["success"], probs >= 0.5), scores(truth, guess)


def describe(f: dict, e: dict) -> str:
    return (f"accuracy {f['accuracy']:.3f}, balanced {f['balanced_accuracy']:.3f} (tp {f['tp']} fp {f['fp']} tn {f['tn']} "
            f"fn {f['fn']}); episodes: accuracy {e['accuracy']:.3f} (tp {e['tp']} fp {e['fp']} tn {e['tn']} fn {e['fn']})")


def pick_device(name: str) -> str:
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("judge: --device cuda but torch sees no CUDA device")
    return name


def load_all(roots, max_frames, seed, known, reconstructed=()):
    """Frames of every dataset per task; with `reconstructed` (one `bwm reconstruct` output per
    root, same order), the frames of the episodes each holds once more as reconstructed."""
    rng = np.random.default_rng(seed)
    parts = [load_frames(r, max_frames // len(roots), rng, known) for r in roots]
    if reconstructed:
        if len(reconstructed) != len(roots):
            raise ValueError(f"{len(roots)} --data datasets but {len(reconstructed)} --reconstructed files (one per dataset, same order)")
        parts = [with_reconstructions(part, path) for part, path in zip(parts, reconstructed)]
    return merge(parts)


def with_reconstructions(part: dict[str, dict], path: str) -> dict[str, dict]:
    """`part` (load_frames' layout) with the frames of the episodes `path` holds appended as that
    file draws them (same flags, episodes and rows), marked in "reconstructed"."""
    from safetensors import safe_open

    with safe_open(path, "numpy") as f:
        held = {int(k.split(".", 1)[1]) for k in f.keys() if k.startswith("episode.") and k.split(".", 1)[1].isdigit()}
        out, added = {}, 0
        for task, d in part.items():
            d = dict(d, reconstructed=np.zeros(len(d["success"]), bool))
            at = np.flatnonzero(np.isin(d["episode"], sorted(held)))
            if len(at):
                sub = {k: v[at] for k, v in d.items()}
                videos = {f"episode.{e}": f.get_tensor(f"episode.{e}") for e in np.unique(sub["episode"])}
                sub["frames"], sub["reconstructed"] = reconstructed_frames(sub, videos, path), np.ones(len(at), bool)
                d = {k: np.concatenate([d[k], sub[k]]) for k in d}
                added += len(at)
            out[task] = d
    if not added:
        raise ValueError(f"{path} holds none of the sampled episodes: reconstruct the same dataset (`bwm reconstruct --data` it)")
    return out


def train(a) -> None:
    import torch

    from mw import TASKS

    device = pick_device(a.device)
    if device == "cpu":
        torch.set_num_threads(os.cpu_count() or 1)
    t0 = time.time()
    data = load_all(a.data, a.max_frames, a.seed, TASKS, a.reconstructed)
    held = load_all(a.val, a.max_frames * 4, a.seed + 1, TASKS) if a.val else {}
    rec = sum(int(d["reconstructed"].sum()) for d in data.values() if "reconstructed" in d)
    print(f"judge: read {sum(len(d['success']) for d in data.values())} training frames ({rec} of them reconstructed) and "
          f"{sum(len(d['success']) for d in held.values())} held-out frames in {time.time() - t0:.0f} s, device {device}", flush=True)
    tasks = [t for t in a.tasks.split(",")] if a.tasks else sorted(data)
    models, report = {}, {"format": FORMAT, "window": a.window, "threshold": 0.5, "device": device,
                          "reconstructed": a.reconstructed, "tasks": {}}
    for task in tasks:
        if task not in data:
            raise SystemExit(f"judge: no training frames of task {task!r} (found: {', '.join(sorted(data))})")
        d = data[task]
        t1 = time.time()
        print(f"judge: {task}: {len(d['success'])} frames, {d['success'].mean():.1%} success", flush=True)
        try:
            net, mean, std = train_task(d["frames"], d["success"], a.steps, a.batch, a.lr, device, a.seed, print)
        except ValueError as e:
            raise SystemExit(f"judge: {task}: {e}")
        entry = {"train_frames": len(d["success"]), "train_success_fraction": float(d["success"].mean()),
                 "train_reconstructed_frames": int(d["reconstructed"].sum()) if "reconstructed" in d else 0, "seconds": time.time() - t1}
        if task in held:
            h = held[task]
            probs = predict(net, mean, std, h["frames"], device)
            f, e = held_out_scores(h, probs, a.window)
            entry["held_out_frames"], entry["held_out_episodes"] = f, e
            print(f"judge: {task}: held-out frames: {describe(f, e)}", flush=True)
        models[task] = {"state_dict": {k: v.cpu() for k, v in net.state_dict().items()}, "mean": mean.cpu(), "std": std.cpu(),
                        "resolution": list(d["frames"].shape[1:3])}
        report["tasks"][task] = entry
    report["seconds"] = time.time() - t0
    torch.save({"format": FORMAT, "window": a.window, "models": models}, a.out)
    out_json = os.path.splitext(a.out)[0] + ".json"
    with open(out_json, "w") as f:
        json.dump(report, f, indent=2)
    print(f"judge: {a.out} and {out_json} written in {report['seconds']:.0f} s", flush=True)


def reconstructed_frames(d: dict, reconstruction: dict, source: str) -> np.ndarray:
    """The frames of `d` (load_frames' layout) taken from a `bwm reconstruct` output instead."""
    out = np.empty_like(d["frames"])
    for e in np.unique(d["episode"]):
        key = f"episode.{e}"
        if key not in reconstruction:
            raise ValueError(f"{source} has no {key}: reconstruct the same dataset, every episode")
        video = reconstruction[key]
        at = np.flatnonzero(d["episode"] == e)
        rows = d["row"][at]
        if video.ndim != 4 or video.shape[0] != 3 or rows.max() >= video.shape[1] or video.shape[2:] != d["frames"].shape[1:3]:
            raise ValueError(f"{source}: {key} is {list(video.shape)}, not [3, F, H, W] covering {rows.max() + 1} frames of "
                             f"{d['frames'].shape[1]}x{d['frames'].shape[2]}")
        out[at] = video[:, rows].transpose(1, 2, 3, 0)
    return out


def object_position_error(task: str, real: dict, rec: dict) -> dict:
    """Where policies.perceive places the object in each episode's first frame, real against
    reconstructed: how far (cm, in xy) the decoder moves what a policy, and the world model,
    must locate."""
    import policies

    errors, unseen = [], 0
    for at in np.flatnonzero(real["row"] == 0):
        a, b = policies.perceive(task, real["frames"][at]), policies.perceive(task, rec["frames"][at])
        if a is None or b is None:
            unseen += 1
        else:
            errors.append(100 * float(np.linalg.norm(a[:2] - b[:2])))
    e = np.array(errors)
    return {"episodes": len(errors) + unseen, "unseen": unseen,
            "mean_cm": float(e.mean()) if len(e) else None, "p90_cm": float(np.percentile(e, 90)) if len(e) else None,
            "max_cm": float(e.max()) if len(e) else None}


def score(a) -> None:
    """The judge on held-out frames and on the same frames after a round trip through the VAE a
    world model decodes with (`bwm reconstruct`): what it would conclude from a perfect world
    model's frames."""
    from safetensors.numpy import load_file

    from mw import TASKS

    if len(a.reconstructed) != len(a.val):
        raise ValueError(f"{len(a.val)} --val datasets but {len(a.reconstructed)} --reconstructed files (one per dataset, same order)")
    device = pick_device(a.device)
    judge = Judge(a.model, device, a.window)
    real, rec = [], []
    for root, path in zip(a.val, a.reconstructed):
        part = load_frames(root, 1 << 62, np.random.default_rng(0), TASKS)
        reconstruction = load_file(path)
        real.append(part)
        rec.append({t: dict(d, frames=reconstructed_frames(d, reconstruction, path)) for t, d in part.items()})
    real, rec = merge(real), merge(rec)
    report = {"judge": a.model, "window": judge.window, "reconstructed": a.reconstructed, "tasks": {}}
    for task in sorted(real):
        if task not in judge.models:
            raise ValueError(f"{a.model} has no model for task {task!r} (models: {', '.join(judge.models)})")
        net, mean, std, _ = judge.models[task]
        entry = {}
        for name, d in (("real", real[task]), ("reconstructed", rec[task])):
            f, e = held_out_scores(d, predict(net, mean, std, d["frames"], device), judge.window)
            entry[name] = {"frames": f, "episodes": e}
            print(f"judge: {task}: {name} held-out frames: {describe(f, e)}", flush=True)
        diff = real[task]["frames"].astype(np.float64) - rec[task]["frames"].astype(np.float64)
        entry["reconstruction_psnr_db"] = float(10 * np.log10(255.0 ** 2 / max(np.mean(diff ** 2), 1e-12)))
        entry["object_position"] = object_position_error(task, real[task], rec[task])
        o = entry["object_position"]
        if o["mean_cm"] is not None:
            print(f"judge: {task}: reconstruction {entry['reconstruction_psnr_db']:.2f} dB; the object perceived "
                  f"{o['mean_cm']:.2f} cm from where the real first frame shows it (p90 {o['p90_cm']:.2f}, max {o['max_cm']:.2f}; "
                  f"{o['unseen']} of {o['episodes']} unseen)", flush=True)
        report["tasks"][task] = entry
    with open(a.out + ".tmp", "w") as f:
        json.dump(report, f, indent=2)
    os.replace(a.out + ".tmp", a.out)
    print(f"judge: wrote {a.out}", flush=True)


# --- serving -------------------------------------------------------------------------------------
class Judge:
    def __init__(self, path: str, device: str, window: int | None):
        import torch

        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        if ckpt.get("format") != FORMAT:
            raise SystemExit(f"judge: {path} is not a judge model ({FORMAT})")
        self.device, self.window, self.lock = device, window or ckpt["window"], threading.Lock()
        self.models = {}
        for task, m in ckpt["models"].items():
            net = make_net()
            net.load_state_dict(m["state_dict"])
            self.models[task] = (net.to(device).eval(), m["mean"].to(device), m["std"].to(device), tuple(m["resolution"]))

    def model_for(self, task: str, prompt: str) -> str:
        if task in self.models:
            return task
        named = [t for t in self.models if t in task] or [t for t in self.models if t in prompt]
        if len(named) == 1:
            return named[0]
        if len(self.models) == 1:
            return next(iter(self.models))
        raise ValueError(f"no judge model for task {task!r} (models: {', '.join(self.models)})")

    def judge(self, request) -> dict:
        import torch
        import torch.nn.functional as F

        if not isinstance(request, dict) or "frames" not in request:
            raise ValueError("expected a msgpack-numpy map with 'frames' (uint8 [T, H, W, 3]), 'task', 'prompt'")
        frames = request["frames"]
        if not (isinstance(frames, np.ndarray) and frames.dtype == np.uint8 and frames.ndim == 4 and frames.shape[3] == 3 and len(frames)):
            shape = f"{frames.dtype} {list(frames.shape)}" if isinstance(frames, np.ndarray) else type(frames).__name__
            raise ValueError(f"frames must be a uint8 [T, H, W, 3] array with T >= 1, got {shape}")
        task = self.model_for(str(request.get("task", "")), str(request.get("prompt", "")))
        net, mean, std, (h, w) = self.models[task]
        with self.lock, torch.no_grad():
            x = to_input(frames, mean, std, self.device)
            if x.shape[2:] != (h, w):
                x = F.interpolate(x, size=(h, w), mode="bilinear", antialias=True, align_corners=False)
            probs = torch.sigmoid(net(x)).squeeze(1).cpu().numpy()
        return {"success_probability": aggregate(probs, self.window), "model": task, "window": self.window,
                "frame_probabilities": [round(float(p), 4) for p in probs]}


def handler(judge: Judge, max_bytes: int):
    from msgpack_numpy import unpackb

    class Handler(BaseHTTPRequestHandler):
        def reply(self, code: int, body: dict) -> None:
            out = json.dumps(body).encode()
            self.send_response(code)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(out)))
            self.end_headers()
            self.wfile.write(out)

        def do_GET(self):
            if self.path == "/healthz":
                self.send_response(200)
                self.send_header("Content-Length", "3")
                self.end_headers()
                self.wfile.write(b"OK\n")
            else:
                self.reply(404, {"error": "POST msgpack-numpy frames to any path; GET /healthz"})

        def do_POST(self):
            try:
                n = int(self.headers.get("Content-Length") or -1)
                if not 0 < n <= max_bytes:
                    raise ValueError(f"Content-Length {n}: expected 1 to {max_bytes} bytes")
                body = self.rfile.read(n)
                try:
                    request = unpackb(body)
                except Exception as e:
                    raise ValueError(f"the body is not msgpack-numpy: {e}") from None
                self.reply(200, judge.judge(request))
            except ValueError as e:
                self.reply(400, {"error": str(e)})
            except Exception as e:
                self.reply(500, {"error": f"{type(e).__name__}: {e}"})

        def log_message(self, *args):
            pass

    return Handler


def serve(a) -> None:
    device = pick_device(a.device)
    judge = Judge(a.model, device, a.window)
    server = ThreadingHTTPServer((a.host, a.port), handler(judge, 1 << 30))
    port = server.server_address[1]
    print(f"judge: {', '.join(judge.models)} on http://{a.host}:{port}/judge (window {judge.window}, {device})", flush=True)
    if a.ready:
        with open(a.ready + ".tmp", "w") as f:
            json.dump({"url": f"http://{a.host}:{port}/judge", "port": port, "pid": os.getpid(), "tasks": list(judge.models)}, f)
        os.replace(a.ready + ".tmp", a.ready)
    if a.lifetime:
        threading.Timer(a.lifetime, server.shutdown).start()
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description="Meta-World success judge: train a frame classifier per task, score it, or serve it over HTTP")
    sub = ap.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="train on datasets' frames labelled by the simulator's success flag")
    t.add_argument("--data", nargs="+", required=True, help="LeRobot v2.1 datasets from generate.py")
    t.add_argument("--reconstructed", nargs="*", default=[],
                   help="`bwm reconstruct` outputs, one per --data dataset (same order): their episodes' sampled frames also learned as reconstructed")
    t.add_argument("--val", nargs="*", default=[], help="held-out datasets (other seeds) to report accuracy on")
    t.add_argument("--tasks", help="comma-separated (default: every task in --data)")
    t.add_argument("--out", default="judge.pt", help="weights; the report goes beside it as .json")
    t.add_argument("--steps", type=int, default=600)
    t.add_argument("--batch", type=int, default=64)
    t.add_argument("--lr", type=float, default=3e-3)
    t.add_argument("--max-frames", type=int, default=20000, help="training frames per task, at most")
    t.add_argument("--window", type=int, default=3, help="consecutive frames the serving rule asks for")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--device", default="auto", help="auto, cpu or cuda")
    c = sub.add_parser("score", help="a trained judge on held-out frames and on the same frames through a VAE (bwm reconstruct)")
    c.add_argument("--model", default="judge.pt")
    c.add_argument("--val", nargs="+", required=True, help="held-out LeRobot datasets")
    c.add_argument("--reconstructed", nargs="+", required=True, help="`bwm reconstruct` outputs, one per --val dataset")
    c.add_argument("--out", required=True, help="JSON report")
    c.add_argument("--window", type=int, help="override the model's window")
    c.add_argument("--device", default="auto")
    s = sub.add_parser("serve", help="answer bwm evaluate's HTTP judge requests")
    s.add_argument("--model", default="judge.pt")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=9000, help="0 picks a free port (see --ready)")
    s.add_argument("--window", type=int, help="override the model's window")
    s.add_argument("--ready", help="JSON file {url, port, pid, tasks} written once listening")
    s.add_argument("--lifetime", type=float, help="exit after this many seconds")
    s.add_argument("--device", default="auto")
    a = ap.parse_args(argv)
    if getattr(a, "window", None) is not None and a.window < 1:
        ap.error("--window must be at least 1")
    try:
        {"train": train, "score": score, "serve": serve}[a.command](a)
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"judge: {e}")


if __name__ == "__main__":
    sys.exit(main())
