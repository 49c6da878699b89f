"""The world model's outcome of one chunk at a time from the simulator's own history (teacher
forcing): where the closed-loop study (study.py) lets the world model run each episode on its own
frames, here every chunk starts from the real frames. Each policy variant runs in the simulator on
the held-out placements (as the truth does, every frame kept); then, for each chunk of K frames,
the world model served by `bwm serve` is given x0, the H real frames before the chunk and the
commands the policy issued, and the judge decides success on the K frames it draws and on the K
frames the simulator rendered. A model whose one-chunk outcomes follow the simulator's while its
closed-loop estimates do not invents over the chunks, from its own frames; one whose one-chunk
outcomes are already wrong draws the wrong outcome of a command from real frames.

    python teacher.py --data VAL_DATASET --judge judge.pt --episodes 50 --out DIR \\
        -- --checkpoint CKPT --vae VAE --stats STAT.json --stats-group observation.state \\
           --history 8 --future 24 --sample-steps 4 --device cuda

Episodes, seeds and variants are study.py's. The chunks follow `bwm evaluate`'s layout: the first
from x0 alone, chunk c from x0 and frames 24c-7 .. 24c, drawing frames 24c+1 .. 24c+24; x0's action
is the initial commanded state, every later frame's the command that led to it. Writes
DIR/teacher.json: per variant the true rate, the rate the judge gives the simulator's chunks and
the teacher-forced rate (an episode counts as a success when the judge passes any of its drawn
chunks), Pearson r / Spearman / MAE of both against the truth (per task and over all), the chunks
drawn succeeding where the simulator's did not (invented) and the other way (missed), over
all chunks their agreement and Cohen's kappa, and per episode each chunk's two probabilities and
the hand's offset from the object at its closest approach in the simulator (`offset_at_closest_cm`,
which contact_map.py maps). Everything after `--` goes to `bwm serve`.

With --own-episodes the episodes are the dataset's own instead (a training set's, to ask whether
the world model learned the outcomes it was trained on, or a held-out set's): its frames, its
`observation.state` as the actions (what `bwm prepare` trains on) and its success flags as the
truth, rows by task and the generator's `behaviour` (--behaviours picks them, e.g. `near`), the
closest approach measured by replaying the episode's commands (`action`) in the simulator from its
seed. --episodes is then per task (its first episodes of those behaviours), --horizon is cut to
the episodes' length, and --variants does not apply.

    python teacher.py --data TRAIN_DATASET --own-episodes --behaviours near --episodes 400 \\
        --judge judge.pt --out DIR -- --checkpoint CKPT ...
"""
from __future__ import annotations

import argparse
import io
import json
import multiprocessing
import os
import re
import subprocess
import sys
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import msgpack_numpy  # noqa: E402
from files import write_json  # noqa: E402
import study  # noqa: E402


def chunk_layout(horizon: int, chunk: int, history: int) -> list[tuple[list[int], list[int]]]:
    """Per chunk: (the frame indices given to the world model, the frame indices it draws), as
    `bwm evaluate` rolls an episode out: x0 then up to `history` frames before the chunk."""
    out, t0 = [], 0
    while t0 < horizon:
        given = [0] + list(range(max(1, t0 - history + 1), t0 + 1))
        out.append((given, list(range(t0 + 1, min(t0 + chunk, horizon) + 1))))
        t0 += chunk
    return out


def frame_actions(task: str, commands: np.ndarray) -> np.ndarray:
    """float32 [T + 1, 4]: frame 0's action is the initial commanded state (the dataset's
    observation.state at x0), frame t's the command issued before it."""
    import mw

    return np.concatenate([mw.initial_state(task)[None], np.asarray(commands, np.float32).reshape(-1, 4)]).astype(np.float32)


def _record_job(job):
    task, variant, seeds, horizon, chunk, resolution = job
    import variants

    return task, variant, [(seed, e.first, e.frames, frame_actions(task, e.commands), e.nearest_cm)
                           for seed in seeds for e in [variants.run_episode(task, variant, seed, horizon, chunk, resolution, record=True)]]


