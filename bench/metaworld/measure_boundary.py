"""Measures where the scripted expert's outcome flips, per task and direction, in the simulator
(boundary.py describes the report; generate.py --miss-boundary draws near misses around it).

    python measure_boundary.py --tasks drawer-open-v3,button-press-topdown-v3 --directions 16 \\
        --seeds 900000:900004 --out boundary.json

Only the simulator is used: nothing is rendered but each reset's frame.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import sys
import zlib

import numpy as np

import generate
from boundary import direction, directions_deg
from mw import TASKS, Sim


def succeeds(task: str, seed: int, offset_cm: np.ndarray, frames: int) -> bool:
    """Whether the expert (its noise drawn from `seed`, no exploration) succeeds steering on the
    object estimate moved `offset_cm`."""
    behaviour = generate.Behaviour(task, np.random.default_rng([seed, zlib.crc32(b"boundary")]), frames, 0.0)
    behaviour.offset = np.asarray(offset_cm, float) / 100
    behaviour.explore[:] = False
    with Sim(task, seed, 32) as sim:
        return any(generate.simulate(behaviour, sim, frames, render=False)[4])


def bracket(job: tuple) -> list[float | None] | None:
    """[lo, hi] (cm) along one direction: the expert succeeds lo off and fails hi off, hi - lo
    <= tolerance (bisected: the outcome is taken to flip once); [max, None] when it succeeds max
    off; None when it fails on the object itself."""
    task, seed, degrees, max_cm, tolerance, frames = job
    unit = direction(math.radians(degrees))
    if not succeeds(task, seed, 0 * unit, frames):
        return None
    if succeeds(task, seed, max_cm * unit, frames):
        return [max_cm, None]
    lo, hi = 0.0, max_cm
    while hi - lo > tolerance:
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if succeeds(task, seed, mid * unit, frames) else (lo, mid)
    return [round(lo, 4), round(hi, 4)]


def measure(tasks: list[str], directions: int, seeds: list[int], max_cm: float, tolerance: float, frames: int, workers: int) -> dict:
    degrees = directions_deg(directions)
    jobs = [(t, s, d, max_cm, tolerance, frames) for t in tasks for d in degrees for s in seeds]
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        found = []
        for i, b in enumerate(pool.imap(bracket, jobs)):
            found.append(b)
            print(f"\rboundary: {i + 1}/{len(jobs)} brackets", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    report = {"frames": frames, "seeds": seeds, "max_cm": max_cm, "tolerance_cm": tolerance, "tasks": {}}
    for t in tasks:
        brackets = [[found.pop(0) for _ in seeds] for _ in degrees]
        cm = []
        for d, row in zip(degrees, brackets):
            mids = [b[0] if b[1] is None else (b[0] + b[1]) / 2 for b in row if b is not None]
            if not mids:
                raise RuntimeError(f"{t}: the expert failed on the object itself for every seed (direction {d:g} deg)")
            cm.append(round(float(np.median(mids)), 3))
        report["tasks"][t] = {"directions_deg": degrees, "boundary_cm": cm, "brackets_cm": brackets}
    return report


def seed_range(text: str) -> list[int]:
    """`A:B` as seeds A..B-1."""
    try:
        a, b = (int(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes FIRST:END, got {text!r}") from None
    if not 0 <= a < b <= 2**32 - 1:
        raise argparse.ArgumentTypeError(f"needs 0 <= FIRST < END < 2**32, got {text!r}")
    return list(range(a, b))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", default=",".join(TASKS))
    parser.add_argument("--directions", type=int, default=16, help="evenly spaced from 0 deg (+x)")
    parser.add_argument("--seeds", type=seed_range, default=seed_range("900000:900004"),
                        help="FIRST:END, object placements (default 900000:900004, outside the recipe's train and validation seeds)")
    parser.add_argument("--max-cm", type=float, default=16.0, help="the farthest distance tried")
    parser.add_argument("--tolerance-cm", type=float, default=0.5, help="bisection stops when the bracket is this narrow")
    parser.add_argument("--frames", type=int, default=120, help="episode length (the generator's --frames: a shorter episode leaves less time to succeed)")
    parser.add_argument("--workers", type=int, default=min(4, os.cpu_count() or 1))
    parser.add_argument("--out", required=True, help="the JSON report (generate.py --miss-boundary reads it)")
    args = parser.parse_args(argv)
    tasks = args.tasks.split(",")
    if unknown := [t for t in tasks if t not in TASKS]:
        parser.error(f"unknown task(s) {', '.join(unknown)} (known: {', '.join(TASKS)})")
    if args.directions < 2 or args.frames < 2 or args.workers < 1:
        parser.error("--directions must be at least 2, --frames at least 2, --workers at least 1")
    if not 0 < args.tolerance_cm < args.max_cm:
        parser.error("needs 0 < --tolerance-cm < --max-cm")
    report = measure(tasks, args.directions, args.seeds, args.max_cm, args.tolerance_cm, args.frames, args.workers)
    tmp = f"{args.out}.tmp-{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(report, f, indent=1)
        f.write("\n")
    os.replace(tmp, args.out)
    for t, row in report["tasks"].items():
        print(f"boundary: {t}: " + ", ".join(f"{d:g} deg {c:g} cm" for d, c in zip(row["directions_deg"], row["boundary_cm"])), file=sys.stderr)


if __name__ == "__main__":
    main()
