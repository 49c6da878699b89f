"""A success judge for `bwm evaluate` that reads the outcome the way the simulator defines it: a
small CNN per Meta-World task estimates, from one 64x64 frame, the object's distance to its goal
(`obj_to_target`, Meta-World's own quantity, in cm) with its own uncertainty, and the frame's
success probability is the simulator's rule (mw.SUCCESS_DISTANCE: success while obj_to_target is
at most 3 cm for drawer-open-v3, 2.4 cm for button-press-topdown-v3) applied to that estimate:
p_t = Phi((threshold - mean_t) / scale_t). A classifier of the success flag never learns how far
short of the threshold a pull or a press stopped; a regression of the state does. Trained on the
real frames of generate.py's datasets (their per-frame `obj_to_target` column: a dataset written
before it must be generated again) and served over evaluate's HTTP judge protocol.

train: judge.py train --data TRAIN_DATASET [...] [--reconstructed REC [...]] --val VAL_DATASET [...] --out judge.pt
  Frames are sampled per task (up to --max-frames). The target is obj_to_target in cm, clipped to
  [0, 25]; the net predicts a mean and a log scale, trained by a Gaussian negative log-likelihood
  (beta-NLL, beta 0.5: each frame's term weighted by its predicted scale, so that the mean is not
  left coarse where the net is unsure). Every batch is balanced over bins of the target, dense
  around the task's threshold (half-centimetre bins within 1 cm of it, wider further away), so
  that the few frames near it weigh as much as the many of a closed drawer or an untouched button.
  Frames are lightly augmented (shifts of a few pixels, brightness/contrast, blur standing in for
  generated frames' softness, noise). With --reconstructed (`bwm reconstruct` of the training
  datasets through the VAE a world model decodes with, one file per --data dataset), the sampled
  frames of the episodes a file holds are also learned as that VAE draws them, with the
  simulator's state of the real frame: a judge that has seen only real frames may read the
  decoder's softened open drawer as closed (docs/fidelity.md at abaed68, run 25). Writes judge.pt
  (weights, normalisation, target scale and threshold per task) and judge.json: per task
  (tasks.TASK), on the held-out datasets' real frames, the state's error (held_out_state: MAE in
  cm overall and within 3 cm of the threshold, bias, how often the truth lies within the predicted
  scale), the success rule's accuracy, balanced accuracy and confusion counts (held_out_frames),
  and the same per episode under the serving rule (held_out_episodes).
score: judge.py score --model judge.pt --val VAL_DATASET [...] [--reconstructed REC [...]] --out FILE
  The trained judge on every held-out frame (JSON tasks.TASK.real) and, with --reconstructed, on
  the same frames after a round trip through the world model's VAE (`bwm reconstruct`, one file per
  dataset; tasks.TASK.reconstructed, with the round trip's PSNR and how far it moves the object),
  the same measures for both: what it concludes from a perfect world model's frames, beside the
  real ones.
serve: judge.py serve --model judge.pt --port 9000 [--ready FILE]
  POST (any path) msgpack-numpy {"frames": uint8 [T, H, W, 3], "task", "prompt", "policy",
  "episode", "final": the frames end the episode (optional, default false)} -> JSON {"success_probability": p (the serving rule), "obj_to_target_cm": the
  closest the object came by the estimate and stayed for w frames (min over t of the max estimate
  over frames t .. t+w-1), "frame": where it did (the index of the frame sent), "success_distance_cm":
  the task's threshold, "model": the task judged, "window": w}; GET /healthz -> OK.

Serving rule: p = max over t of min(p_t, ..., p_t+w-1), w = --window (default 3), over all frames
sent; with "final" the windows that start in the last w - 1 frames hold the frames left, so a
success reached at the episode's last frames counts as the simulator counts it (without it, the
development families' slow policies lost 25 of their 37 missed successes there: docs/fidelity.md,
"What the trainings show"). bwm evaluate sends every frame generated so far after each chunk,
"final" once they reach the horizon, and stops at the first success, so "at any frame" matches the
simulator's measure (success at any step). Success, once
reached, holds for many frames (the drawer stays open, the expert keeps the button down), so asking
for w consecutive frames costs little recall, while a single blurry generated frame that happens
to look open or pressed no longer decides the episode. obj_to_target_cm is the same rule on the
estimated state itself; where the net's scale is about even over the frames, p is about
Phi((threshold - obj_to_target_cm) / scale).

A judge.pt of the former classifier (bwm-metaworld-judge/1) is refused: train the judge again.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np

from files import replacing, write_json

FORMAT = "bwm-metaworld-judge/2"
# Judges this file no longer reads, and what they were.
FORMERLY = {"bwm-metaworld-judge/1": "a classifier of the success flag"}
STATE = "obj_to_target"  # the per-frame column the judge learns: the object's distance to its goal (m)
CLIP_CM = 25.0  # the learned state is obj_to_target in cm clipped to [0, CLIP_CM]
NEAR_CM = 3.0  # the reports' "near the threshold": within this many cm of it
BETA = 0.5  # beta-NLL's weight exponent


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


def no_state(where: str) -> ValueError:
    return ValueError(f"{where} has no per-frame `{STATE}` column (the object's distance to its goal, which the judge "
                      f"learns): the dataset was written by an older generate.py; regenerate it with the current generate.py")


def success_distance(task: str) -> float:
    """The task's success threshold on obj_to_target (m): the simulator's rule."""
    from mw import SUCCESS_DISTANCE

    if task not in SUCCESS_DISTANCE:
        raise ValueError(f"no success rule for task {task!r} (mw.SUCCESS_DISTANCE: {', '.join(SUCCESS_DISTANCE)})")
    return SUCCESS_DISTANCE[task]


def load_frames(root: str, max_frames: int, rng: np.random.Generator, known=()) -> dict[str, dict]:
    """Per task: frames uint8 [N, H, W, 3], the object's distance to its goal (obj_to_target, m,
    float32), the simulator's success rule on it, episode indices and frame positions in their
    episode (at most max_frames, drawn evenly across episodes)."""
    import pyarrow.parquet as pq
    from PIL import Image

    if not os.path.isfile(os.path.join(root, "meta", "info.json")):
        raise ValueError(f"{root} is not a LeRobot dataset (no meta/info.json)")
    with open(os.path.join(root, "meta", "info.json")) as f:
        info = json.load(f)
    if not str(info.get("codebase_version", "")).startswith("v2"):
        raise ValueError(f"{root}: LeRobot {info.get('codebase_version')} dataset; v2.x is read here")
    if STATE not in info.get("features", {}):
        raise no_state(root)
    key = image_column(info)
    by_task: dict[str, list[dict]] = {}
    for ep in read_jsonl(os.path.join(root, "meta", "episodes.jsonl")):
        by_task.setdefault(task_name("; ".join(ep.get("tasks", [])), known), []).append(ep)
    out = {}
    for task, eps in by_task.items():
        threshold = np.float32(success_distance(task))
        total = sum(ep["length"] for ep in eps)
        keep = min(1.0, max_frames / total)
        frames, states, episodes, positions = [], [], [], []
        for ep in eps:
            i = ep["episode_index"]
            path = episode_file(root, info, i)
            table = pq.read_table(path)
            if STATE not in table.column_names:
                raise no_state(path)
            rows = np.flatnonzero(rng.random(table.num_rows) < keep)
            cells = table.column(key).combine_chunks().field("bytes").to_pylist()
            frames += [np.asarray(Image.open(io.BytesIO(cells[r])).convert("RGB")) for r in rows]
            states.append(np.asarray(table.column(STATE).to_numpy(zero_copy_only=False), np.float32)[rows])
            episodes.append(np.full(len(rows), i))
            positions.append(rows)
        state = np.concatenate(states)
        if not np.isfinite(state).all():
            raise ValueError(f"{root}: {task}: `{STATE}` holds {int((~np.isfinite(state)).sum())} values that are not finite")
        # The simulator's rule, as tests/check_dataset.py checks it against the `success` column.
        out[task] = {"frames": np.stack(frames), STATE: state, "success": state <= threshold,
                     "episode": np.concatenate(episodes), "row": np.concatenate(positions)}
    return out


def merge(parts: list[dict[str, dict]]) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for part in parts:
        for task, d in part.items():
            out.setdefault(task, []).append(d)
    return {t: {k: np.concatenate([d[k] for d in ds]) for k in ds[0]} for t, ds in out.items()}


def target_cm(state_m: np.ndarray) -> np.ndarray:
    """The learned state: obj_to_target in cm, clipped to [0, CLIP_CM]."""
    return np.clip(np.asarray(state_m, np.float64) * 100, 0, CLIP_CM).astype(np.float32)


def bin_edges(threshold_cm: float) -> np.ndarray:
    """Inner edges of the bins training balances its batches over: half a centimetre wide within
    1 cm of the threshold, widening away from it, up to CLIP_CM. The threshold is an edge, so no
    bin mixes successes and failures."""
    near = [threshold_cm + d for d in (-2, -1, -0.5, 0, 0.5, 1, 2, 4, 8)]
    far = np.arange(threshold_cm + 12, CLIP_CM, 4).tolist()
    return np.array(sorted({round(e, 6) for e in near + far if 0 < e < CLIP_CM}))


def state_bins(target: np.ndarray, threshold_cm: float) -> np.ndarray:
    """Each target's bin, bins closed on the right ((a, b]): a state at the threshold is a success's."""
    return np.searchsorted(bin_edges(threshold_cm), target, side="left")


# --- model ---------------------------------------------------------------------------------------
def make_net():
    import torch.nn as nn

    def conv(i, o, stride):
        return [nn.Conv2d(i, o, 3, stride, 1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True)]

    # Flattened 4x4 features, not a global pool: where the handle or the hand is matters. Two
    # outputs: the state's mean and log scale, both in units of the training targets' spread.
    return nn.Sequential(*conv(3, 16, 1), *conv(16, 32, 2), *conv(32, 32, 2), *conv(32, 64, 2), *conv(64, 64, 2),
                         nn.AdaptiveAvgPool2d(4), nn.Flatten(), nn.Dropout(0.3), nn.Linear(64 * 16, 2))


def to_input(frames, mean, std, device):
    import torch

    x = frames if isinstance(frames, torch.Tensor) else torch.from_numpy(np.array(frames))
    x = x.to(device).permute(0, 3, 1, 2).float() / 255
    return (x - mean.view(1, 3, 1, 1)) / std.view(1, 3, 1, 1)


class TaskModel:
    """One task's net with what reads it: pixel normalisation, the target's scale (cm), the
    task's success threshold (cm) and the frame size it was trained at."""

    def __init__(self, net, mean, std, target_mean: float, target_std: float, threshold_cm: float, resolution):
        self.net, self.mean, self.std = net, mean, std
        self.target_mean, self.target_std, self.threshold_cm = float(target_mean), float(target_std), float(threshold_cm)
        self.resolution = tuple(int(v) for v in resolution)

    def state(self, x):
        """Mean and scale (cm) of the state of normalised inputs x [N, 3, H, W] (tensors)."""
        out = self.net(x)
        return (out[:, 0] * self.target_std + self.target_mean,
                log_scale(out[:, 1]).exp() * self.target_std)

    def to_checkpoint(self) -> dict:
        return {"state_dict": {k: v.cpu() for k, v in self.net.state_dict().items()}, "mean": self.mean.cpu(), "std": self.std.cpu(),
                "target_mean": self.target_mean, "target_std": self.target_std, "success_distance_cm": self.threshold_cm,
                "resolution": list(self.resolution)}

    @classmethod
    def from_checkpoint(cls, m: dict, device: str) -> "TaskModel":
        net = make_net()
        net.load_state_dict(m["state_dict"])
        return cls(net.to(device).eval(), m["mean"].to(device), m["std"].to(device), m["target_mean"], m["target_std"],
                   m["success_distance_cm"], m["resolution"])


