"""Where the scripted expert's outcome flips, per task and direction (measured in the simulator by
measure_boundary.py), and the near misses that generate.py draws around it (`--miss-boundary`).

The report (measure_boundary.py): for each direction in the table plane (0 deg = +x, 90 deg =
+y, away from the robot) and each seed (an object placement outside the train and validation
seeds), the expert with its usual action noise steers on the object estimate moved d cm that way,
and d is bisected between 0 (it succeeds) and --max-cm (it fails) until a distance where the
outcome flips is known within --tolerance-cm (the outcome is taken to change once along a
direction). Each bracket [succeeds at lo, fails at hi] is kept; a direction's boundary is the
median of its brackets' midpoints, --max-cm where the expert still succeeds that far off (the
button's +y: the hand's reach ends beyond it).
A world model needs examples on both sides of this boundary in every direction: the drawer's
handle is still caught about 8 cm to the side of it but not 4 cm in front, and near misses drawn
at one distance for every direction put most of them where the outcome is the same on both
sides. `generate.py --miss-boundary FILE` draws each miss in a random direction at FACTOR times
that direction's boundary, never beyond the report's --max-cm, where nothing was measured;
`--miss-factor LO,HI` sets that range (1.1,2 keeps every miss beyond the boundary: failing pulls
just past the contact, without the successes inside it).
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass

import numpy as np

# A miss drawn around the boundary lies at this many times its direction's boundary distance:
# a third inside (the expert still succeeds), two thirds outside up to twice as far, where the
# outcome is settled but the motion is still a near one.
FACTOR = (0.5, 2.0)


def direction(angle: float) -> np.ndarray:
    """The unit vector in the table plane toward `angle` (rad; 0 = +x, pi/2 = +y)."""
    return np.array([np.cos(angle), np.sin(angle), 0.0])


def directions_deg(n: int) -> list[float]:
    """`n` directions evenly spaced from 0 deg."""
    return [k * 360 / n for k in range(n)]


def axis(offset) -> str:
    """Which way an `offset` from the object (an aim, a closest approach) points in the table
    plane: "-y" or "+y" within 45 degrees of that axis, else "x" (either side). For the drawer, -y
    is in front of its handle (where its `wrong` variant aims) and x is beside it (where its
    `blind` hand misses a drawer placed off centre)."""
    x, y = float(offset[0]), float(offset[1])
    if abs(y) > abs(x):
        return "-y" if y < 0 else "+y"
    return "x"


AXES = ("-y", "+y", "x")


def bands(distances_cm, band_cm: float, **counted) -> dict:
    """Episodes by distance band of `band_cm` ("LO-HI" in cm, nearest first, empty bands left out):
    per band {"episodes": n, NAME: how many of them are true in the list NAME, ...} for each
    keyword list of flags, one per distance."""
    out = {}
    for i, d in enumerate(distances_cm):
        k = int(d // band_cm)
        cell = out.setdefault(k, {"episodes": 0, **{name: 0 for name in counted}})
        cell["episodes"] += 1
        for name, flags in counted.items():
            cell[name] += bool(flags[i])
    return {f"{k * band_cm:g}-{(k + 1) * band_cm:g}": out[k] for k in sorted(out)}


@dataclass
class Boundary:
    """Per task, the boundary distance (m) at evenly spaced directions from 0 rad, and the
    farthest distance measured (m)."""

    radii: dict[str, np.ndarray]
    limit: float
    source: str = "boundary"
    factor: tuple[float, float] = FACTOR

    def radius(self, task: str, angle: float) -> float:
        """The boundary distance (m) toward `angle` (rad), linear between measured directions."""
        if task not in self.radii:
            raise ValueError(f"{self.source} has no boundary for {task} (it has {', '.join(self.radii)})")
        r = self.radii[task]
        x = (angle % (2 * math.pi)) / (2 * math.pi / len(r))
        i, w = int(x) % len(r), x - int(x)
        return float((1 - w) * r[i] + w * r[(i + 1) % len(r)])

    def draw(self, task: str, rng: np.random.Generator) -> np.ndarray:
        """A miss offset (m): a random direction, `factor` times its boundary distance, at most the
        farthest distance measured."""
        angle = rng.uniform(0, 2 * np.pi)
        return direction(angle) * min(self.radius(task, angle) * rng.uniform(*self.factor), self.limit)


def _numbers(values) -> bool:
    return isinstance(values, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values)


def load(path: str, tasks: list[str] = ()) -> Boundary:
    """A measure_boundary.py report as a Boundary, every task's distances checked, and each of
    `tasks` in it; ValueError naming `path` otherwise."""
    try:
        with open(path) as f:
            report = json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"cannot read the boundary file {path}: {e}") from None
    rows = report.get("tasks") if isinstance(report, dict) else None
    if not isinstance(rows, dict) or not rows:
        raise ValueError(f"{path} is not a measure_boundary.py report (no \"tasks\")")
    limit = report.get("max_cm")
    if not (_numbers([limit]) and limit > 0):
        raise ValueError(f"{path}: max_cm must be a number > 0, got {limit!r}")
    radii = {}
    for task, row in rows.items():
        cm = row.get("boundary_cm") if isinstance(row, dict) else None
        degrees = row.get("directions_deg") if isinstance(row, dict) else None
        if not (_numbers(cm) and _numbers(degrees)) or len(cm) < 2 or len(cm) != len(degrees):
            raise ValueError(f"{path}: {task} needs boundary_cm and directions_deg, lists of numbers of one length, at least 2")
        if not np.allclose(degrees, directions_deg(len(cm))):
            raise ValueError(f"{path}: {task}'s directions are not evenly spaced from 0 deg")
        if not all(0 < c <= limit for c in cm):
            raise ValueError(f"{path}: {task}'s boundary distances must be > 0 and at most max_cm ({limit:g}) cm, got {cm}")
        radii[task] = np.array(cm, float) / 100
    if missing := [t for t in tasks if t not in radii]:
        raise ValueError(f"{path} has no boundary for {', '.join(missing)} (it has {', '.join(radii)})")
    return Boundary(radii, limit / 100, path)


def factor_range(text: str) -> tuple[float, float]:
    """`--miss-factor LO,HI`: how many times its direction's boundary distance a miss lies, 0 < LO <= HI."""
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes LO,HI (times the boundary distance), got {text!r}") from None
    if not (math.isfinite(hi) and 0.0 < lo <= hi):
        raise argparse.ArgumentTypeError(f"needs 0 < LO <= HI, got {text!r}")
    return lo, hi


def add_factor_argument(parser) -> None:
    parser.add_argument("--miss-factor", type=factor_range, metavar="LO,HI",
                        help=f"with --miss-boundary: each miss LO-HI times its direction's boundary distance (default "
                             f"{FACTOR[0]:g},{FACTOR[1]:g}: a third inside, where the expert still succeeds; 1.1,2 puts all beyond it)")


def from_argument(parser, path: str | None, tasks: list[str], factor: tuple[float, float] | None = None) -> Boundary | None:
    """`--miss-boundary FILE` (and `--miss-factor`) of a command line: the Boundary, None when not
    given; the parser's error (exit 2) when the file does not load or lacks one of `tasks`, or a
    factor comes without a file."""
    if path is None:
        if factor is not None:
            parser.error("--miss-factor needs --miss-boundary")
        return None
    try:
        around = load(path, tasks)
    except ValueError as e:
        parser.error(f"--miss-boundary: {e}")
    if factor is not None:
        around.factor = factor
    return around
