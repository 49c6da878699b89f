"""Scripted policies that see only what a world-model loop can give them: the current frame and
the commanded state [x, y, z, g]. They find the object in the frame by colour (the drawer's green
box, the button's yellow box) through a fitted pixel -> world map (calibration.json, refit with
calibrate.py), then follow Meta-World's scripted experts (SawyerDrawerOpenV3Policy,
SawyerButtonPressTopdownV3Policy) in terms of the estimated object and the commanded hand,
integrating their own commands with `next_state` over the chunk they return.

Variants degrade the expert in one way each, with per-episode parameters drawn from the policy's
seed, so their true success rates spread (docs/fidelity.md has them). Beside the named ones,
`wrong-<d>cm` is the expert with every target moved d cm along the task's `wrong` offset: a
graded `wrong` whose success falls with d, for probing whether a world model's contact follows a
shifted command.

`run` is the episode loop the world-model evaluator mirrors, for any policy object (`act(image,
state, n)`), and `replay` issues a fixed command sequence. This module knows only its own
variants: variants.py makes, checks and runs every variant by name, these and the policy families
of families.py (which builds on this module: its expert's law, perception and loop). Imports
numpy only.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, replace

import numpy as np

from mw import ACTION_SCALE, TASKS, next_state

CALIBRATION = os.path.join(os.path.dirname(os.path.abspath(__file__)), "calibration.json")
# The object's range over placements (drawer handle / button top at reset), and where a blind
# policy assumes it.
OBJECT_RANGE = {
    "drawer-open-v3": (np.array([-0.1, 0.73, 0.09]), np.array([0.1, 0.73, 0.09])),
    "button-press-topdown-v3": (np.array([-0.1, 0.8, 0.3085]), np.array([0.1, 0.9, 0.3085])),
}


def object_mask(task: str, image: np.ndarray) -> np.ndarray:
    """Pixels of the drawer's light-green box (not the pure-green goal marker) / the button's yellow box."""
    r, g, b = (image[..., i].astype(np.int16) for i in range(3))
    if task == "drawer-open-v3":
        return (g > r + 30) & (g > b + 30) & (r > 40)
    return (r > 100) & (g > r // 2) & (b < g // 3)


def features(task: str, image: np.ndarray) -> np.ndarray | None:
    """Mask centroid and extent in [0, 1] image coordinates, as regression inputs; None when the
    object is not visible."""
    mask = object_mask(task, image)
    if mask.sum() < 3:
        return None
    h, w = mask.shape
    v, u = np.nonzero(mask)
    u, v = (u + 0.5) / w, (v + 0.5) / h
    return np.array([1.0, u.mean(), v.mean(), u.min(), u.max(), v.min(), v.max(), len(u) / (h * w)])


_calibration: dict | None = None


def calibration() -> dict:
    global _calibration
    if _calibration is None:
        with open(CALIBRATION) as f:
            _calibration = json.load(f)
    return _calibration


def perceive(task: str, image: np.ndarray) -> np.ndarray | None:
    """The object's estimated world position (drawer handle / button top), or None if unseen."""
    f = features(task, image)
    if f is None:
        return None
    c = calibration()[task]
    xy = f @ np.array(c["coef"])
    return np.array([xy[0], xy[1], c["z"]])


@dataclass(frozen=True)
class Params:
    """How a variant departs from the expert. Ranges are per-episode draws (uniform)."""

    noise: float = 0.0  # Gaussian action noise, in action units (x 1 cm)
    bias: tuple = (0.0, 0.0)  # perception offset radius range, m, random direction in xy
    speed: tuple = (1.0, 1.0)  # cap on |action| per axis
    delay: tuple = (0, 0)  # frames spent holding still before starting
    pause: float = 0.0  # probability per frame of starting a 6-frame pause
    blind: bool = False  # ignores the image: object at the centre of its range
    target: tuple = (0.0, 0.0, 0.0)  # constant offset of every target (a wrong goal)
    grip: float | None = None  # gripper command instead of the expert's


EXPERT = Params(noise=0.1)
VARIANT_PARAMS = {
    "drawer-open-v3": {
        "expert": EXPERT,
        "blind": replace(EXPERT, blind=True),
        "noisy": replace(EXPERT, noise=0.6),
        "biased": replace(EXPERT, bias=(0.0, 0.10)),
        "slow": replace(EXPERT, speed=(0.4, 1.0)),
        "late": replace(EXPERT, delay=(0, 80)),
        "hesitant": replace(EXPERT, pause=0.1),
        "wrong": replace(EXPERT, target=(0.0, -0.05, 0.0)),
    },
    "button-press-topdown-v3": {
        "expert": EXPERT,
        "biased": replace(EXPERT, bias=(0.0, 0.08)),
        "late": replace(EXPERT, delay=(0, 110)),
        "slow": replace(EXPERT, speed=(0.2, 0.7)),
        "blind": replace(EXPERT, blind=True),
        "noisy": replace(EXPERT, noise=1.8),
        "hesitant": replace(EXPERT, pause=0.2),
        "wrong": replace(EXPERT, target=(0.0, 0.0, 0.15)),
    },
}
VARIANTS: dict[str, list[str]] = {task: list(v) for task, v in VARIANT_PARAMS.items()}
GRADED = re.compile(r"wrong-(\d+(?:\.\d+)?)cm")