def log_scale(raw):
    """The net's second output as a log scale, kept within e^-6 .. e^3 of the targets' spread."""
    return raw.clamp(-6.0, 3.0)


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


def train_task(frames, target, threshold_cm, steps, batch, lr, device, seed, log) -> TaskModel:
    """A TaskModel of `frames` with states `target` (cm, clipped), batches balanced over
    state_bins, trained by beta-NLL."""
    import torch

    torch.manual_seed(seed)
    if len(frames) == 0:
        raise ValueError("no training frames")
    bins = state_bins(target, threshold_cm)
    groups = [np.flatnonzero(bins == b) for b in np.unique(bins)]
    pixels = frames.reshape(-1, 3).astype(np.float64) / 255
    mean = torch.tensor(pixels.mean(0), dtype=torch.float32, device=device)
    std = torch.tensor(pixels.std(0) + 1e-3, dtype=torch.float32, device=device)
    t_mean, t_std = float(target.mean()), float(max(target.std(), 0.5))
    data = torch.as_tensor(frames, device=device)
    goal = torch.as_tensor((target - t_mean) / t_std, dtype=torch.float32, device=device)
    net = make_net().to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps, pct_start=0.1)
    rng = np.random.default_rng(seed)
    t0 = time.time()
    errors = []
    for step in range(steps):
        which = rng.integers(len(groups), size=batch)
        idx = torch.as_tensor(np.array([g[rng.integers(len(g))] for g in (groups[w] for w in which)]), device=device)
        out = net(augment(to_input(data[idx], mean, std, device)))
        mu, ls = out[:, 0], log_scale(out[:, 1])
        y = goal[idx]
        # Gaussian NLL, each frame's term weighted by its (detached) variance ** BETA.
        nll = 0.5 * ((y - mu) * torch.exp(-ls)) ** 2 + ls
        loss = (nll * torch.exp(2 * BETA * ls).detach()).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        errors.append(float((y - mu).detach().abs().mean()) * t_std)
        if (step + 1) % max(steps // 5, 1) == 0:
            log(f"  step {step + 1}/{steps}: loss {loss.item():.4f}, state error {np.mean(errors):.2f} cm on its batches "
                f"({time.time() - t0:.0f} s)")
            errors = []
    net.eval()
    return TaskModel(net, mean, std, t_mean, t_std, threshold_cm, frames.shape[1:3])


def predict(model: TaskModel, frames, device, batch=512) -> tuple[np.ndarray, np.ndarray]:
    """Mean and scale (cm) of the state of each frame (uint8 [N, H, W, 3])."""
    import torch
    import torch.nn.functional as F

    mus, scales = [np.zeros(0, np.float32)], [np.zeros(0, np.float32)]
    with torch.no_grad():
        for i in range(0, len(frames), batch):
            x = to_input(frames[i:i + batch], model.mean, model.std, device)
            if tuple(x.shape[2:]) != model.resolution:
                x = F.interpolate(x, size=model.resolution, mode="bilinear", antialias=True, align_corners=False)
            mu, scale = model.state(x)
            mus.append(mu.cpu().numpy())
            scales.append(scale.cpu().numpy())
    return np.concatenate(mus).astype(np.float64), np.concatenate(scales).astype(np.float64)


# --- the success rule ----------------------------------------------------------------------------
def margin(mu: np.ndarray, scale: np.ndarray, threshold_cm: float) -> np.ndarray:
    """(threshold - mean) / scale per frame: Phi of it is the probability that the state is within
    the threshold under the net's own uncertainty. Kept as z, not p, so that frames far from the
    threshold still rank (p saturates at 0)."""
    return (threshold_cm - np.asarray(mu, np.float64)) / np.maximum(np.asarray(scale, np.float64), 1e-3)


def phi(z) -> np.ndarray:
    """The standard normal CDF."""
    return 0.5 * np.vectorize(math.erfc, otypes=[float])(-np.asarray(z, np.float64) / math.sqrt(2))


def _windows(values: np.ndarray, window: int, final: bool, pad: float) -> tuple[np.ndarray, int]:
    """The sliding windows of `window` consecutive values (all of them when fewer) and their width;
    with `final` (the values end the episode) also the shorter windows that start in the last
    width - 1 values, padded with `pad` (a value that never decides)."""
    v = np.asarray(values, np.float64)
    w = min(window, len(v))
    if final:
        v = np.concatenate([v, np.full(w - 1, pad)])
    return np.lib.stride_tricks.sliding_window_view(v, w), w


def deciding_frame(z: np.ndarray, window: int, final: bool = False) -> int:
    """The frame that decides the serving rule max over t of min(z_t .. z_t+w-1): the least likely
    frame of the best window of `window` consecutive frames (all of them when fewer). With `final`
    the frames end the episode, and a window may run past its last frame (it then holds the
    frames left): a success reached in the last w - 1 frames is seen, as the simulator sees it."""
    v, _ = _windows(z, window, final, np.inf)
    start = int(v.min(1).argmax())
    return start + int(v[start].argmin())


def closest_held(values: np.ndarray, window: int, final: bool = False) -> tuple[int, float]:
    """min over t of max(v_t .. v_t+w-1): the closest the object came and stayed for `window`
    consecutive frames (all of them when fewer; with `final`, or until the episode's last frame),
    and the frame of the best window where it did."""
    v, _ = _windows(values, window, final, -np.inf)
    start = int(v.max(1).argmin())
    f = start + int(v[start].argmax())
    return f, float(v[start].max())


def aggregate(probs: np.ndarray, window: int, final: bool = False) -> float:
    """max over t of min(p_t .. p_t+w-1): success held for `window` consecutive frames (with
    `final`, or until the episode's last frame)."""
    return float(np.asarray(probs, np.float64)[deciding_frame(probs, window, final)])


def scores(truth: np.ndarray, predicted: np.ndarray) -> dict:
    tp, tn = int((truth & predicted).sum()), int((~truth & ~predicted).sum())
    fp, fn = int((~truth & predicted).sum()), int((truth & ~predicted).sum())
    recall = tp / (tp + fn) if tp + fn else None
    specificity = tn / (tn + fp) if tn + fp else None
    parts = [v for v in (recall, specificity) if v is not None]
    return {"n": len(truth), "accuracy": (tp + tn) / max(len(truth), 1), "balanced_accuracy": sum(parts) / len(parts) if parts else None,
            "recall": recall, "specificity": specificity, "tp": tp, "fp": fp, "tn": tn, "fn": fn}


def state_errors(truth: np.ndarray, mu: np.ndarray, scale: np.ndarray, threshold_cm: float) -> dict:
    """The estimated state (cm) against the clipped truth (cm): overall, and near the threshold
    (within NEAR_CM of it), where the verdict turns; how often the truth lies within one and two
    predicted scales (0.68 and 0.95 for a calibrated Gaussian)."""
    err = np.asarray(mu, np.float64) - truth
    near = np.abs(truth - threshold_cm) <= NEAR_CM

    def summary(e):
        return {"n": int(len(e)), "mae_cm": float(np.abs(e).mean()) if len(e) else None,
                "bias_cm": float(e.mean()) if len(e) else None,
                "p90_abs_error_cm": float(np.percentile(np.abs(e), 90)) if len(e) else None}

    z = np.abs(err) / np.maximum(scale, 1e-3)
    return {**summary(err), "near_threshold": {"within_cm": NEAR_CM, **summary(err[near])},
            "within_one_scale": float((z <= 1).mean()) if len(z) else None,
            "within_two_scales": float((z <= 2).mean()) if len(z) else None,
            "mean_scale_cm": float(np.mean(scale)) if len(scale) else None}


def held_out_scores(h: dict, mu: np.ndarray, scale: np.ndarray, threshold_cm: float, window: int) -> dict:
    """On held-out frames `h` (load_frames' layout) with estimated states (mean, scale in cm):
    "state": the estimate's errors; "frames": the success rule per frame (p_t >= 0.5) against the
    simulator's; "episodes": the same per episode under the serving rule (success held `window`
    frames), with "closest_mae_cm", the estimate of how close the
    object came and stayed for `window` frames (closest_held) against the same of the truth."""
    truth_cm = target_cm(h[STATE])
    z = margin(mu, scale, threshold_cm)
    eps = np.unique(h["episode"])
    truth, guess, closest = [], [], []
    for e in eps:
        at = np.flatnonzero(h["episode"] == e)
        at = at[np.argsort(h["row"][at], kind="stable")]
        truth.append(bool(h["success"][at].any()))
        guess.append(bool(z[at[deciding_frame(z[at], window, final=True)]] >= 0))
        closest.append(abs(closest_held(mu[at], window, final=True)[1] - closest_held(truth_cm[at], window, final=True)[1]))
    episodes = scores(np.array(truth, bool), np.array(guess, bool))
    episodes["closest_mae_cm"] = float(np.mean(closest)) if closest else None
    return {"state": state_errors(truth_cm, mu, scale, threshold_cm), "frames": scores(h["success"], z >= 0), "episodes": episodes}


def describe(r: dict) -> str:
    s, f, e = r["state"], r["frames"], r["episodes"]
    near = s["near_threshold"]
    near_text = (f"{near['mae_cm']:.2f} cm within {near['within_cm']:g} cm of the threshold ({near['n']} frames)" if near["n"]
                 else "no frames near the threshold")
    balanced = f"{f['balanced_accuracy']:.3f}" if f["balanced_accuracy"] is not None else "-"
    return (f"state MAE {s['mae_cm']:.2f} cm, {near_text}; success rule: accuracy {f['accuracy']:.3f}, balanced {balanced} "
            f"(tp {f['tp']} fp {f['fp']} tn {f['tn']} fn {f['fn']}); episodes: accuracy {e['accuracy']:.3f} "
            f"(tp {e['tp']} fp {e['fp']} tn {e['tn']} fn {e['fn']}), closest approach off by {e['closest_mae_cm']:.2f} cm")


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
    file draws them (same states, flags, episodes and rows), marked in "reconstructed"."""
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
    models, report = {}, {"format": FORMAT, "window": a.window, "threshold": 0.5, "state": f"{STATE} in cm, clipped to [0, {CLIP_CM:g}]",
                          "device": device, "reconstructed": a.reconstructed, "tasks": {}}
    for task in tasks:
        if task not in data:
            raise SystemExit(f"judge: no training frames of task {task!r} (found: {', '.join(sorted(data))})")
        d = data[task]
        threshold_cm = 100 * success_distance(task)
        target = target_cm(d[STATE])
        t1 = time.time()
        print(f"judge: {task}: {len(target)} frames, {d['success'].mean():.1%} success, state {target.min():.1f} to "
              f"{target.max():.1f} cm (threshold {threshold_cm:g} cm), {int((np.abs(target - threshold_cm) <= NEAR_CM).sum())} "
              f"within {NEAR_CM:g} cm of it", flush=True)
        try:
            model = train_task(d["frames"], target, threshold_cm, a.steps, a.batch, a.lr, device, a.seed, print)
        except ValueError as e:
            raise SystemExit(f"judge: {task}: {e}")
        entry = {"success_distance_cm": threshold_cm, "train_frames": len(target), "train_success_fraction": float(d["success"].mean()),
                 "train_reconstructed_frames": int(d["reconstructed"].sum()) if "reconstructed" in d else 0,
                 "train_near_threshold_frames": int((np.abs(target - threshold_cm) <= NEAR_CM).sum()),
                 "train_bins": np.bincount(state_bins(target, threshold_cm), minlength=len(bin_edges(threshold_cm)) + 1).tolist(),
                 "bin_edges_cm": bin_edges(threshold_cm).tolist(), "seconds": time.time() - t1}
        if task in held:
            h = held[task]
            r = held_out_scores(h, *predict(model, h["frames"], device), threshold_cm, a.window)
            entry["held_out_frames"], entry["held_out_episodes"], entry["held_out_state"] = r["frames"], r["episodes"], r["state"]
            print(f"judge: {task}: held-out frames: {describe(r)}", flush=True)
        models[task] = model.to_checkpoint()
        report["tasks"][task] = entry
    report["seconds"] = time.time() - t0
    with replacing(a.out, "wb") as f:
        torch.save({"format": FORMAT, "window": a.window, "models": models}, f)
    out_json = os.path.splitext(a.out)[0] + ".json"
    write_json(out_json, report, indent=2)
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
    """The judge on held-out frames and, given `bwm reconstruct` outputs, on the same frames after
    a round trip through the VAE a world model decodes with: what it would conclude from a perfect
    world model's frames."""
    from safetensors.numpy import load_file

    from mw import TASKS

    if a.reconstructed and len(a.reconstructed) != len(a.val):
        raise ValueError(f"{len(a.val)} --val datasets but {len(a.reconstructed)} --reconstructed files (one per dataset, same order)")
    device = pick_device(a.device)
    judge = Judge(a.model, device, a.window)
    real, rec = [], []
    for i, root in enumerate(a.val):
        part = load_frames(root, 1 << 62, np.random.default_rng(0), TASKS)
        real.append(part)
        if a.reconstructed:
            reconstruction = load_file(a.reconstructed[i])
            rec.append({t: dict(d, frames=reconstructed_frames(d, reconstruction, a.reconstructed[i])) for t, d in part.items()})
    real, rec = merge(real), merge(rec) if rec else {}
    report = {"format": FORMAT, "judge": a.model, "window": judge.window, "reconstructed": a.reconstructed, "tasks": {}}
    for task in sorted(real):
        if task not in judge.models:
            raise ValueError(f"{a.model} has no model for task {task!r} (models: {', '.join(judge.models)})")
        model = judge.models[task]
        entry = {"success_distance_cm": model.threshold_cm}
        for name, d in (("real", real[task]), ("reconstructed", rec.get(task))):
            if d is not None:
                entry[name] = held_out_scores(d, *predict(model, d["frames"], device), model.threshold_cm, judge.window)
                print(f"judge: {task}: {name} held-out frames: {describe(entry[name])}", flush=True)
        if task in rec:
            diff = real[task]["frames"].astype(np.float64) - rec[task]["frames"].astype(np.float64)
            entry["reconstruction_psnr_db"] = float(10 * np.log10(255.0 ** 2 / max(np.mean(diff ** 2), 1e-12)))
            entry["object_position"] = object_position_error(task, real[task], rec[task])
            o = entry["object_position"]
            if o["mean_cm"] is not None:
                print(f"judge: {task}: reconstruction {entry['reconstruction_psnr_db']:.2f} dB; the object perceived "
                      f"{o['mean_cm']:.2f} cm from where the real first frame shows it (p90 {o['p90_cm']:.2f}, max {o['max_cm']:.2f}; "
                      f"{o['unseen']} of {o['episodes']} unseen)", flush=True)
        report["tasks"][task] = entry
    write_json(a.out, report, indent=2)
    print(f"judge: wrote {a.out}", flush=True)


# --- serving -------------------------------------------------------------------------------------
def read_model(path: str) -> dict:
    """judge.pt's contents, refused (ValueError) unless this file's FORMAT."""
    import torch

    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as e:
        raise ValueError(f"{path} is not a judge model ({FORMAT}): {type(e).__name__}: {e}") from None
    found = ckpt.get("format") if isinstance(ckpt, dict) else None
    if found in FORMERLY:
        raise ValueError(f"{path} is a judge of the former format {found} ({FORMERLY[found]}), which this judge.py no longer "
                         f"reads ({FORMAT} regresses {STATE} and applies the simulator's success rule to it): train it again "
                         f"with `judge.py train` on datasets from the current generate.py")
    if found != FORMAT:
        raise ValueError(f"{path} is not a judge model ({FORMAT}; its format: {found!r})")
    return ckpt


class Judge:
    def __init__(self, path: str, device: str, window: int | None):
        ckpt = read_model(path)
        self.device, self.window, self.lock = device, window or ckpt["window"], threading.Lock()
        self.models = {task: TaskModel.from_checkpoint(m, device) for task, m in ckpt["models"].items()}

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
        if not isinstance(request, dict) or "frames" not in request:
            raise ValueError("expected a msgpack-numpy map with 'frames' (uint8 [T, H, W, 3]), 'task', 'prompt'")
        frames = request["frames"]
        if not (isinstance(frames, np.ndarray) and frames.dtype == np.uint8 and frames.ndim == 4 and frames.shape[3] == 3 and len(frames)):
            shape = f"{frames.dtype} {list(frames.shape)}" if isinstance(frames, np.ndarray) else type(frames).__name__
            raise ValueError(f"frames must be a uint8 [T, H, W, 3] array with T >= 1, got {shape}")
        final = request.get("final", False)
        if not isinstance(final, bool):
            raise ValueError(f"'final' must be true or false (the frames end the episode), got {final!r}")
        task = self.model_for(str(request.get("task", "")), str(request.get("prompt", "")))
        model = self.models[task]
        with self.lock:
            mu, scale = predict(model, frames, self.device)
        z = margin(mu, scale, model.threshold_cm)
        f, closest = closest_held(mu, self.window, final)
        return {"success_probability": float(phi(z[deciding_frame(z, self.window, final)])), "obj_to_target_cm": round(closest, 3),
                "frame": f, "success_distance_cm": model.threshold_cm, "model": task, "window": self.window}


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
        write_json(a.ready, {"url": f"http://{a.host}:{port}/judge", "port": port, "pid": os.getpid(), "tasks": list(judge.models)}, indent=None)
    if a.lifetime:
        threading.Timer(a.lifetime, server.shutdown).start()
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description="Meta-World success judge: train a per-task regressor of the object's distance to its "
                                 "goal (obj_to_target) whose success is the simulator's rule on it, score it, or serve it over HTTP")
    sub = ap.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="train on datasets' frames labelled by the simulator's obj_to_target")
    t.add_argument("--data", nargs="+", required=True, help="LeRobot v2.1 datasets from generate.py (with its obj_to_target column)")
    t.add_argument("--reconstructed", nargs="*", default=[],
                   help="`bwm reconstruct` outputs, one per --data dataset (same order): their episodes' sampled frames also learned as reconstructed")
    t.add_argument("--val", nargs="*", default=[],
                   help="held-out datasets (other seeds) to report the state's error and the rule's accuracy on")
    t.add_argument("--tasks", help="comma-separated (default: every task in --data)")
    t.add_argument("--out", default="judge.pt", help="weights; the report goes beside it as .json")
    t.add_argument("--steps", type=int, default=600)
    t.add_argument("--batch", type=int, default=64)
    t.add_argument("--lr", type=float, default=3e-3)
    t.add_argument("--max-frames", type=int, default=20000, help="training frames per task, at most")
    t.add_argument("--window", type=int, default=3, help="consecutive frames the serving rule asks for")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--device", default="auto", help="auto, cpu or cuda")
    c = sub.add_parser("score", help="a trained judge on held-out frames (and on the same frames through a VAE: bwm reconstruct)")
    c.add_argument("--model", default="judge.pt")
    c.add_argument("--val", nargs="+", required=True, help="held-out LeRobot datasets")
    c.add_argument("--reconstructed", nargs="*", default=[], help="`bwm reconstruct` outputs, one per --val dataset (same order): "
                   "the same measures on the frames through the VAE")
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
