"""Writes a LeRobot v2.1 dataset of Meta-World episodes (frames as PNG `image` cells inside the
parquet files, no video). docs/metaworld.md (the `data` stage) describes the layout and the seed
convention.

    python generate.py --tasks drawer-open-v3,button-press-topdown-v3 --episodes 200 \\
        --seed-start 0 --frames 120 --resolution 64 --out DIR --workers 2

Each episode is a pure function of (task, seed, --frames, --resolution, --mix, --observe-every) and,
for the `learned` behaviour, of families.py's pool of behaviour-cloned policies:
the same arguments give the same bytes whatever --workers is. meta/generator.json records them, so
that `--reuse` keeps an existing dataset only when it was made with the same ones.
"""

from __future__ import annotations

import argparse
import io
import json
import multiprocessing
import os
import shutil
import sys
import time
import zlib

import numpy as np

from mw import ACTION_SCALE, FPS, TASKS, Sim

DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
CHUNKS_SIZE = 1000
# Where wide exploration sends the hand (inside the mocap bounds, around the table).
EXPLORE_LOW = np.array([-0.35, 0.40, 0.05])
EXPLORE_HIGH = np.array([0.35, 0.95, 0.40])
# The behaviour mix: each episode is one of these, drawn with these shares. It is built from what a
# world model of the task must learn, not from what moves any evaluation policy (docs/fidelity.md,
# "The data"):
# - expert: the task done: the scripted expert on the object with action noise, sometimes after
#   wandering a little and with a burst of heavy noise: what contact that succeeds looks like.
# - near: contact and its absence around the object: the expert steering on an object estimate off
#   by a distance drawn uniformly in 0-15 cm, in a direction uniform in the table plane, and up to
#   3 cm in height: every direction at graded distances, both sides of wherever contact ends.
# - partial: outcomes that stop short: a pull that ends after a uniform 0-20 cm (the drawer opens
#   16 cm or more after about 17-18 cm of pull), a press whose hand stops at a uniform height from
#   6 cm above to 5 cm below the button's top as the expert sees it (the button untouched at the
#   one end, pressed home from about 2-3 cm below at the other), then held or backed away from.
# - explore: the hand wandering without the task's intent, half of the episodes around the object
#   (waypoints in a box 15 cm either way of it in the table plane, 7.5 cm in height, gripper random:
#   touches happen by chance), half across the table.
# - idle: time that passes without progress: holding still, a late start, pauses.
# - learned: rollouts of behaviour-cloned policies from a pool kept apart from every evaluation
#   family (families.POOL: its own demonstration seeds): the states learned policies reach.
MIX = {"expert": 0.25, "near": 0.25, "partial": 0.15, "explore": 0.10, "idle": 0.05, "learned": 0.20}
NEAR_CM = (0.0, 15.0)
PARTIAL_PULL_CM = (0.0, 20.0)
PARTIAL_PRESS_CM = (-6.0, 5.0)
# A learned policy from the pool acts in chunks, as the evaluator runs policies.
LEARNED_CHUNK = 24