class EpisodeFrames:
    """A dataset episode's frames, uint8 [T, H, W, 3], decoded from its parquet file only when
    `np.asarray` asks for them: the own stage holds hundreds of episodes at once, and takes each
    episode's frames only while the world model draws from them."""

    def __init__(self, path: str, column: str, count: int, size: tuple[int, int]):
        self.path, self.column, self.count, self.size = path, column, count, size

    def __len__(self) -> int:
        return self.count

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        import pyarrow.parquet as pq
        from PIL import Image

        cells = pq.read_table(self.path, columns=[self.column]).column(self.column).combine_chunks().field("bytes").to_pylist()
        frames = np.stack([np.asarray(Image.open(io.BytesIO(c)).convert("RGB")) for c in cells])
        if frames.shape != (self.count, *self.size, 3):
            raise ValueError(f"{self.path}: frames {frames.shape}, its dataset's meta/info.json says {self.count} of {self.size}")
        return frames if dtype is None else frames.astype(dtype)


def _own_job(job):
    """One dataset episode as teacher_forced takes it: its behaviour and (seed, first success
    frame, its frames (EpisodeFrames), actions float32 [T, 4], the hand's offset from the object at
    its closest approach in cm, from its commands replayed in the simulator)."""
    root, info, task, episode = job
    import pyarrow.parquet as pq

    import judge
    import policies

    i = episode["episode_index"]
    path = judge.episode_file(root, info, i)
    flag = judge.success_column(pq.read_schema(path).names)
    table = pq.read_table(path, columns=["observation.state", "action", flag])
    column = lambda name: np.asarray(table.column(name).to_pylist(), np.float32)
    success = np.asarray(table.column(flag).to_pylist(), bool)
    first = int(np.argmax(success)) if success.any() else None
    replayed = policies.replay(task, int(episode["seed"]), column("action")[: table.num_rows - 1])
    if replayed.first != first:
        raise ValueError(f"{root}: episode {i}'s commands replayed from seed {episode['seed']} first succeed at frame "
                         f"{replayed.first}, its success flags say {first}: not this simulator's episode")
    return episode["behaviour"], (int(episode["seed"]), first, EpisodeFrames(path, judge.image_column(info), table.num_rows, judge.image_size(info)),
                                  column("observation.state"), replayed.nearest_cm)


def record_own(root: str, episodes: dict[str, list[dict]], resolution: int, workers: int) -> dict[str, dict[str, list]]:
    """{task: {behaviour: [records]}} of the dataset's `episodes` (study.dataset_episodes), in their order."""
    import judge

    with open(os.path.join(root, "meta", "info.json")) as f:
        info = json.load(f)
    height, width = judge.image_size(info)
    if (height, width) != (resolution, resolution):
        raise SystemExit(f"teacher: {root}: frames of {width}x{height}, but --resolution is {resolution}")
    jobs = [(root, info, t, e) for t, eps in episodes.items() for e in eps]
    # The workers raise ValueError, which the pool hands back (a SystemExit would end a worker and
    # leave the map waiting for it).
    try:
        with multiprocessing.get_context("spawn").Pool(min(workers, len(jobs))) as pool:
            done = pool.map(_own_job, jobs)
    except ValueError as e:
        raise SystemExit(f"teacher: {e}") from None
    out: dict[str, dict[str, list]] = {t: {} for t in episodes}
    for (_, _, t, _), (behaviour, record) in zip(jobs, done):
        out[t].setdefault(behaviour, []).append(record)
    return out


def post(url: str, body: bytes, patience: float = 600.0) -> bytes:
    """The server's answer to a msgpack POST; asked again while it answers 503 (its queue full:
    more requests at once than `bwm serve --queue` holds), for up to `patience` seconds."""
    deadline = time.time() + patience
    while True:
        request = urllib.request.Request(url, data=body, headers={"Content-Type": "application/msgpack"})
        try:
            with urllib.request.urlopen(request, timeout=600) as r:
                return r.read()
        except urllib.error.HTTPError as e:
            text = e.read().decode(errors="replace")
            if e.code != 503 or time.time() >= deadline:
                raise SystemExit(f"teacher: bwm serve answered {e.code}: {text}") from None
        time.sleep(0.05)


class WorldModel:
    """`bwm serve` on a free port for the run's lifetime; `chunk` asks it for one chunk."""

    def __init__(self, bwm: str, flags: list[str], log: str):
        self.log = open(log, "w")
        self.proc = subprocess.Popen([bwm, "serve", *flags, "--port", "0"], stdout=self.log, stderr=subprocess.STDOUT)
        start = time.time()
        while True:
            with open(log) as f:
                m = re.search(r"serve: listening on (http://\S+)", f.read())
            if m:
                self.url = m.group(1) + "/v1/chunk"
                return
            if self.proc.poll() is not None:
                raise SystemExit(f"teacher: bwm serve exited ({self.proc.returncode}) before listening; its log {log}:\n{study.tail(log)}")
            if time.time() - start > 300:
                self.close()
                raise SystemExit(f"teacher: bwm serve did not listen within 300 s; its log {log}:\n{study.tail(log)}")
            time.sleep(0.2)

    def chunk(self, frames: np.ndarray, actions: np.ndarray, seed: int) -> np.ndarray:
        body = msgpack_numpy.packb({"frames": frames, "actions": actions, "normalized": False, "seed": seed})
        return msgpack_numpy.unpackb(post(self.url, body))["frames"]

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        self.log.close()