def known(task: str) -> list[str]:
    """This module's variant names for `task`, the graded `wrong` as its pattern."""
    return VARIANTS[task] + ["wrong-<d>cm"]


def variant_params(task: str, variant: str) -> Params:
    """A named variant's parameters, or those of `wrong-<d>cm` (see the module's docstring)."""
    if task not in VARIANT_PARAMS:
        raise ValueError(f"unknown task {task!r} (known: {', '.join(VARIANT_PARAMS)})")
    if variant in VARIANT_PARAMS[task]:
        return VARIANT_PARAMS[task][variant]
    m = GRADED.fullmatch(variant)
    if not m:
        raise ValueError(f"unknown variant {variant!r} for {task} (known: {', '.join(known(task))})")
    direction = np.array(VARIANT_PARAMS[task]["wrong"].target)
    offset = direction / np.linalg.norm(direction) * float(m[1]) / 100
    return replace(EXPERT, target=tuple(float(x) for x in offset))


def expert_target(task: str, obj: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, float, bool]:
    """Meta-World's scripted expert for one step, in terms of the object estimate and the
    commanded hand: (where to go, gain, whether the hand pulls the drawer handle).

    Meta-World's experts steer the measured hand, which lags the mocap; steering the commanded
    hand instead, the pull and the press aim past the object (the mocap must lead the hand to push
    it) and the pull lasts while the hand is low and in front of the handle (it leads the handle)."""
    if task == "drawer-open-v3":
        handle = obj + [0.0, 0.02, -0.02]
        low = state[2] - handle[2] < 0.0
        if low and abs(state[0] - handle[0]) < 0.04 and -0.15 < state[1] - handle[1] < 0.03:
            return np.array([handle[0], state[1] - 0.1, handle[2] - 0.02]), 50.0, True
        if np.linalg.norm(state[:2] - handle[:2]) > 0.06:
            return handle + [0.0, 0.0, 0.3], 4.0, False
        return handle + [0.0, 0.0, -0.06], 4.0, False
    if np.linalg.norm(state[:2] - obj[:2]) > 0.04:
        return obj + [0.0, 0.0, 0.1], 25.0, False
    return obj + [0.0, 0.0, -0.08], 25.0, False


GRIP = {"drawer-open-v3": -1.0, "button-press-topdown-v3": 1.0}


class Policy:
    """One of this module's variants for one episode: act(image, state, n) -> float32[n, 4]."""

    def __init__(self, task: str, variant: str, seed: int):
        self.task, self.variant, self.p = task, variant, variant_params(task, variant)
        self.reset(seed)

    def reset(self, seed: int) -> None:
        """A new episode: per-episode draws and the noise stream follow `seed`."""
        p, rng = self.p, np.random.default_rng([seed, 0x5EED])
        angle = rng.uniform(0, 2 * np.pi)
        self.bias = rng.uniform(*p.bias) * np.array([np.cos(angle), np.sin(angle), 0.0])
        self.speed = rng.uniform(*p.speed)
        self.delay = int(rng.integers(p.delay[0], p.delay[1] + 1))
        self.rng, self.frame, self.paused = rng, 0, 0

    def act(self, image: np.ndarray, state: np.ndarray, n: int) -> np.ndarray:
        """The next n absolute commands [x, y, z, g] (float32[n, 4])."""
        p, task = self.p, self.task
        lo, hi = OBJECT_RANGE[task]
        obj = None if p.blind else perceive(task, np.asarray(image))
        obj = ((lo + hi) / 2 if obj is None else obj) + self.bias + p.target
        state = np.asarray(state, np.float32)
        grip = GRIP[task] if p.grip is None else p.grip
        out = np.empty((n, 4), np.float32)
        for i in range(n):
            if self.frame >= self.delay and not self.paused and p.pause and self.rng.random() < p.pause:
                self.paused = 6
            waiting = self.frame < self.delay or self.paused > 0
            if waiting:
                command, pulling = state.copy(), False
                self.paused = max(self.paused - 1, 0) if self.frame >= self.delay else 0
            else:
                to, gain, pulling = expert_target(task, obj, state)
                a = np.clip(gain * (to - state[:3]), -1, 1) * self.speed
                a = np.clip(a + p.noise * self.rng.standard_normal(3), -1, 1)
                command = np.append(state[:3] + a * ACTION_SCALE, grip).astype(np.float32)
            new = next_state(state, command)
            if pulling:
                # The handle follows the hand that hooks it.
                obj = obj + [0.0, new[1] - state[1], 0.0]
            out[i], state = command, new
            self.frame += 1
        return out