class Behaviour:
    """One episode's behaviour (`mode`, one of MIX), drawn from `rng`: the scripted expert on the
    object with action noise, steered off it, stopped short, wandering, idle, or a learned policy
    of the pool. `observe_every` (LOW, HIGH): frames between the expert's looks at the object."""

    def __init__(self, task: str, rng: np.random.Generator, frames: int, observe_every: tuple[int, int] = (1, 1),
                 mix: dict[str, float] = MIX):
        import policies

        if not 1 <= observe_every[0] <= observe_every[1]:
            raise ValueError(f"the observation interval {observe_every} must be 1 <= low <= high (frames)")
        if set(mix) - set(MIX) or not all(np.isfinite(w) and w >= 0 for w in mix.values()) or sum(mix.values()) <= 0:
            raise ValueError(f"a behaviour mix takes weights >= 0 of {', '.join(MIX)}, not all 0; got {mix}")
        self.policies, self.task, self.rng = policies, task, rng
        # In MIX's order, whatever order the weights were given in (meta/generator.json records
        # them as a mapping, so that order must not change the episodes).
        modes = [m for m in MIX if m in mix]
        weights = np.array([mix[m] for m in modes], float)
        self.mode = str(rng.choice(modes, p=weights / weights.sum()))
        self.noise, self.speed = rng.uniform(0.05, 0.4), 1.0
        self.explore = np.zeros(frames, bool)  # frames spent on random waypoints
        self.hold = np.zeros(frames, bool)  # frames spent still
        self.burst = np.zeros(frames, bool)  # frames of heavy noise
        self.offset = np.zeros(3)
        self.around = None  # exploration's centre (None: the whole table)
        self.stop_after = None  # partial: how far (m) the pull or press goes before it stops
        self.learned = None  # learned: the pool's policy (kind, demos) and its episode seed

        def span(lo: int, hi: int) -> slice:
            start = int(rng.integers(0, frames))
            return slice(start, start + int(rng.integers(lo, hi)))

        def in_plane(lo_cm: float, hi_cm: float) -> np.ndarray:
            angle = rng.uniform(0, 2 * np.pi)
            return np.array([np.cos(angle), np.sin(angle), 0.0]) * rng.uniform(lo_cm, hi_cm) / 100

        if self.mode == "expert":
            # Up to 3 cm off: approaches vary, and the expert still succeeds.
            self.offset = in_plane(0.0, 3.0)
            if rng.random() < 0.4:
                self.explore[: rng.integers(5, 25)] = True
            if rng.random() < 0.2:
                self.burst[span(10, 30)] = True
        elif self.mode == "near":
            self.offset = in_plane(*NEAR_CM) + [0.0, 0.0, rng.uniform(-0.03, 0.03)]
        elif self.mode == "partial":
            self.offset = in_plane(0.0, 2.0)
            lo, hi = PARTIAL_PULL_CM if task == "drawer-open-v3" else PARTIAL_PRESS_CM
            self.stop_after = rng.uniform(lo, hi) / 100
            self.back_off = bool(rng.random() < 0.5)
        elif self.mode == "explore":
            self.explore[:] = True
            self.around = rng.random() < 0.5
        elif self.mode == "idle":
            kind = rng.integers(3)
            if kind == 0:
                self.hold[:] = True
            elif kind == 1:
                self.hold[: rng.integers(30, max(31, frames))] = True
            else:
                for _ in range(rng.integers(2, 5)):
                    self.hold[span(8, 25)] = True
        elif self.mode == "learned":
            import families

            self.learned = (families.POOL[int(rng.integers(len(families.POOL)))], int(rng.integers(2**31)))
        self.waypoint, self.until, self.gain, self.grip = None, -1, 10.0, -1.0
        # How often the expert looks at the object (drawn last, so that at 1,1 every other draw
        # stays as it was). Between looks it acts on its belief, which, as policies.Policy's does,
        # takes the drawer handle to follow the hand that pulls it: a pull that misses the handle
        # then goes on as long as one that hooks it, and the commands do not tell the outcome.
        lo, hi = observe_every
        self.observe_every = lo if lo == hi else int(rng.integers(lo, hi + 1))
        self.belief, self.pulled_from = None, None
        self.started_at, self.stopped = None, False  # partial: where the pull or press began; whether it has ended
        self.policy, self.queue = None, []

    def command(self, t: int, state: np.ndarray, obj: np.ndarray, image: np.ndarray | None = None) -> np.ndarray:
        """The command of frame `t` in `state`, the object (ground truth, which the expert reads
        every `observe_every` frames) at `obj`; a learned policy reads `image` instead."""
        if self.learned is not None:
            return self._learned(state, image)
        rng, grip = self.rng, self.policies.GRIP[self.task]
        if t % self.observe_every == 0:
            self.belief = np.array(obj, float)
        elif self.pulled_from is not None:
            self.belief[1] += state[1] - self.pulled_from
        self.pulled_from = None
        if self.hold[t] or self.stopped:
            if self.stopped and self.back_off:
                return np.append(state[:3] + [0.0, 0.0, ACTION_SCALE], grip).astype(np.float32)
            return state.copy()
        if self.explore[t]:
            if t >= self.until or np.abs(self.waypoint - state[:3]).max() < 0.01:
                if self.around:
                    self.waypoint = np.clip(self.belief + rng.uniform(-0.15, 0.15, 3) * [1, 1, 0.5], EXPLORE_LOW, EXPLORE_HIGH)
                else:
                    self.waypoint = rng.uniform(EXPLORE_LOW, EXPLORE_HIGH)
                self.until = t + int(rng.integers(10, 30))
                self.gain = rng.uniform(5.0, 30.0)
                self.grip = rng.choice([-1.0, 1.0])
            to, gain, grip = self.waypoint, self.gain, self.grip
        else:
            to, gain, pulling = self.policies.expert_target(self.task, self.belief + self.offset, state)
            if pulling:
                self.pulled_from = state[1]
            if self.stop_after is not None:
                self._stop_short(state, pulling)
        speed = 1.0 if self.explore[t] else self.speed
        noise = rng.uniform(1.0, 2.0) if self.burst[t] else self.noise
        a = np.clip(np.clip(gain * (to - state[:3]), -1, 1) * speed + noise * rng.standard_normal(3), -1, 1)
        return np.append(state[:3] + a * ACTION_SCALE, grip).astype(np.float32)

    def _stop_short(self, state: np.ndarray, pulling: bool) -> None:
        """partial: ends the pull once the hand has pulled `stop_after` since it hooked the handle,
        the press once the hand is `stop_after` below the button's top."""
        if self.task == "drawer-open-v3":
            if pulling and self.started_at is None:
                self.started_at = float(state[1])
            if self.started_at is not None and self.started_at - state[1] >= self.stop_after:
                self.stopped = True
        elif state[2] <= self.belief[2] + self.offset[2] - self.stop_after and np.linalg.norm(state[:2] - (self.belief + self.offset)[:2]) < 0.04:
            self.stopped = True

    def _learned(self, state: np.ndarray, image: np.ndarray | None) -> np.ndarray:
        """learned: the pool's policy, a chunk of commands per frame it is shown."""
        if image is None:
            raise ValueError("a learned behaviour needs the frame")
        if not self.queue:
            if self.policy is None:
                import families

                (kind, demos), seed = self.learned
                # The pool's demonstrations at the frames' resolution (prepare_pool's).
                self.policy = families.pool_policy(self.task, kind, demos, seed, image.shape[0])
            self.queue = list(self.policy.act(image, state, LEARNED_CHUNK))
        return np.asarray(self.queue.pop(0), np.float32)


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


