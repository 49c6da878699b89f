"""Writes a LeRobot v2.1 dataset of Meta-World episodes (frames as PNG `image` cells inside the
parquet files, no video). README.md describes the layout and the seed convention.

    python generate.py --tasks drawer-open-v3,button-press-topdown-v3 --episodes 200 \\
        --seed-start 0 --frames 120 --resolution 64 --out DIR --workers 2

Each episode is a pure function of (task, seed, --frames, --resolution, --degraded-fraction, --spread,
--miss-cm or --miss-boundary, --miss-weight, --decoy-weight, --observe-every):
the same arguments give the same bytes whatever --workers is. meta/generator.json records them, so
that `--reuse` keeps an existing dataset only when it was made with the same ones.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import multiprocessing
import os
import shutil
import sys
import time
import zlib

import numpy as np

import boundary
from mw import ACTION_SCALE, FPS, TASKS, Sim

DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
CHUNKS_SIZE = 1000
# Where exploration sends the hand (inside the mocap bounds, around the table).
EXPLORE_LOW = np.array([-0.35, 0.40, 0.05])
EXPLORE_HIGH = np.array([0.35, 0.95, 0.40])
# Degraded modes and their weights among degraded episodes. "miss" (the expert steering on an
# object estimate off by 2-12 cm, 2-15 with --spread wide, --miss-cm, or around the outcome's
# boundary in its direction with --miss-boundary) is weighted up (--miss-weight): its hand
# goes through the expert's motions close to the object, succeeding or not depending on the
# distance and direction, and a world model (and a judge) that saw few such episodes shows the
# drawer opening or the button pressed whenever the hand passes near them.
DEGRADED_MODES = {"pause": 1, "wrong": 1, "miss": 3, "burst": 1, "stop": 1, "explore": 1, "late": 1}
# "decoy" (the expert acting on an object placement drawn afresh from the task's range, as in
# another episode: the motion of a success, aimed wherever that placement was) weighs
# --decoy-weight beside those, 0 by default. It comes last, so that at weight 0 every other draw
# stays as it was.
DECOY = "decoy"


class Behaviour:
    """The scripted expert on the true object position with action noise, randomly interrupted
    by exploration (random waypoints and gripper commands), or degraded in one `mode`."""

    def __init__(self, task: str, rng: np.random.Generator, frames: int, degraded_fraction: float, spread: str = "narrow",
                 miss: tuple[float, float] | boundary.Boundary | None = None, decoy_weight: float = 0.0,
                 miss_weight: float = DEGRADED_MODES["miss"], observe_every: tuple[int, int] = (1, 1)):
        import policies

        if spread not in ("narrow", "wide"):
            raise ValueError(f"unknown spread {spread!r} (narrow or wide)")
        miss = miss or ((0.02, 0.15) if spread == "wide" else (0.02, 0.12))
        if not isinstance(miss, boundary.Boundary) and not 0.0 <= miss[0] <= miss[1]:
            raise ValueError(f"the miss range {miss} must be 0 <= low <= high (m)")
        for name, w in (("decoy", decoy_weight), ("miss", miss_weight)):
            if not (np.isfinite(w) and w >= 0):
                raise ValueError(f"the {name} weight {w} must be finite and >= 0")
        if not 1 <= observe_every[0] <= observe_every[1]:
            raise ValueError(f"the observation interval {observe_every} must be 1 <= low <= high (frames)")
        self.policies, self.task, self.rng = policies, task, rng
        if spread == "wide":
            # The experts' action noise log-uniform from near-clean to a jitter that sometimes
            # fails, and in 30% of episodes a cap on their speed (docs/fidelity.md, run 16).
            self.noise = float(np.exp(rng.uniform(np.log(0.05), np.log(1.2))))
            self.speed = float(rng.uniform(0.3, 1.0)) if rng.random() < 0.3 else 1.0
        else:
            self.noise, self.speed = rng.uniform(0.05, 0.4), 1.0
        weights = {**DEGRADED_MODES, "miss": miss_weight, DECOY: decoy_weight}
        modes, weights = list(weights), np.array(list(weights.values()), float)
        self.mode = str(rng.choice(modes, p=weights / weights.sum())) if rng.random() < degraded_fraction else "expert"
        self.explore = np.zeros(frames, bool)  # frames spent on random waypoints
        self.hold = np.zeros(frames, bool)  # frames spent still
        self.burst = np.zeros(frames, bool)  # frames of heavy noise
        self.offset = np.zeros(3)
        self.decoy = None  # where a decoy episode's expert believes the object is

        def span(lo: int, hi: int) -> slice:
            start = int(rng.integers(0, frames))
            return slice(start, start + int(rng.integers(lo, hi)))

        def perception_error(lo: float, hi: float) -> np.ndarray:
            angle = rng.uniform(0, 2 * np.pi)
            return boundary.direction(angle) * rng.uniform(lo, hi)

        if self.mode == "expert":
            # Up to 3 cm off: approaches vary, and the expert still succeeds.
            self.offset = perception_error(0.0, 0.03)
            if rng.random() < 0.4:
                self.explore[: rng.integers(5, 25)] = True
        elif self.mode == "miss":
            self.offset = miss.draw(task, rng) if isinstance(miss, boundary.Boundary) else perception_error(*miss)
        elif self.mode == "pause":
            for _ in range(rng.integers(2, 5)):
                self.hold[span(8, 25)] = True
        elif self.mode == "wrong":
            self.offset = perception_error(0.05, 0.15) + [0, 0, rng.uniform(-0.02, 0.1)]
        elif self.mode == "burst":
            for _ in range(rng.integers(1, 4)):
                self.burst[span(10, 30)] = True
        elif self.mode == "stop":
            self.explore[rng.integers(15, 70) :] = True
        elif self.mode == "explore":
            self.explore[:] = True
        elif self.mode == "late":
            self.hold[: rng.integers(30, 70)] = True
        elif self.mode == DECOY:
            self.decoy = rng.uniform(*policies.OBJECT_RANGE[task])
        self.waypoint, self.until, self.gain, self.grip = None, -1, 10.0, -1.0
        # How often the expert looks at the object (drawn last, so that at 1,1 every other draw
        # stays as it was). Between looks it acts on its belief, which, as policies.Policy's does,
        # takes the drawer handle to follow the hand that pulls it: a pull that misses the handle
        # then goes on as long as one that hooks it, and the commands do not tell the outcome.
        lo, hi = observe_every
        self.observe_every = lo if lo == hi else int(rng.integers(lo, hi + 1))
        self.belief, self.pulled_from = None, None

    def command(self, t: int, state: np.ndarray, obj: np.ndarray) -> np.ndarray:
        rng, grip = self.rng, self.policies.GRIP[self.task]
        if self.decoy is not None:
            # Relative to the object as placed, so that a drawer the hand does pull still follows it.
            self.offset, self.decoy = self.decoy - obj, None
        if t % self.observe_every == 0:
            self.belief = np.array(obj, float)
        elif self.pulled_from is not None:
            self.belief[1] += state[1] - self.pulled_from
        self.pulled_from = None
        if self.hold[t]:
            return state.copy()
        if self.explore[t]:
            if t >= self.until or np.abs(self.waypoint - state[:3]).max() < 0.01:
                self.waypoint = rng.uniform(EXPLORE_LOW, EXPLORE_HIGH)
                self.until = t + int(rng.integers(10, 30))
                self.gain = rng.uniform(5.0, 30.0)
                self.grip = rng.choice([-1.0, 1.0])
            to, gain, grip = self.waypoint, self.gain, self.grip
        else:
            to, gain, pulling = self.policies.expert_target(self.task, self.belief + self.offset, state)
            if pulling:
                self.pulled_from = state[1]
        speed = 1.0 if self.explore[t] else self.speed
        noise = rng.uniform(1.0, 2.0) if self.burst[t] else self.noise
        a = np.clip(np.clip(gain * (to - state[:3]), -1, 1) * speed + noise * rng.standard_normal(3), -1, 1)
        return np.append(state[:3] + a * ACTION_SCALE, grip).astype(np.float32)


def episode_rng(task: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(task.encode())])


def png(image: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def stats(values: np.ndarray) -> dict:
    """LeRobot's per-episode feature statistics (per dimension)."""
    v = values.reshape(len(values), -1).astype(np.float64)
    return {"min": v.min(0).tolist(), "max": v.max(0).tolist(), "mean": v.mean(0).tolist(), "std": v.std(0).tolist(), "count": [len(v)]}