@dataclass
class Episode:
    """One simulator episode: the step (1-based) at which the success flag was first raised (None:
    not within the horizon), the closest the hand came to the object before then (cm; the end
    effector to the drawer handle / the button top, over every step), the commands issued
    (float32 [T, 4]) and with `record` every frame from x0 on (uint8 [T + 1, H, W, 3])."""

    first: int | None
    approach_cm: float
    commands: np.ndarray
    frames: np.ndarray | None = None
    # The hand's offset from the object at that closest approach (cm, world x, y, z).
    nearest_cm: np.ndarray | None = None


class _Outcome:
    """The first success step and the closest approach before it, step by step."""

    def __init__(self, sim):
        self.sim, self.t, self.first, self.commands = sim, 0, None, []
        self.nearest = self._offset()
        self.approach = float(np.linalg.norm(self.nearest))

    def _offset(self) -> np.ndarray:
        return self.sim.hand_pos() - self.sim.object_pos()

    def step(self, command, render: bool):
        image, state, done = self.sim.step(command, render=render)
        self.t += 1
        self.commands.append(np.asarray(command, np.float32))
        if self.first is None:
            offset = self._offset()
            distance = float(np.linalg.norm(offset))
            if distance < self.approach:
                self.nearest, self.approach = offset, distance
            if done:
                self.first = self.t
        return image, state, done

    def episode(self, frames=None) -> Episode:
        commands = np.stack(self.commands) if self.commands else np.zeros((0, 4), np.float32)
        return Episode(self.first, 100 * self.approach, commands, None if frames is None else np.stack(frames), 100 * self.nearest)


def run(policy, task: str, seed: int, horizon: int = 120, chunk: int = 24, resolution: int = 64,
        record: bool = False) -> Episode:
    """One episode of `policy` (made for this episode: act(image, state, n) -> float32[n, 4]) in
    the simulator from the placement of `seed`, as the world-model evaluator runs it (a frame every
    `chunk` steps, `chunk` commands back). Without `record` it stops at the first success; with it
    the episode runs the whole horizon and keeps every frame."""
    from mw import Sim

    with Sim(task, seed, resolution) as sim:
        image, state = sim.reset()
        frames = [image] if record else None
        outcome = _Outcome(sim)
        while outcome.t < horizon and (record or outcome.first is None):
            commands = policy.act(image, state, min(chunk, horizon - outcome.t))
            for i, command in enumerate(commands):
                image, state, done = outcome.step(command, render=record or i == len(commands) - 1)
                if record:
                    frames.append(image)
                elif done:
                    break
        return outcome.episode(frames)


def replay(task: str, seed: int, commands, resolution: int = 64, record: bool = False) -> Episode:
    """A fixed sequence of commands (a world-model episode's actions) issued open loop in the
    simulator from the placement of `seed`, up to its first success; with `record`, every command
    and every frame from x0 on."""
    from mw import Sim

    with Sim(task, seed, resolution) as sim:
        image, _ = sim.reset()
        frames = [image] if record else None
        outcome = _Outcome(sim)
        for command in np.asarray(commands, np.float32).reshape(-1, 4):
            image, _, done = outcome.step(command, render=record)
            if record:
                frames.append(image)
            elif done:
                break
        return outcome.episode(frames)


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="True success rate of each of policies.py's own variants in the simulator "
                                                 "(families.py measures the families')")
    parser.add_argument("--tasks", nargs="+", default=list(TASKS))
    parser.add_argument("--seed-start", type=int, default=100000)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--horizon", type=int, default=120)
    parser.add_argument("--chunk", type=int, default=24)
    parser.add_argument("--json", help="also write the rates here")
    args = parser.parse_args()
    seeds = range(args.seed_start, args.seed_start + args.episodes)
    rates = {}
    for task in args.tasks:
        for variant in VARIANTS[task]:
            episodes = [run(Policy(task, variant, seed), task, seed, args.horizon, args.chunk) for seed in seeds]
            rates.setdefault(task, {})[variant] = sum(e.first is not None for e in episodes) / len(episodes)
            print(f"{task:26s} {variant:10s} {100 * rates[task][variant]:5.1f}%", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rates, f, indent=1)