def simulate(behaviour: Behaviour, sim, frames: int, render: bool = True) -> tuple[list, list, list, list, list, list]:
    """`behaviour` in `sim` for `frames` frames from its reset: per frame the image (None unless
    `render`), state, command and Meta-World delta action; and frames + 1 success flags and object
    distances to the goal (m, `Sim.obj_to_target`), each as that frame was shown (the last: after
    the last command)."""
    images, states, commands, deltas, success, distance = [], [], [], [], [], []
    image, state = sim.reset()
    done = False
    for t in range(frames):
        command = behaviour.command(t, state, sim.object_pos(), image)
        images.append(image)
        states.append(state)
        commands.append(command)
        success.append(done)
        distance.append(sim.obj_to_target())
        image, state, done = sim.step(command, render=render and t + 1 < frames)
        deltas.append(sim.last_action)
    success.append(done)
    distance.append(sim.obj_to_target())
    return images, states, commands, deltas, success, distance


def run_episode(job: tuple) -> dict:
    """Simulates one episode and writes its parquet file; returns its metadata."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    root, episode_index, first_index, task_index, task, seed, frames, resolution, mix, observe = job
    behaviour = Behaviour(task, episode_rng(task, seed), frames, observe, mix)
    with Sim(task, seed, resolution) as sim:
        images, states, commands, deltas, success, distance = simulate(behaviour, sim, frames)
    images, states, commands, deltas = (np.stack(x) for x in (images, states, commands, deltas))
    success, distance = np.array(success), np.array(distance, np.float32)
    vec = lambda rows: pa.FixedSizeListArray.from_arrays(pa.array(rows.reshape(-1), pa.float32()), rows.shape[1])
    n = frames
    table = pa.table({
        "observation.image": pa.array([{"bytes": png(i), "path": None} for i in images], pa.struct([("bytes", pa.binary()), ("path", pa.string())])),
        "observation.state": vec(states),
        "action": vec(commands),
        "action_delta": vec(deltas),
        "success": pa.array(success[:-1]),
        "next.success": pa.array(success[1:]),
        "obj_to_target": pa.array(distance[:-1]),
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
                "obj_to_target": stats(distance[:-1]),
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
        # The object's distance to its goal as the frame is shown (m; mw.Sim.obj_to_target): the
        # simulator's state behind `success`, for judges that read the outcome as it defines it.
        "obj_to_target": scalar("float32"),
        "timestamp": scalar("float32"),
        "frame_index": scalar("int64"),
        "episode_index": scalar("int64"),
        "index": scalar("int64"),
        "task_index": scalar("int64"),
    }


def mix(text: str) -> dict[str, float]:
    """`--mix MODE=W,...`: the behaviours' weights (modes left out weigh 0)."""
    out = {}
    for part in text.split(","):
        name, _, value = part.partition("=")
        if name not in MIX or name in out:
            raise argparse.ArgumentTypeError(f"takes MODE=W,... with each of {', '.join(MIX)} at most once, got {text!r}")
        try:
            out[name] = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}'s weight must be a number, got {value!r}") from None
        if not (np.isfinite(out[name]) and out[name] >= 0):
            raise argparse.ArgumentTypeError(f"{name}'s weight must be finite and >= 0, got {value!r}")
    if sum(out.values()) <= 0:
        raise argparse.ArgumentTypeError(f"some weight must be above 0, got {text!r}")
    return {k: out[k] for k in MIX if k in out}


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
    """What a dataset's bytes depend on (not --workers), as meta/generator.json records it; with a
    `learned` share, the bytes of families.py too (its pool's policies)."""
    chosen = {"tasks": args.tasks, "episodes": args.episodes, "seed_start": args.seed_start, "frames": args.frames,
              "resolution": args.resolution, "mix": args.mix, "observe_every": args.observe_every}
    if args.mix.get("learned", 0) > 0:
        import families

        chosen["families_py"] = families.source_digest()
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
    parser.add_argument("--mix", type=mix, default=dict(MIX), metavar="MODE=W,...",
                        help="the behaviours' weights (normalised; modes left out weigh 0); default "
                             + ",".join(f"{k}={v:g}" for k, v in MIX.items()) + " (the module's MIX says why)")
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
    if args.workers < 1:
        parser.error("--workers must be at least 1")
    if os.path.exists(args.out) and not (args.force or args.reuse):
        parser.error(f"{args.out} exists (--force replaces it, --reuse keeps it when made with the same settings)")
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.reuse and os.path.exists(args.out):
        reuse(args)
        return
    if args.mix.get("learned", 0) > 0:
        # The pool's policies trained (or found in their cache) once, before the workers use them.
        import families

        families.prepare_pool(args.tasks, args.resolution, args.workers)
    out = os.path.abspath(args.out)
    tmp = f"{out}.tmp-{os.getpid()}"
    os.makedirs(os.path.join(tmp, "meta"))
    jobs = []
    for i in range(args.episodes):
        for task_index, task in enumerate(args.tasks):
            e = len(jobs)
            jobs.append((tmp, e, e * args.frames, task_index, task, args.seed_start + i, args.frames, args.resolution, args.mix, args.observe_every))
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