def image_stats(images: np.ndarray) -> dict:
    """Per-channel statistics of pixel values in [0, 1], shaped [3, 1, 1] as LeRobot stores them."""
    s = stats(images.reshape(-1, 3) / 255.0)
    return {k: ([[[x]] for x in s[k]] if k != "count" else [len(images)]) for k in s}


def simulate(behaviour: Behaviour, sim, frames: int, render: bool = True) -> tuple[list, list, list, list, list]:
    """`behaviour` in `sim` for `frames` frames from its reset: per frame the image (None unless
    `render`), state, command and Meta-World delta action; and frames + 1 success flags, each
    whether the task was done as that frame was shown (the last: after the last command)."""
    images, states, commands, deltas, success = [], [], [], [], []
    image, state = sim.reset()
    done = False
    for t in range(frames):
        command = behaviour.command(t, state, sim.object_pos())
        images.append(image)
        states.append(state)
        commands.append(command)
        success.append(done)
        image, state, done = sim.step(command, render=render and t + 1 < frames)
        deltas.append(sim.last_action)
    success.append(done)
    return images, states, commands, deltas, success


def run_episode(job: tuple) -> dict:
    """Simulates one episode and writes its parquet file; returns its metadata."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    root, episode_index, first_index, task_index, task, seed, frames, resolution, degraded, spread, miss, decoy, miss_weight, observe = job
    behaviour = Behaviour(task, episode_rng(task, seed), frames, degraded, spread, miss, decoy, miss_weight, observe)
    with Sim(task, seed, resolution) as sim:
        images, states, commands, deltas, success = simulate(behaviour, sim, frames)
    images, states, commands, deltas = (np.stack(x) for x in (images, states, commands, deltas))
    success = np.array(success)
    vec = lambda rows: pa.FixedSizeListArray.from_arrays(pa.array(rows.reshape(-1), pa.float32()), rows.shape[1])
    n = frames
    table = pa.table({
        "observation.image": pa.array([{"bytes": png(i), "path": None} for i in images], pa.struct([("bytes", pa.binary()), ("path", pa.string())])),
        "observation.state": vec(states),
        "action": vec(commands),
        "action_delta": vec(deltas),
        "success": pa.array(success[:-1]),
        "next.success": pa.array(success[1:]),
        "timestamp": pa.array(np.arange(n, dtype=np.float32) / np.float32(FPS)),
        "frame_index": pa.array(np.arange(n, dtype=np.int64)),
        "episode_index": pa.array(np.full(n, episode_index, np.int64)),
        "index": pa.array(np.arange(first_index, first_index + n, dtype=np.int64)),
        "task_index": pa.array(np.full(n, task_index, np.int64)),
    })
    path = os.path.join(root, DATA_PATH.format(episode_chunk=episode_index // CHUNKS_SIZE, episode_index=episode_index))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    pq.write_table(table, path, compression="snappy")
    first = int(np.argmax(success)) if success.any() else None
    return {
        "episode": {"episode_index": episode_index, "tasks": [task], "length": n, "seed": seed, "behaviour": str(behaviour.mode), "success": first is not None, "first_success_frame": first},
        "stats": {
            "episode_index": episode_index,
            "stats": {
                "observation.image": image_stats(images),
                "observation.state": stats(states),
                "action": stats(commands),
                "action_delta": stats(deltas),
                "success": stats(success[:-1]),
                "next.success": stats(success[1:]),
                "timestamp": stats(np.arange(n) / FPS),
                "frame_index": stats(np.arange(n)),
                "episode_index": stats(np.full(n, episode_index)),
                "index": stats(np.arange(first_index, first_index + n)),
                "task_index": stats(np.full(n, task_index)),
            },
        },
    }


def features(resolution: int) -> dict:
    vec = lambda names: {"dtype": "float32", "shape": [len(names)], "names": names}
    scalar = lambda dtype: {"dtype": dtype, "shape": [1], "names": None}
    return {
        "observation.image": {"dtype": "image", "shape": [resolution, resolution, 3], "names": ["height", "width", "channel"]},
        "observation.state": vec(["x", "y", "z", "gripper"]),
        "action": vec(["x", "y", "z", "gripper"]),
        "action_delta": vec(["dx", "dy", "dz", "gripper"]),
        "success": scalar("bool"),
        "next.success": scalar("bool"),
        "timestamp": scalar("float32"),
        "frame_index": scalar("int64"),
        "episode_index": scalar("int64"),
        "index": scalar("int64"),
        "task_index": scalar("int64"),
    }


def weight(text: str) -> float:
    """A mode's weight (`--decoy-weight W`, `--miss-weight W`): finite and >= 0."""
    try:
        w = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes a number, got {text!r}") from None
    if not (np.isfinite(w) and w >= 0):
        raise argparse.ArgumentTypeError(f"must be finite and >= 0, got {text!r}")
    return w


