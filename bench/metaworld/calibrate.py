"""Fits the policies' pixel -> world map (calibration.json) by least squares on simulator frames
labelled with the true object position, and reports its error on held-out seeds.

    python calibrate.py [--fit-seeds 1000:1100] [--test-seeds 2000:2050] [--out calibration.json]

Frames come from episodes of the expert driven by the true object position with action noise
(even seeds) or after random waypoints (odd seeds), every 6th frame of 120, so that the arm
occludes the object and the drawer opens as it will when a policy looks.
"""

from __future__ import annotations

import argparse

import numpy as np

import policies
from files import write_json
from mw import ACTION_SCALE, TASKS, Sim


def frames(task: str, seeds, every: int = 6, resolution: int = 64):
    """Yields (seed, frame index, image, true object position)."""
    for seed in seeds:
        rng = np.random.default_rng([seed, 0xCA1])
        with Sim(task, seed, resolution) as sim:
            image, state = sim.reset()
            waypoint = None
            for t in range(120):
                if t % every == 0:
                    yield seed, t, image, sim.object_pos()
                if seed % 2 and t < 60:
                    if t % 20 == 0:
                        waypoint = rng.uniform([-0.25, 0.45, 0.08], [0.25, 0.85, 0.35])
                    to, gain = waypoint, 10.0
                else:
                    to, gain, _ = policies.expert_target(task, sim.object_pos(), state)
                a = np.clip(np.clip(gain * (to - state[:3]), -1, 1) + 0.3 * rng.standard_normal(3), -1, 1)
                command = np.append(state[:3] + a * ACTION_SCALE, policies.GRIP[task]).astype(np.float32)
                image, state, _ = sim.step(command, render=(t + 1) % every == 0)


def dataset(task: str, seeds):
    x, y, first = [], [], []
    for _, t, image, pos in frames(task, seeds):
        f = policies.features(task, image)
        if f is not None:
            x.append(f)
            y.append(pos)
            first.append(t == 0)
    return np.array(x), np.array(y), np.array(first)


def errors(coef, x, y) -> np.ndarray:
    return np.linalg.norm(x @ coef - y[:, :2], axis=1)


def summary(e: np.ndarray) -> dict:
    return {"mean_cm": round(float(100 * e.mean()), 2), "p95_cm": round(float(100 * np.percentile(e, 95)), 2), "max_cm": round(float(100 * e.max()), 2), "n": len(e)}


def span(text: str) -> range:
    a, b = text.split(":")
    return range(int(a), int(b))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fit-seeds", type=span, default=span("1000:1100"))
    parser.add_argument("--test-seeds", type=span, default=span("2000:2050"))
    parser.add_argument("--out", default=policies.CALIBRATION)
    args = parser.parse_args()
    out = {}
    for task in TASKS:
        x, y, _ = dataset(task, args.fit_seeds)
        coef, *_ = np.linalg.lstsq(x, y[:, :2], rcond=None)
        tx, ty, first = dataset(task, args.test_seeds)
        e = errors(coef, tx, ty)
        out[task] = {
            "coef": coef.round(6).tolist(),
            # The handle's height is fixed; the button top's unpressed height.
            "z": float(policies.OBJECT_RANGE[task][0][2]),
            "fit_seeds": f"{args.fit_seeds.start}:{args.fit_seeds.stop}",
            "held_out": {"seeds": f"{args.test_seeds.start}:{args.test_seeds.stop}", "all_frames": summary(e), "first_frames": summary(e[first])},
        }
        print(f"{task}: xy error on held-out seeds, all frames {out[task]['held_out']['all_frames']}, first frames {out[task]['held_out']['first_frames']}")
    write_json(args.out, out)


if __name__ == "__main__":
    main()
