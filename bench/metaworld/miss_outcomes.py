"""How the generator's near misses end in the simulator, by how far off they steer.

    python miss_outcomes.py --tasks drawer-open-v3,button-press-topdown-v3 --episodes 400 \\
        --miss-cm 2,12 --miss-cm 3,9

For the training seeds 0..episodes-1 (the recipe's train split), every episode that generate.py
would degrade into a `miss` (the expert steering on an object estimate off by a random distance in
a random direction) is simulated with that distance drawn from each --miss-cm range, and its
outcome counted by distance band, over all directions and per axis (`by_axis`: within 45 degrees
of -y or of +y, else beside the object along x; for the drawer, in front of its handle, behind it,
beside it). The bands where outcomes flip are where a world model needs
examples on both sides of the contact; a range that puts most misses far past them adds failures
it already draws, one inside them adds successes. With --miss-boundary FILE, the misses are
drawn as `generate.py --miss-boundary FILE` draws them (around where the outcome flips in their
direction, measure_boundary.py) and counted beside the ranges. With --miss-weight W and
--decoy-weight W, the data's draws are those of generate.py with the same weights; with a decoy
weight above 0 the `decoy` episodes (the expert aiming at a fresh placement from the task's
range) are counted the same way, by how far from the object they aim. With --observe-every
LOW,HIGH the expert looks at the object only that often, as `generate.py --observe-every` (the
recipe's data: 24,48) has it.
Prints one JSON object (and writes it to --out).
Only the episodes' draws and the simulator are used: nothing is rendered but each reset's frame.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

import boundary
import generate
from mw import TASKS, Sim


def outcomes(task: str, episodes: int, miss: tuple[float, float] | boundary.Boundary, frames: int, degraded: float, spread: str,
             decoy_weight: float = 0.0, mode: str = "miss", miss_weight: float = generate.DEGRADED_MODES["miss"],
             observe_every: tuple[int, int] = (1, 1)) -> list[tuple[float, bool, str]]:
    """(distance in cm, succeeded, axis) of every `mode` episode among seeds 0..episodes-1, the
    misses drawn `miss` (m) off or around its boundary; the distance is how far from the object
    the episode's expert aims, the axis which way (`boundary.axis`)."""
    out = []
    for seed in range(episodes):
        behaviour = generate.Behaviour(task, generate.episode_rng(task, seed), frames, degraded, spread, miss, decoy_weight, miss_weight,
                                      observe_every)
        if behaviour.mode != mode:
            continue
        with Sim(task, seed, 32) as sim:
            success = generate.simulate(behaviour, sim, frames, render=False)[4]
        out.append((float(np.linalg.norm(behaviour.offset[:2])) * 100, any(success), boundary.axis(behaviour.offset)))
    return out


def by_band(results: list[tuple[float, bool, str]], band: float) -> dict:
    return boundary.bands([d for d, _, _ in results], band, succeeded=[s for _, s, _ in results])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", default=",".join(TASKS))
    parser.add_argument("--episodes", type=int, default=400, help="training seeds 0..episodes-1 per task")
    parser.add_argument("--miss-cm", type=generate.miss_range, action="append", help="LOW,HIGH (cm); repeat to compare (default 2,12)")
    parser.add_argument("--miss-boundary", metavar="FILE", help="also count misses drawn around this boundary (generate.py --miss-boundary)")
    boundary.add_factor_argument(parser)
    parser.add_argument("--miss-weight", type=generate.weight, default=float(generate.DEGRADED_MODES["miss"]),
                        help="the data's `miss` weight (generate.py --miss-weight)")
    parser.add_argument("--decoy-weight", type=generate.weight, default=0.0, help="the data's `decoy` weight (generate.py --decoy-weight); above 0 "
                        "the decoy episodes are counted too")
    parser.add_argument("--observe-every", type=generate.interval, default=(1, 1), metavar="LOW,HIGH",
                        help="frames between the expert's looks at the object (generate.py --observe-every; default every frame)")
    parser.add_argument("--band-cm", type=float, default=2.0, help="width of the distance bands")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--degraded-fraction", type=float, default=0.4)
    parser.add_argument("--spread", choices=["narrow", "wide"], default="narrow")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args(argv)
    tasks = args.tasks.split(",")
    if unknown := [t for t in tasks if t not in TASKS]:
        parser.error(f"unknown task(s) {', '.join(unknown)} (known: {', '.join(TASKS)})")
    if args.episodes < 1 or args.frames < 2 or args.band_cm <= 0:
        parser.error("--episodes must be at least 1, --frames at least 2, --band-cm positive")
    around = boundary.from_argument(parser, args.miss_boundary, tasks, args.miss_factor)
    report = {"episodes": args.episodes, "frames": args.frames, "degraded_fraction": args.degraded_fraction, "spread": args.spread,
              "miss_weight": args.miss_weight, "decoy_weight": args.decoy_weight, "observe_every": list(args.observe_every), "tasks": {}}
    for task in tasks:
        # (name in the report, mode, how misses are drawn)
        counted = [(f"{round(lo * 100, 6):g},{round(hi * 100, 6):g}", "miss", (lo, hi)) for lo, hi in args.miss_cm or [(0.02, 0.12)]]
        if around:
            counted.append(("boundary", "miss", around))
        if args.decoy_weight > 0:
            counted.append(("decoy", "decoy", counted[0][2]))
        for name, mode, miss in counted:
            results = outcomes(task, args.episodes, miss, args.frames, args.degraded_fraction, args.spread, args.decoy_weight, mode, args.miss_weight,
                               args.observe_every)
            row = {f"{mode}_episodes": len(results), "succeeded": sum(s for _, s, _ in results), "by_cm": by_band(results, args.band_cm),
                   "by_axis": {}}
            for way in boundary.AXES:
                these = [r for r in results if r[2] == way]
                if these:
                    row["by_axis"][way] = {"episodes": len(these), "succeeded": sum(s for _, s, _ in these), "by_cm": by_band(these, args.band_cm)}
            report["tasks"].setdefault(task, {})[name] = row
            label = {"decoy": "decoy", "boundary": "--miss-boundary"}.get(name, f"--miss-cm {name}")
            print(f"miss_outcomes: {task} {label}: {row['succeeded']} of {len(results)} {mode} episodes succeed", file=sys.stderr, flush=True)
    text = json.dumps(report, indent=1)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