def teacher_forced(task, variant, recorded, wm: WorldModel, judge, layout, positions: dict, requests: int = 1) -> list[dict]:
    """Per recorded episode (seed, first success step, frames from x0 on (an array or
    EpisodeFrames), each frame's action, the hand's offset at its closest approach; in their
    order): its first success step, that offset and, per chunk, the judge's probability on the
    simulator's frames and on the world model's drawn from them. `requests` episodes at once, so
    that the server generates while the judge scores another's chunk; each chunk's sampling seed
    is its own, so the order the server takes them in changes nothing."""

    def episode(record):
        seed, first, frames, actions, nearest = record
        frames = np.asarray(frames)
        real, drawn = [], []
        for c, (given, target) in enumerate(layout):
            generated = wm.chunk(frames[given], actions[given + target], seed=positions[task, seed] * 1000 + c)
            ask = {"task": task, "prompt": task}
            real.append(round(float(judge.judge(dict(ask, frames=frames[target]))["success_probability"]), 4))
            drawn.append(round(float(judge.judge(dict(ask, frames=generated[: len(target)]))["success_probability"]), 4))
        return {"seed": seed, "first": first, "real": real, "drawn": drawn, "offset_at_closest_cm": [round(float(x), 3) for x in nearest]}

    with ThreadPoolExecutor(requests) as pool:
        return list(pool.map(episode, recorded))


def summarize(results: dict, tasks: list[str], variants: list[str]) -> dict:
    """Rates and agreement from {task: {variant: [episode records]}}."""
    rows, real_chunks, drawn_chunks = [], [], []
    for t in tasks:
        for v in (v for v in variants if v in results[t]):
            eps = results[t][v]
            # Each chunk as an episode of study.episode_agreement: the simulator's verdict, the world model's.
            real = [r >= study.THRESHOLD for e in eps for r in e["real"]]
            drawn = [d >= study.THRESHOLD for e in eps for d in e["drawn"]]
            per = study.episode_agreement(real, drawn)
            real_chunks += real
            drawn_chunks += drawn
            n = len(eps)
            rows.append({"task": t, "variant": v, "episodes": n,
                         "true": sum(e["first"] is not None for e in eps) / n,
                         "judged_simulator": sum(max(e["real"]) >= study.THRESHOLD for e in eps) / n,
                         "teacher_forced": sum(max(e["drawn"]) >= study.THRESHOLD for e in eps) / n,
                         "chunks_invented": per["invented"], "chunks_missed": per["missed"]})

    def scores(rs):
        names = [f"{r['variant']}/{r['task']}" for r in rs]
        true = [r["true"] for r in rs]
        return {"teacher_forced": study.agreement(names, [r["teacher_forced"] for r in rs], true),
                "judged_simulator": study.agreement(names, [r["judged_simulator"] for r in rs], true)}

    return {"rates": rows, "all": scores(rows), "per_task": {t: scores([r for r in rows if r["task"] == t]) for t in tasks},
            "chunks": study.episode_agreement(real_chunks, drawn_chunks)}


