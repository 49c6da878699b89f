"""How far the hand pulls the drawer's way (toward the robot, -y) while low enough to hook the
handle, by outcome: in a generate.py dataset's drawer episodes (their observation.state and
success flags, by generator behaviour) and in policy variants' simulator episodes on the same
placements, as the study runs them (a frame every chunk).

A world model sees the commands of a whole chunk beside its frames. If the data's failing pulls
are all shorter than their successful ones (an expert that sees the drawer stay behind stops
pulling), the commands alone tell the outcome, and a policy whose pull misses the handle but goes
on, as a policy acting on one frame per chunk does, is drawn opening the drawer
(docs/fidelity.md, run 39).

    python pulls.py DATA [--behaviours miss,expert] [--variants wrong,blind] [--episodes 50] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os

import numpy as np

import study

TASK = "drawer-open-v3"
# The commanded hand is low enough to hook the handle (at z 0.07 over its placements; the expert
# pulls at 0.05) below this height (m).
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


def _dataset_job(job):
    root, info, episode = job
    import pyarrow.parquet as pq

    i = episode["episode_index"]
    table = pq.read_table(os.path.join(root, info["data_path"].format(episode_chunk=i // info.get("chunks_size", 1000), episode_index=i)))
    states = np.asarray(table.column("observation.state").to_pylist(), np.float32)
    commands = np.asarray(table.column("action").to_pylist(), np.float32)
    # The states are the commanded hand before each command; the last command adds the last step.
    return episode["behaviour"], bool(episode["success"]), pull_cm(np.concatenate([states, commands[-1:]]))


def _variant_job(job):
    variant, seed, horizon, chunk, resolution = job
    import policies

    # The policies find the object in the frame: at the dataset's resolution, as in the study.
    e = policies.run_episode(TASK, variant, seed, horizon, chunk, resolution, record=True)
    return variant, e.first is not None, pull_cm(e.commands)


def summary(cm: list[float]) -> dict:
    v = np.asarray(cm, float)
    if not len(v):
        return {"n": 0}
    return {"n": len(v), "p10": float(np.percentile(v, 10)), "median": float(np.median(v)), "p90": float(np.percentile(v, 90))}


def pull_rule(dataset: dict, variants: dict) -> dict | None:
    """The rule that reads the outcome off the commands alone: a pull at least `threshold_cm` long
    opens the drawer, the shortest threshold that sorts the dataset's episodes best; its accuracy
    there, and the success rate it gives each variant (what a world model that learned only the
    rule would estimate). None without both outcomes in the data."""
    rows = [(cm, ok) for g in dataset.values() for ok, k in ((True, "succeeded"), (False, "failed")) for cm in g[k]]
    if not any(ok for _, ok in rows) or all(ok for _, ok in rows):
        return None
    right = lambda t: sum((cm >= t) == ok for cm, ok in rows)  # noqa: E731
    threshold = max(sorted({cm for cm, _ in rows}), key=right)  # max keeps the first (shortest) of equals
    rate = lambda g: float(np.mean([cm >= threshold for cm in g["succeeded"] + g["failed"]]))  # noqa: E731
    return {"threshold_cm": threshold, "data_accuracy": right(threshold) / len(rows), "episodes": len(rows),
            "variants": {v: {"rule": rate(g), "true": len(g["succeeded"]) / len(g["succeeded"] + g["failed"])} for v, g in variants.items()}}


def measure(data: str, behaviours: list[str] | None, variants: list[str], episodes: int | None, variant_episodes: int,
            horizon: int, chunk: int, workers: int) -> dict:
    with open(os.path.join(data, "meta", "info.json")) as f:
        info = json.load(f)
    own = study.dataset_episodes(data, [TASK], episodes, behaviours, tool="pulls")[TASK]
    seeds = [int(e["seed"]) for e in study.dataset_episodes(data, [TASK], variant_episodes, need=variant_episodes if variants else 1, tool="pulls")[TASK]]
    import judge

    resolution = info["features"][judge.image_column(info)]["shape"][0]
    jobs = [(data, info, e) for e in own]
    with multiprocessing.get_context("spawn").Pool(max(1, min(workers, len(jobs)))) as pool:
        rows = [("dataset", *r) for r in pool.map(_dataset_job, jobs)]
        if variants:
            rows += [("variant", *r) for r in pool.map(_variant_job, [(v, s, horizon, chunk, resolution) for v in variants for s in seeds])]
    out: dict = {"dataset": {}, "variants": {}}
    for kind, name, ok, cm in rows:
        group = out["dataset" if kind == "dataset" else "variants"].setdefault(name, {"succeeded": [], "failed": []})
        group["succeeded" if ok else "failed"].append(round(cm, 3))
    succeeded = sorted(cm for g in out["dataset"].values() for cm in g["succeeded"])
    # The shortest pulls that open the drawer in the data: a failing pull as long is one whose
    # commands look like a success's.
    floor = float(np.percentile(succeeded, 10)) if succeeded else None
    out["succeeding_pull_p10_cm"] = floor
    for section in ("dataset", "variants"):
        for g in out[section].values():
            g["summary"] = {k: summary(g[k]) for k in ("succeeded", "failed")}
            g["failed_as_long_as_successes"] = None if floor is None else sum(int(cm >= floor) for cm in g["failed"])
    out["rule"] = pull_rule(out["dataset"], out["variants"])
    return out


def report(out: dict) -> str:
    floor = out["succeeding_pull_p10_cm"]
    lines = [f"{TASK}: the longest pull (cm of -y travel while low) by outcome; the data's successful pulls' 10th percentile "
             + ("-" if floor is None else f"{floor:.1f} cm")]
    for section, label in (("dataset", "data"), ("variants", "variant")):
        for name, g in out[section].items():
            for k in ("succeeded", "failed"):
                s = g["summary"][k]
                if s["n"]:
                    extra = f"; {g['failed_as_long_as_successes']} at least as long" if k == "failed" and floor is not None else ""
                    lines.append(f"  {label} {name:10s} {k:9s} {s['n']:4d}: p10 {s['p10']:5.1f}  median {s['median']:5.1f}  p90 {s['p90']:5.1f}{extra}")
    rule = out.get("rule")
    if rule:
        lines.append(f"  the commands alone: a pull of at least {rule['threshold_cm']:.1f} cm opens the drawer in "
                     f"{rule['data_accuracy']:.3f} of the data's {rule['episodes']} episodes")
        lines += [f"    variant {v:10s} true {r['true']:.2f}, by that rule {r['rule']:.2f}" for v, r in rule["variants"].items()]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="a generate.py dataset holding drawer-open-v3 episodes")
    ap.add_argument("--behaviours", help="generator behaviours taken, comma-separated (default: all)")
    ap.add_argument("--episodes", type=study.at_least_one, help="at most this many of the dataset's drawer episodes (default: all)")
    ap.add_argument("--variants", default="", help="policy variants run on the dataset's first placements, comma-separated (e.g. wrong,blind)")
    ap.add_argument("--variant-episodes", type=study.at_least_one, default=30, help="placements per variant")
    ap.add_argument("--horizon", type=study.at_least_one, default=120)
    ap.add_argument("--chunk", type=study.at_least_one, default=24, help="commands per frame the policies see (the world model's K)")
    ap.add_argument("--workers", type=study.at_least_one, default=os.cpu_count() or 1)
    ap.add_argument("--json", help="write the pulls and their summary here")
    a = ap.parse_args(argv)
    import policies

    variants = [v for v in a.variants.split(",") if v]
    if problem := policies.check_variants([TASK], variants):
        ap.error(problem)
    out = measure(a.data, a.behaviours.split(",") if a.behaviours else None, variants, a.episodes, a.variant_episodes, a.horizon, a.chunk, a.workers)
    print(report(out))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