def miss_range(text: str) -> tuple[float, float]:
    """`--miss-cm LOW,HIGH` (cm) as (low, high) in metres."""
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes LOW,HIGH in cm, got {text!r}") from None
    if not 0.0 <= lo <= hi <= 100.0:
        raise argparse.ArgumentTypeError(f"needs 0 <= LOW <= HIGH <= 100, got {text!r}")
    return lo / 100, hi / 100


def interval(text: str) -> tuple[int, int]:
    """`--observe-every LOW,HIGH` (frames)."""
    try:
        lo, hi = (int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes LOW,HIGH in frames, got {text!r}") from None
    if not 1 <= lo <= hi:
        raise argparse.ArgumentTypeError(f"needs 1 <= LOW <= HIGH, got {text!r}")
    return lo, hi


def settings(args: argparse.Namespace) -> dict:
    """What a dataset's bytes depend on (not --workers), as meta/generator.json records it."""
    boundary_file = None
    if args.miss_boundary is not None:
        with open(args.miss_boundary, "rb") as f:
            boundary_file = {"sha256": hashlib.sha256(f.read()).hexdigest()}
    chosen = {"tasks": args.tasks, "episodes": args.episodes, "seed_start": args.seed_start, "frames": args.frames,
              "resolution": args.resolution, "degraded_fraction": args.degraded_fraction, "spread": args.spread,
              "miss_cm": args.miss_cm, "miss_boundary": boundary_file, "miss_factor": args.miss_factor,
              "miss_weight": args.miss_weight, "decoy_weight": args.decoy_weight, "observe_every": args.observe_every}
    return json.loads(json.dumps(chosen))


def reuse(args: argparse.Namespace) -> None:
    """`--reuse`: --out as it is when meta/generator.json records these settings; the program's end
    (exit 2) naming what differs when it records others."""
    path = os.path.join(args.out, "meta", "generator.json")
    if not os.path.isfile(path):
        print(f"generate.py: {args.out} holds no meta/generator.json (made before generate.py recorded its settings): "
              "taken as it is, unchecked", file=sys.stderr)
        return
    with open(path) as f:
        there = json.load(f)["settings"]
    asked = settings(args)
    if differ := [k for k in sorted(set(there) | set(asked)) if there.get(k) != asked.get(k)]:
        raise SystemExit(f"generate.py: {args.out} was made with other settings ("
                         + "; ".join(f"{k}: {json.dumps(there.get(k))} there, {json.dumps(asked.get(k))} asked" for k in differ)
                         + "): remove it, or pick another --out")
    print(f"generate.py: {args.out} exists, made with these settings", file=sys.stderr)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--task", choices=TASKS)
    which.add_argument("--tasks", help="several tasks in one dataset, comma-separated; episodes interleaved by seed")
    parser.add_argument("--episodes", type=int, required=True, help="episodes per task")
    parser.add_argument("--seed-start", type=int, default=0, help="seeds seed-start .. seed-start+episodes-1 (train from 0, validation from 100000)")
    parser.add_argument("--frames", type=int, default=120, help="frames per episode (all episodes have this length)")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--degraded-fraction", type=float, default=0.4, help="share of episodes degraded so that they fail or succeed late")
    parser.add_argument("--spread", choices=["narrow", "wide"], default="narrow",
                        help="the experts' action noise and speed: narrow (noise 0.05-0.4, full speed; misses 2-12 cm) or wide "
                             "(noise log-uniform 0.05-1.2, 30%% of episodes at a speed cap of 0.3-1; misses 2-15 cm)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--miss-cm", type=miss_range, help="LOW,HIGH: how far off (cm, random direction) the `miss` episodes' expert steers; "
                        "default 2,12 (2,15 with --spread wide). Outcomes flip a few cm from the object, so a range "
                        "close to it puts more episodes on both sides of the contact boundary")
    where.add_argument("--miss-boundary", metavar="FILE", help="measure_boundary.py's report: each `miss` steers in a random direction "
                       "--miss-factor times (default 0.5-2) as far off as the expert's outcome flips in that "
                       "direction (measured in the simulator, for the same --frames), at most the report's max_cm; with the default "
                       "factor every direction has misses on both sides of it")
    boundary.add_factor_argument(parser)
    parser.add_argument("--miss-weight", type=weight, default=float(DEGRADED_MODES["miss"]),
                        help=f"weight of `miss` episodes among the degraded ones (default {DEGRADED_MODES['miss']}; the others weigh 1)")
    parser.add_argument("--decoy-weight", type=weight, default=0.0,
                        help="weight of `decoy` episodes among the degraded ones (the others weigh 1, `miss` --miss-weight): the expert "
                             "acting on an object placement drawn afresh from the task's range, so that the motion of a "
                             "success does not tell where the object is; default 0 (none)")
    parser.add_argument("--observe-every", type=interval, default=(1, 1), metavar="LOW,HIGH",
                        help="frames between the expert's looks at the object, per episode uniform in LOW..HIGH; between looks "
                             "it takes the drawer handle to follow the hand that pulls it (as a policy seeing a frame per "
                             "chunk does), so that a pull that misses lasts as long as one that hooks the handle. Default 1,1: "
                             "every frame, and a missed pull stops as soon as the handle stays behind")
    parser.add_argument("--out", required=True, help="dataset folder (must not exist unless --force)")
    parser.add_argument("--workers", type=int, default=min(4, os.cpu_count() or 1))
    exists = parser.add_mutually_exclusive_group()
    exists.add_argument("--force", action="store_true", help="replace --out if it exists")
    exists.add_argument("--reuse", action="store_true",
                        help="keep --out if it exists and was made with the same settings (its meta/generator.json); refuse if not")
    args = parser.parse_args(argv)
    args.tasks = args.tasks.split(",") if args.tasks else [args.task]
    unknown = [t for t in args.tasks if t not in TASKS]
    if unknown:
        parser.error(f"unknown task(s) {', '.join(unknown)} (known: {', '.join(TASKS)})")
    if len(set(args.tasks)) != len(args.tasks):
        parser.error("--tasks names a task twice")
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    if not 0 <= args.seed_start <= 2**32 - 1 - args.episodes:
        parser.error("seeds must lie in 0 .. 2**32-1")
    if args.frames < 2:
        parser.error("--frames must be at least 2")
    if not 16 <= args.resolution <= 1024:
        parser.error("--resolution must be in 16 .. 1024")
    if not 0.0 <= args.degraded_fraction <= 1.0:
        parser.error("--degraded-fraction must be in [0, 1]")
    if args.workers < 1:
        parser.error("--workers must be at least 1")
    if os.path.exists(args.out) and not (args.force or args.reuse):
        parser.error(f"{args.out} exists (--force replaces it, --reuse keeps it when made with the same settings)")
    args.miss = boundary.from_argument(parser, args.miss_boundary, args.tasks, args.miss_factor) or args.miss_cm
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.reuse and os.path.exists(args.out):
        reuse(args)
        return
    out = os.path.abspath(args.out)
    tmp = f"{out}.tmp-{os.getpid()}"
    os.makedirs(os.path.join(tmp, "meta"))
    jobs = []
    for i in range(args.episodes):
        for task_index, task in enumerate(args.tasks):
            e = len(jobs)
            jobs.append((tmp, e, e * args.frames, task_index, task, args.seed_start + i, args.frames, args.resolution, args.degraded_fraction, args.spread, args.miss, args.decoy_weight, args.miss_weight, args.observe_every))
    start = time.time()
    try:
        results = []
        with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
            for r in pool.imap(run_episode, jobs):
                results.append(r)
                rate = len(results) * args.frames / (time.time() - start)
                print(f"\r{len(results)}/{len(jobs)} episodes, {rate:.0f} frames/s", end="", file=sys.stderr, flush=True)
        print(file=sys.stderr)
        episodes = [r["episode"] for r in results]
        info = {
            "codebase_version": "v2.1", "robot_type": "sawyer", "total_episodes": len(jobs), "total_frames": len(jobs) * args.frames,
            "total_tasks": len(args.tasks), "total_videos": 0, "total_chunks": (len(jobs) + CHUNKS_SIZE - 1) // CHUNKS_SIZE,
            "chunks_size": CHUNKS_SIZE, "fps": FPS, "splits": {"train": f"0:{len(jobs)}"}, "data_path": DATA_PATH,
            "features": features(args.resolution),
        }
        lines = lambda items: "".join(json.dumps(x) + "\n" for x in items)
        meta = {
            "info.json": json.dumps(info, indent=4) + "\n",
            "episodes.jsonl": lines(episodes),
            "tasks.jsonl": lines({"task_index": i, "task": t} for i, t in enumerate(args.tasks)),
            "episodes_stats.jsonl": lines(r["stats"] for r in results),
            "generator.json": json.dumps({"generator": "bench/metaworld/generate.py", "settings": settings(args)}, indent=1) + "\n",
        }
        for name, text in meta.items():
            with open(os.path.join(tmp, "meta", name), "w") as f:
                f.write(text)
        if os.path.exists(out):
            shutil.rmtree(out)
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for task in args.tasks:
        mine = [e for e in episodes if e["tasks"] == [task]]
        ok = sum(e["success"] for e in mine)
        print(f"{task}: {ok}/{len(mine)} episodes succeed", file=sys.stderr)
    print(f"wrote {out}: {len(jobs)} episodes, {len(jobs) * args.frames} frames in {time.time() - start:.1f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