def main(argv=None) -> None:
    argv, serve_flags = study.split_flags(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--judge", required=True, help="judge.pt from judge.py train")
    ap.add_argument("--judge-device", default="auto", help="where the judge runs (auto, cpu, cuda)")
    ap.add_argument("--history", type=study.at_least_one, default=8, help="real frames before each chunk (the world model's H)")
    ap.add_argument("--requests", type=study.at_least_one, default=3,
                    help="chunks asked of bwm serve at once (more than its --queue + 1 wait their turn)")
    study.add_episode_arguments(ap)
    ap.add_argument("--own-episodes", action="store_true",
                    help="the dataset's own episodes (frames, observation.state, success flags) instead of the policy variants on its placements")
    ap.add_argument("--behaviours", help="with --own-episodes: the generator behaviours taken, comma-separated (default: all)")
    a = ap.parse_args(argv)
    if not serve_flags:
        ap.error("the world model's flags for `bwm serve` go after --")
    if a.own_episodes and a.variants:
        ap.error("--variants names policy variants; with --own-episodes pick the dataset's episodes by --behaviours")
    if a.behaviours and not a.own_episodes:
        ap.error("--behaviours picks the dataset's own episodes (--own-episodes)")
    if a.own_episodes:
        tasks = study.tasks_checked(ap, a)
    else:
        tasks, variants = study.tasks_and_variants(ap, a)
    if not os.path.isfile(a.judge):
        ap.error(f"no judge at {a.judge} (judge.py train writes it)")
    if not os.access(a.bwm, os.X_OK):
        ap.error(f"no bwm binary at {a.bwm} (make build, or pass --bwm)")
    if a.own_episodes:
        behaviours = a.behaviours.split(",") if a.behaviours else None
        own = study.dataset_episodes(a.data, tasks, a.episodes, behaviours, tool="teacher")
        positions = {(t, int(e["seed"])): e["position"] for t, eps in own.items() for e in eps}
    else:
        episodes = study.episodes_by_task(a.data, tasks, a.episodes)
        positions = {(t, s): p for t, eps in episodes.items() for p, s in eps}
    os.makedirs(a.out, exist_ok=True)

    from judge import Judge, pick_device

    judge = Judge(a.judge, pick_device(a.judge_device), None)
    results: dict = {t: {} for t in tasks}
    start = time.time()

    def show(t, v, n, total):
        eps = results[t][v]
        print(f"teacher: {t} {v}: true {np.mean([e['first'] is not None for e in eps]):.2f}, teacher-forced "
              f"{np.mean([max(e['drawn']) >= study.THRESHOLD for e in eps]):.2f} {n}/{total} ({time.time() - start:.0f} s)", flush=True)

    if a.own_episodes:
        recorded = record_own(a.data, own, a.resolution, a.workers)
        length = min(len(r[2]) for by in recorded.values() for rs in by.values() for r in rs)
        horizon = min(a.horizon, length - 1)
        variants = sorted({b for by in recorded.values() for b in by}, key=lambda b: -sum(len(by.get(b, ())) for by in recorded.values()))
        print(f"teacher: {sum(len(e) for e in own.values())} episodes of {a.data} ({', '.join(variants)}) recorded with their "
              f"closest approaches ({time.time() - start:.0f} s)", flush=True)
    else:
        horizon = a.horizon
    layout = chunk_layout(horizon, a.chunk, a.history)
    wm = WorldModel(a.bwm, serve_flags, os.path.join(a.out, "serve.log"))
    try:
        if a.own_episodes:
            pairs = [(t, v) for t in tasks for v in variants if v in recorded[t]]
            for n, (t, v) in enumerate(pairs, 1):
                results[t][v] = teacher_forced(t, v, recorded[t][v], wm, judge, layout, positions, a.requests)
                show(t, v, n, len(pairs))
        else:
            jobs = [(t, v, [s for _, s in episodes[t]], a.horizon, a.chunk, a.resolution) for t in tasks for v in variants]
            with multiprocessing.get_context("spawn").Pool(min(a.workers, len(jobs))) as pool:
                for n, (t, v, recorded) in enumerate(pool.imap_unordered(_record_job, jobs), 1):
                    results[t][v] = teacher_forced(t, v, recorded, wm, judge, layout, positions, a.requests)
                    show(t, v, n, len(jobs))
    finally:
        wm.close()
    summary = summarize(results, tasks, variants)
    report = {"settings": {"data": a.data, "judge": a.judge, "episodes": a.episodes, "horizon": horizon, "chunk": a.chunk,
                           "history": a.history, "resolution": a.resolution, "serve": serve_flags, "threshold": study.THRESHOLD,
                           "own_episodes": a.own_episodes, "behaviours": a.behaviours},
              **summary, "episodes": results}
    path = os.path.join(a.out, "teacher.json")
    write_json(path, report)
    for r in summary["rates"]:
        print(f"teacher: {r['task']:26s} {r['variant']:10s} true {r['true']:.2f}  judged simulator {r['judged_simulator']:.2f}  "
              f"teacher-forced {r['teacher_forced']:.2f}  chunks invented {r['chunks_invented']} missed {r['chunks_missed']}")
    s = summary["all"]
    print(f"teacher: over all {len(summary['rates'])} rates: teacher-forced r {study.fmt(s['teacher_forced']['pearson_r'])}, "
          f"judge on the simulator's chunks r {study.fmt(s['judged_simulator']['pearson_r'])}; {path}")


if __name__ == "__main__":
    main()
