"""What a dataset's commands tell of the outcome, per task, beside what the policy variants'
commands tell: for the drawer the hand's longest pull toward the robot (-y) while low enough to
hook the handle, for the button how far below its starting height the hand is commanded. Measured
by outcome in a generate.py dataset's episodes (their observation.state and success flags, by
generator behaviour) and in policy variants' simulator episodes on the same placements, as the
study runs them (a frame every chunk); and the rule that reads the outcome off that one number,
fit on the dataset, applied to the variants.

A world model sees the commands of a whole chunk beside its frames. If the data's outcome follows
its commands (an expert that sees the drawer stay behind stops pulling; one that sees the button
go down follows it), the world model can learn the commands instead of the contact, and draws a
policy's pull that misses but goes on, as a policy acting on one frame per chunk does, opening
the drawer (docs/fidelity.md at abaed68, run 39).

    python tells.py DATA [--tasks drawer-open-v3] [--behaviours near,expert] [--variants wrong,blind] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np

import study
from files import write_json

# The commanded hand is low enough to hook the drawer handle (at z 0.07 over its placements; the
# expert pulls at 0.05) below this height (m).
LOW_Z = 0.10


def pull_cm(positions) -> float:
    """The longest stretch of -y travel of the hand (rows [x, y, z, ...]) while it stays low, in cm."""
    p = np.asarray(positions, np.float64)
    best = run = 0.0
    for a, b in zip(p[:-1], p[1:]):
        if b[2] < LOW_Z and b[1] < a[1]:
            run += a[1] - b[1]
            best = max(best, run)
        elif b[2] >= LOW_Z or b[1] > a[1]:
            run = 0.0
    return 100 * best


def press_cm(positions) -> float:
    """How far below its first height the hand (rows [x, y, z, ...]) is commanded, in cm (0 if never)."""
    p = np.asarray(positions, np.float64)
    return 100 * max(0.0, float(p[0, 2] - p[:, 2].min()))


@dataclass(frozen=True)
class Tell:
    name: str
    what: str
    measure: Callable


TELLS = {
    "drawer-open-v3": Tell("pull", "cm of travel toward the robot while low", pull_cm),
    "button-press-topdown-v3": Tell("press", "cm below the hand's first height", press_cm),
}


def _dataset_job(job):
    root, info, task, episode = job
    import pyarrow.parquet as pq

    import judge

    i = episode["episode_index"]
    table = pq.read_table(judge.episode_file(root, info, i), columns=["observation.state", "action"])
    states = np.asarray(table.column("observation.state").to_pylist(), np.float32)
    commands = np.asarray(table.column("action").to_pylist(), np.float32)
    # The states are the commanded hand before each command; the last command adds the last step.
    return task, episode["behaviour"], bool(episode["success"]), TELLS[task].measure(np.concatenate([states, commands[-1:]]))


def _variant_job(job):
    task, variant, seed, horizon, chunk, resolution = job
    import mw
    import variants

    # The policies find the object in the frame: at the dataset's resolution, as in the study.
    e = variants.run_episode(task, variant, seed, horizon, chunk, resolution, record=True)
    hand = np.concatenate([mw.initial_state(task)[None], e.commands])
    return task, variant, e.first is not None, TELLS[task].measure(hand)


def summary(values: list[float]) -> dict:
    v = np.asarray(values, float)
    if not len(v):
        return {"n": 0}
    return {"n": len(v), "p10": float(np.percentile(v, 10)), "median": float(np.median(v)), "p90": float(np.percentile(v, 90))}


def rule(dataset: dict, variants: dict) -> dict | None:
    """The rule that reads the outcome off the commands alone: a value of at least `threshold`
    means success, the lowest threshold that sorts the dataset's episodes best; its accuracy
    there, and the success rate it gives each variant (what a world model that learned only the
    rule would estimate). None without both outcomes in the data."""
    rows = [(x, ok) for g in dataset.values() for ok, k in ((True, "succeeded"), (False, "failed")) for x in g[k]]
    if not any(ok for _, ok in rows) or all(ok for _, ok in rows):
        return None
    right = lambda t: sum((x >= t) == ok for x, ok in rows)  # noqa: E731
    threshold = max(sorted({x for x, _ in rows}), key=right)  # max keeps the first (lowest) of equals
    rate = lambda g: float(np.mean([x >= threshold for x in g["succeeded"] + g["failed"]]))  # noqa: E731
    return {"threshold": threshold, "data_accuracy": right(threshold) / len(rows), "episodes": len(rows),
            "variants": {v: {"rule": rate(g), "true": len(g["succeeded"]) / len(g["succeeded"] + g["failed"])} for v, g in variants.items()}}


def measure(data: str, tasks: list[str], behaviours: list[str] | None, variants: list[str], episodes: int | None,
            variant_episodes: int, horizon: int, chunk: int, workers: int) -> dict:
    """Per task: the dataset's and the variants' values by outcome, their summaries, and the rule."""
    import judge

    with open(os.path.join(data, "meta", "info.json")) as f:
        info = json.load(f)
    resolution = judge.image_size(info)[0]
    own = study.dataset_episodes(data, tasks, episodes, behaviours, tool="tells")
    jobs = [(data, info, t, e) for t in tasks for e in own[t]]
    variant_jobs = []
    if variants:
        placements = study.dataset_episodes(data, tasks, variant_episodes, need=variant_episodes, tool="tells")
        variant_jobs = [(t, v, int(e["seed"]), horizon, chunk, resolution) for t in tasks for v in variants for e in placements[t]]
    with multiprocessing.get_context("spawn").Pool(max(1, min(workers, len(jobs) + len(variant_jobs)))) as pool:
        rows = [("dataset", *r) for r in pool.map(_dataset_job, jobs)]
        rows += [("variants", *r) for r in pool.map(_variant_job, variant_jobs)]
    out: dict = {t: {"tell": TELLS[t].name, "unit": TELLS[t].what, "dataset": {}, "variants": {}} for t in tasks}
    for section, task, name, ok, x in rows:
        group = out[task][section].setdefault(name, {"succeeded": [], "failed": []})
        group["succeeded" if ok else "failed"].append(round(float(x), 3))
    for t in tasks:
        succeeded = [x for g in out[t]["dataset"].values() for x in g["succeeded"]]
        # The data's lowest successful values: a failure that reaches them has commands like a success's.
        floor = float(np.percentile(succeeded, 10)) if succeeded else None
        out[t]["succeeded_p10"] = floor
        for section in ("dataset", "variants"):
            for g in out[t][section].values():
                g["summary"] = {k: summary(g[k]) for k in ("succeeded", "failed")}
                g["failed_reaching_succeeded_p10"] = None if floor is None else sum(int(x >= floor) for x in g["failed"])
        out[t]["rule"] = rule(out[t]["dataset"], out[t]["variants"])
    return out


def report(out: dict) -> str:
    lines = []
    for task, o in out.items():
        floor = o["succeeded_p10"]
        lines.append(f"{task}: the {o['tell']} ({o['unit']}) by outcome; the data's successes' 10th percentile "
                     + ("-" if floor is None else f"{floor:.1f}"))
        for section, label in (("dataset", "data"), ("variants", "variant")):
            for name, g in o[section].items():
                for k in ("succeeded", "failed"):
                    s = g["summary"][k]
                    if s["n"]:
                        extra = f"; {g['failed_reaching_succeeded_p10']} reach it" if k == "failed" and floor is not None else ""
                        lines.append(f"  {label} {name:10s} {k:9s} {s['n']:4d}: p10 {s['p10']:5.1f}  median {s['median']:5.1f}  p90 {s['p90']:5.1f}{extra}")
        r = o["rule"]
        if r:
            lines.append(f"  the commands alone: a {o['tell']} of at least {r['threshold']:.1f} means success in "
                         f"{r['data_accuracy']:.3f} of the data's {r['episodes']} episodes")
            lines += [f"    variant {v:10s} true {x['true']:.2f}, by that rule {x['rule']:.2f}" for v, x in r["variants"].items()]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="a generate.py dataset")
    ap.add_argument("--tasks", default=",".join(TELLS), help="comma-separated; default every task with a tell")
    ap.add_argument("--behaviours", help="generator behaviours taken, comma-separated (default: all)")
    ap.add_argument("--episodes", type=study.at_least_one, help="at most this many of the dataset's episodes per task (default: all)")
    ap.add_argument("--variants", default="", help="policy variants run on the dataset's first placements, comma-separated (e.g. wrong,blind)")
    ap.add_argument("--variant-episodes", type=study.at_least_one, default=30, help="placements per variant and task")
    ap.add_argument("--horizon", type=study.at_least_one, default=120)
    ap.add_argument("--chunk", type=study.at_least_one, default=24, help="commands per frame the policies see (the world model's K)")
    ap.add_argument("--workers", type=study.at_least_one, default=os.cpu_count() or 1)
    ap.add_argument("--json", help="write the values and their summary here")
    a = ap.parse_args(argv)
    from variants import check_variants

    tasks = a.tasks.split(",")
    if unknown := [t for t in tasks if t not in TELLS]:
        ap.error(f"no tell for {', '.join(unknown)} (known: {', '.join(TELLS)})")
    variants = [v for v in a.variants.split(",") if v]
    if problem := check_variants(tasks, variants):
        ap.error(problem)
    out = measure(a.data, tasks, a.behaviours.split(",") if a.behaviours else None, variants, a.episodes, a.variant_episodes,
                  a.horizon, a.chunk, a.workers)
    print(report(out))
    if a.json:
        write_json(a.json, out)


if __name__ == "__main__":
    main()
