"""Policy families that differ in kind from policies.py's expert variants, each with variants whose
true success rates spread, split into development families (iterated on) and test families (kept
locked: evaluated once per change, never used to choose anything).

- `learned` (test): behaviour cloning of policies.py's expert, closed loop, frame and commanded
  state in, a chunk of commands relative to the state out: a nearest-neighbour policy (`bc-nn-<k>`)
  and a small network (`bc-net-<k>`, torch on the CPU) cloned from k demonstrations.
- `scripted` (development): the expert's law (policies.expert_target) run otherwise: a lower gain,
  latency, a per-episode error in the perceived object, a straight approach without the lift.
- `partial` (development): the expert's pull / press going 2 cm past what the simulator counts
  (`over-2cm`), stopping 2 or 5 cm short of it (`short-<d>cm`), or quitting in a share of its
  episodes (`quit-<pct>`: pct% of them stop 2-5 cm short, the others go 2 cm past).
- `wander` (test): a hand wandering between random waypoints near the object, gripper random
  (`wander-<R>cm`), or within 5 cm until step k before doing the task (`wander-then-<k>`).

Every variant exists for both tasks under the same name; no name collides with policies.py's.
`make_policy(task, variant, seed)` builds one (variants.make_policy hands family names here);
`variants(split)` lists them, `family_of(variant)` names a variant's family. This module builds on
policies.py (the expert's law, perception and episode loop) and never imports variants.py.

Demonstrations are the expert's episodes (policies.run of policies.Policy, with frames) on seeds
DEMO_SEED_START + k (500000 + k; no evaluation uses them). The data generator's pool of cloned
policies (POOL, `pool_policy`) learns from seeds POOL_DEMO_SEED_START + k (600000 + k) and other
demo counts: apart from the `learned` family by its demonstrations, not by its method.
Cloned policies are cached in $BWM_POLICY_CACHE (default ~/.cache/bwm-metaworld-policies), keyed
by the bytes of this file, policies.py, mw.py and calibration.json, the task, the kind, the demo
count and seeds and the demos' resolution, and for a network the torch version and the machine
(its training is not bit-reproducible across CPUs); written atomically, shared by parallel
processes. `prepare(tasks, variants, workers)` builds a study's clones before it runs them, and
`clones_digest` names what they are, so a study's cached truth is measured again for other clones.

True success rates (%) as measured in the simulator by `python families.py --episodes 50 --workers
2` on the development machine (measure_truth, policies.run: seeds 100000..100049, horizon 120, chunk 24,
64 x 64 frames; the learned family also with `--resolution 128`; its clones from demos at 128 x
128; the networks' rates move with the machine they were trained on, docs/fidelity.md run 45):

  family     split        variant         drawer  button
  learned    test         bc-nn-1             70      60   (128 x 128:  70  60)
                          bc-nn-4             82      66                84  66
                          bc-nn-16           100      94               100  94
                          bc-net-1            36      60                42  60
                          bc-net-4            70      82                70  78
                          bc-net-16           94     100               100 100
  scripted   development  gain-0.7            88     100
                          lag-6               62     100
                          lag-12               0      70
                          est-2cm             98      96
                          est-6cm             46      52
                          straight             0       0
  partial    development  over-2cm           100     100
                          quit-25             76      76
                          quit-50             50      50
                          quit-75             28      28
                          short-2cm            0       0
                          short-5cm            0       0
  wander     test         wander-2cm           0       0
                          wander-10cm          0      30
                          wander-then-80      98     100
                          wander-then-88      46     100
                          wander-then-96       6     100

A clone of one demonstration already succeeds where the expert's path happens to fit (36-70%):
the learned family spans 36..100%, not down to 0. Stopping short is sharp in the simulator (the
drawer fully open is obj_to_target 0.029, 0.1 cm inside the 0.03 that counts; the button resists
at 0.0245, just outside its 0.024), so the partial family grades its rates by how many of its
episodes stop short, and each stops at least 2 cm away from the boundary on either side: a stop a
few millimetres from it decides the simulator's outcome by a distance no 128 x 128 frame shows
(about a centimetre per pixel there; docs/fidelity.md, run 45).

Imports numpy only; torch is imported to train a network, never to run one.
"""

from __future__ import annotations

import hashlib
import os
import zipfile
from dataclasses import dataclass
from typing import Callable

import numpy as np

import policies
from files import replacing, write_json
from mw import ACTION_SCALE, MOCAP_HIGH, MOCAP_LOW, TASKS, initial_state, next_state, simulator_versions
from policies import GRIP, OBJECT_RANGE, expert_target, perceive

HERE = os.path.dirname(os.path.abspath(__file__))
NOISE = 0.1  # per-step Gaussian action noise, in action units (the expert's)


def believed_object(task: str, image) -> np.ndarray:
    """The perceived object, or the centre of its range when it is not seen."""
    obj = perceive(task, np.asarray(image))
    lo, hi = OBJECT_RANGE[task]
    return (lo + hi) / 2 if obj is None else obj


def bounded(command) -> np.ndarray:
    """A command within the mocap's bounds and the gripper's range."""
    c = np.asarray(command, np.float32)
    return np.append(np.clip(c[:3], MOCAP_LOW, MOCAP_HIGH), np.clip(c[3], -1, 1)).astype(np.float32)


# -- scripted and partial: the expert's law, changed one way ------------------------------------

# How far the commanded hand must go past the object's first perceived position (the drawer: in
# -y from the handle, the button: down from its top) for the simulator to count a success, about
# half the time. Measured (6 seeds, 100000..): the drawer's obj_to_target at rest is 0.2267 m
# minus that distance, to 0.029 (fully open); the button's 0.0426 m minus it, to 0.025 at 0.02 m,
# where it resists and passes 0.024 only near 0.0285 m.
BOUNDARY = {"drawer-open-v3": 0.197, "button-press-topdown-v3": 0.0285}


class Scripted:
    """policies.expert_target on the perceived object and the commanded hand, with `gain` times the
    expert's gains, holding still the first `lag` steps of every chunk, a per-episode Gaussian
    error of `est` m (per axis, x and y) in the perceived object, `straight`: heading straight for
    the final approach point (no lift first), and `stop`: the pull / press ending `stop` m before
    BOUNDARY (negative: past it); with `quit`, that share of the episodes (drawn per episode)
    stops short instead, by a distance uniform in QUIT_SHORT."""

    def __init__(self, task: str, seed: int, gain: float = 1.0, lag: int = 0, est: float = 0.0,
                 straight: bool = False, stop: float | None = None, quit: float = 0.0):
        self.task, self.gain, self.lag, self.est, self.straight = task, gain, lag, est, straight
        self.stop, self.quit = stop, quit
        self.reset(seed)

    def reset(self, seed: int) -> None:
        rng = np.random.default_rng([seed, 0xFA31])
        self.error = np.append(self.est * rng.standard_normal(2), 0.0)
        self.depth = None
        if self.stop is not None:
            stop = rng.uniform(*QUIT_SHORT) if self.quit and rng.random() < self.quit else self.stop
            self.depth = BOUNDARY[self.task] - stop
        self.rng, self.origin = rng, None

    def law(self, obj: np.ndarray, state: np.ndarray):
        to, gain, pulling = expert_target(self.task, obj, state)
        if self.straight and not pulling:
            to = obj + ([0.0, 0.02, -0.08] if self.task == "drawer-open-v3" else [0.0, 0.0, -0.08])
        return to, gain * self.gain, pulling

    def act(self, image, state, n: int) -> np.ndarray:
        task = self.task
        obj = believed_object(task, image) + self.error
        if self.origin is None:
            self.origin = obj
        state = np.asarray(state, np.float32)
        out = np.empty((n, 4), np.float32)
        for i in range(n):
            pulling = False
            if i < self.lag:
                command = state.copy()
            else:
                to, gain, pulling = self.law(obj, state)
                a = np.clip(gain * (to - state[:3]), -1, 1)
                a = np.clip(a + NOISE * self.rng.standard_normal(3), -1, 1)
                command = np.append(state[:3] + a * ACTION_SCALE, GRIP[task]).astype(np.float32)
                if self.depth is not None and task == "drawer-open-v3" and pulling:
                    command[1] = max(command[1], self.origin[1] + 0.02 - self.depth)
                elif self.depth is not None and task != "drawer-open-v3":
                    command[2] = max(command[2], self.origin[2] - self.depth)
            new = next_state(state, command)
            if pulling:
                obj = obj + [0.0, new[1] - state[1], 0.0]
            out[i], state = bounded(command), new
        return out


SCRIPTED = {
    "gain-0.7": dict(gain=0.7),
    "lag-6": dict(lag=6),
    "lag-12": dict(lag=12),
    "est-2cm": dict(est=0.02),
    "est-6cm": dict(est=0.06),
    "straight": dict(straight=True),
}
QUIT_SHORT = (0.02, 0.05)  # how far short of BOUNDARY (m) a quitting episode stops
PARTIAL = {
    "over-2cm": dict(stop=-0.02),
    "quit-25": dict(stop=-0.02, quit=0.25),
    "quit-50": dict(stop=-0.02, quit=0.5),
    "quit-75": dict(stop=-0.02, quit=0.75),
    "short-2cm": dict(stop=0.02),
    "short-5cm": dict(stop=0.05),
}


# -- wander: random waypoints near the object ----------------------------------------------------


class Wander:
    """The expert's approach (policies.expert_target) until the hand is within `radius` + 2 cm of
    the perceived object, then random waypoints within `radius` m of it (uniform in the ball),
    each approached at a random speed with a random gripper command for a random while; with
    `then`, from that step on the expert's task instead."""

    def __init__(self, task: str, seed: int, radius: float, then: int | None = None):
        self.task, self.radius, self.then = task, radius, then
        self.reset(seed)

    def reset(self, seed: int) -> None:
        self.rng, self.frame, self.left, self.near = np.random.default_rng([seed, 0x3A4D]), 0, 0, False
        self.expert = Scripted(self.task, seed)

    def act(self, image, state, n: int) -> np.ndarray:
        rng, obj = self.rng, believed_object(self.task, image)
        state = np.asarray(state, np.float32)
        out = np.empty((n, 4), np.float32)
        for i in range(n):
            if self.then is not None and self.frame >= self.then:
                out[i:] = self.expert.act(image, state, n - i)
                self.frame += n - i
                return out
            self.near = self.near or np.linalg.norm(state[:3] - obj) < self.radius + 0.02
            if not self.near:
                to, gain, _ = expert_target(self.task, obj, state)
                a, grip = np.clip(gain * (to - state[:3]), -1, 1), GRIP[self.task]
            else:
                if self.left <= 0 or np.linalg.norm(self.waypoint - state[:3]) < 0.005:
                    u = rng.standard_normal(3)
                    self.waypoint = obj + self.radius * rng.random() ** (1 / 3) * u / np.linalg.norm(u)
                    self.speed, self.grip, self.left = rng.uniform(0.3, 1.0), rng.uniform(-1, 1), int(rng.integers(8, 33))
                a, grip = np.clip(10 * (self.waypoint - state[:3]), -1, 1) * self.speed, self.grip
                self.left -= 1
            a = np.clip(a + NOISE * rng.standard_normal(3), -1, 1)
            out[i] = bounded(np.append(state[:3] + a * ACTION_SCALE, grip))
            state = next_state(state, out[i])
            self.frame += 1
        return out


WANDER = {
    "wander-2cm": dict(radius=0.02),
    "wander-10cm": dict(radius=0.10),
    "wander-then-80": dict(radius=0.05, then=80),
    "wander-then-88": dict(radius=0.05, then=88),
    "wander-then-96": dict(radius=0.05, then=96),
}


# -- learned: behaviour cloning ------------------------------------------------------------------

SIZE = 16  # frames are area-averaged to SIZE x SIZE, whatever their resolution
CHUNK = 24  # commands per prediction
DEMO_SEED_START = 500000
DEMO_RESOLUTION = 128  # the world model's frames (the recipe's RESOLUTION)
HORIZON = 120
NET_STEPS = 2000  # Adam steps of 256 samples
SOURCES = [os.path.join(HERE, name) for name in ("families.py", "policies.py", "mw.py", "calibration.json")]
TRAINED: list[str] = []  # cache files this process recorded or trained and wrote (tests count them)
_models: dict[str, dict] = {}
_digest: list[str] = []


def _area(m: int, n: int) -> np.ndarray:
    """[m, n]: each of m output pixels the mean of the n input pixels it covers (fractions at edges)."""
    edges = np.arange(m + 1) * (n / m)
    k = np.arange(n)
    return np.clip(np.minimum(edges[1:, None], k + 1) - np.maximum(edges[:-1, None], k), 0, None) * (m / n)


def small(image) -> np.ndarray:
    """The frame area-averaged to SIZE x SIZE x 3, in [0, 1] (float32)."""
    image = np.asarray(image, np.float32) / 255
    h, w = image.shape[:2]
    return np.einsum("ih,hwc,jw->ijc", _area(SIZE, h), image, _area(SIZE, w), optimize=True).astype(np.float32)


def observation(image, state) -> np.ndarray:
    """What a cloned policy sees: the small frame and the commanded state."""
    return np.concatenate([small(image).ravel(), np.asarray(state, np.float32)])


def cache_dir() -> str:
    return os.environ.get("BWM_POLICY_CACHE") or os.path.expanduser("~/.cache/bwm-metaworld-policies")


def source_digest() -> str:
    """The sha256 of SOURCES' bytes and the simulator's versions: what every cloned policy (and so
    generate.py's `learned` episodes) depends on beside its key."""
    if not _digest:
        h = hashlib.sha256()
        for path in SOURCES:
            with open(path, "rb") as f:
                h.update(f.read())
        h.update(repr(sorted(simulator_versions().items())).encode())
        _digest.append(h.hexdigest())
    return _digest[0]


def _cached(name: str, key: tuple, build: Callable[[], dict]) -> dict:
    """The arrays stored under `key` (built, saved atomically and counted in TRAINED when absent)."""
    digest = hashlib.sha256(repr((source_digest(),) + key).encode()).hexdigest()[:16]
    path = os.path.join(cache_dir(), f"{name}-{digest}.npz")
    if path in _models:
        return _models[path]
    try:
        with np.load(path) as f:
            _models[path] = dict(f)
        return _models[path]
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        pass
    arrays = build()
    os.makedirs(cache_dir(), exist_ok=True)
    with replacing(path, "wb") as f:
        np.savez(f, **arrays)
    TRAINED.append(path)
    _models[path] = arrays
    return arrays


def demo_arrays(task: str, frames, commands) -> dict:
    """A demonstration as a cloned policy learns from it: `commands` [T, 4] issued from the task's
    initial state, `frames` the T + 1 (or T) frames shown before each of them (and after the last):
    observations x [len(frames), D], and per command the next CHUNK commands relative to the state
    then (action units, x 1 cm) with their gripper commands: targets y [T, CHUNK, 4]. A world
    model's episode (frames drawn from the commanded states) is read the same way as the
    simulator's."""
    commands = np.asarray(commands, np.float32).reshape(-1, 4)
    states = [initial_state(task)]
    for c in commands:
        states.append(next_state(states[-1], c))
    states = np.stack(states)
    hold = np.append(states[-1, :3], commands[-1, 3])
    padded = np.concatenate([commands, np.repeat(hold[None], CHUNK, 0)])
    t = np.arange(len(commands))[:, None] + np.arange(CHUNK)
    targets = padded[t].copy()
    targets[..., :3] = (targets[..., :3] - states[:-1, None, :3]) / ACTION_SCALE
    if len(frames) not in (len(commands), len(commands) + 1):
        raise ValueError(f"{len(frames)} frames for {len(commands)} commands (expected one before each command, and one after the last or not)")
    x = np.stack([observation(f, s) for f, s in zip(frames, states)])
    return {"x": x.astype(np.float32), "y": targets.astype(np.float32)}


def demo(task: str, seed: int, resolution: int) -> dict:
    """The expert's episode on `seed` in the simulator, as `demo_arrays` (x [T+1, D], y [T, CHUNK, 4])."""

    def record() -> dict:
        e = policies.run(policies.Policy(task, "expert", seed), task, seed, HORIZON, CHUNK, resolution, record=True)
        return demo_arrays(task, e.frames, e.commands)

    return _cached(f"demo-{task}-{seed}-{resolution}", ("demo", task, seed, resolution, HORIZON, CHUNK, SIZE), record)


def normalizer(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each input's mean, and a scale: the state's own standard deviations, one for every pixel
    (their spread over all pixels): a pixel nearly constant over the demos is not blown up, so
    frames rendered at another resolution or drawn by a world model stay near the demos'."""
    xm, xs = x.mean(0), x.std(0)
    xs[:-4] = np.sqrt(np.mean(xs[:-4] ** 2))
    return xm, np.maximum(xs, 1e-3)


def train_net(x: np.ndarray, y: np.ndarray, steps: int = NET_STEPS, seed: int = 0) -> dict:
    """A two-hidden-layer MLP fitted to standardized inputs and targets [N, CHUNK * 4]
    (deterministic for a seed, one CPU thread): the arrays `Cloned` runs."""
    import torch

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    xm, xs = normalizer(x)
    ym, ys = y.mean(0), np.maximum(y.std(0), 0.05)
    X, Y = torch.tensor((x - xm) / xs), torch.tensor((y - ym) / ys)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 256), torch.nn.ReLU(), torch.nn.Linear(256, 256), torch.nn.ReLU(),
                              torch.nn.Linear(256, y.shape[1]))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, weight_decay=1e-5)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        batch = torch.randint(len(X), (min(256, len(X)),), generator=g)
        loss = torch.nn.functional.mse_loss(net(X[batch]), Y[batch])
        opt.zero_grad()
        loss.backward()
        opt.step()
    layers = [m for m in net if isinstance(m, torch.nn.Linear)]
    weights = {f"w{i}": m.weight.detach().numpy().T.copy() for i, m in enumerate(layers)}
    weights.update({f"b{i}": m.bias.detach().numpy().copy() for i, m in enumerate(layers)})
    return {"xm": xm, "xs": xs, "ym": ym, "ys": ys, **weights}


# The nearest neighbour's distance weighs the 4 state inputs as much as the frame's SIZE*SIZE*3.
STATE_WEIGHT = np.sqrt(SIZE * SIZE * 3 / 4)


def model(task: str, kind: str, demos: int, demo_seed_start: int = DEMO_SEED_START, resolution: int = DEMO_RESOLUTION,
          steps: int = NET_STEPS) -> dict:
    """A cloned policy's arrays: `nn` keeps the demos' observations and targets, `net` an MLP."""
    if kind not in ("nn", "net"):
        raise ValueError(f"unknown kind {kind!r} (known: nn, net)")
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r} (known: {', '.join(TASKS)})")

    def train() -> dict:
        data = [demo(task, demo_seed_start + k, resolution) for k in range(demos)]
        x = np.concatenate([d["x"][:-1] for d in data])
        y = np.concatenate([d["y"] for d in data]).reshape(len(x), -1)
        if kind == "nn":
            xm, xs = normalizer(x)
            return {"xm": xm, "xs": xs, "x": (x - xm) / xs, "y": y}
        return train_net(x, y, steps)

    key = (kind, task, demos, demo_seed_start, resolution, HORIZON, CHUNK, SIZE) + (_trainer() + (steps,) if kind == "net" else ())
    return _cached(f"bc-{kind}-{task}-{demos}x{demo_seed_start}-{resolution}", key, train)


def _trainer() -> tuple:
    """What a network's training depends on beside its data: torch's version and the machine."""
    import platform
    from importlib.metadata import version

    return (version("torch"), platform.machine(), platform.processor())


class Cloned:
    """A cloned policy: from the frame and the commanded state, the next CHUNK commands relative to
    the state (again from the last of them when more are asked for), with the expert's action noise."""

    def __init__(self, task: str, arrays: dict, seed: int):
        self.task, self.m = task, arrays
        self.reset(seed)

    def reset(self, seed: int) -> None:
        self.rng = np.random.default_rng([seed, 0xBC])

    def predict(self, x: np.ndarray) -> np.ndarray:
        m = self.m
        z = (x - m["xm"]) / m["xs"]
        if "x" in m:
            d = m["x"] - z
            d[:, -4:] *= STATE_WEIGHT
            y = m["y"][np.argmin(np.einsum("nd,nd->n", d, d))]
        else:
            h = np.maximum(z @ m["w0"] + m["b0"], 0)
            h = np.maximum(h @ m["w1"] + m["b1"], 0)
            y = (h @ m["w2"] + m["b2"]) * m["ys"] + m["ym"]
        return y.reshape(CHUNK, 4).copy()

    def act(self, image, state, n: int) -> np.ndarray:
        frame = small(image).ravel()
        state = np.asarray(state, np.float32)
        out = np.empty((n, 4), np.float32)
        for start in range(0, n, CHUNK):
            y = self.predict(np.concatenate([frame, state]))[: n - start]
            y[:, :3] += NOISE * self.rng.standard_normal((len(y), 3))
            for k, (offset, g) in enumerate(zip(y[:, :3], y[:, 3])):
                out[start + k] = bounded(np.append(state[:3] + offset * ACTION_SCALE, g))
            for c in out[start: start + len(y)]:
                state = next_state(state, c)
        return out


def learned_policy(task: str, kind: str, demos: int, demo_seed_start: int = DEMO_SEED_START, seed: int = 0,
                   resolution: int = DEMO_RESOLUTION, steps: int = NET_STEPS) -> Cloned:
    """A policy cloned (`nn` or `net`, the latter trained `steps` steps) from the expert's
    episodes on seeds demo_seed_start + k, k < demos, recorded at `resolution`; trained once,
    then loaded from the cache."""
    return Cloned(task, model(task, kind, demos, demo_seed_start, resolution, steps), seed)


LEARNED = {f"bc-{kind}-{k}": dict(kind=kind, demos=k) for kind in ("nn", "net") for k in (1, 4, 16)}

# The data generator's pool of cloned policies (generate.py's `learned` behaviour): demonstrations
# on seeds of their own and demo counts no evaluation variant uses, recorded at the dataset's
# resolution, so that no evaluation family's policy is in the training data.
POOL_DEMO_SEED_START = 600000
POOL = (("nn", 2), ("nn", 8), ("net", 2), ("net", 8))


def pool_policy(task: str, kind: str, demos: int, seed: int, resolution: int) -> Cloned:
    """One of POOL's policies for one episode (`seed`), its demonstrations at `resolution`."""
    if (kind, demos) not in POOL:
        raise ValueError(f"({kind!r}, {demos}) is not in the pool {POOL}")
    return learned_policy(task, kind, demos, POOL_DEMO_SEED_START, seed, resolution)


def _pool_demo(job) -> None:
    demo(*job)


def _pool_model(job) -> None:
    task, kind, demos, resolution = job
    model(task, kind, demos, POOL_DEMO_SEED_START, resolution)


def prepare_pool(tasks, resolution: int, workers: int) -> None:
    """POOL's policies for `tasks` trained (or found in the cache) in `workers` processes: their
    demonstrations first, then the policies, so that the generator's workers only load them."""
    import multiprocessing

    most = max(demos for _, demos in POOL)
    jobs = [[(t, POOL_DEMO_SEED_START + k, resolution) for t in tasks for k in range(most)],
            [(t, kind, demos, resolution) for t in tasks for kind, demos in POOL]]
    with multiprocessing.get_context("spawn").Pool(max(1, min(workers, len(jobs[1])))) as pool:
        pool.map(_pool_demo, jobs[0])
        pool.map(_pool_model, jobs[1])


# -- the registry --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Family:
    split: str  # "development" or "test"
    params: dict  # variant name -> the keyword arguments of `make`
    make: Callable  # (task, seed, **params) -> a policy

    @property
    def variants(self) -> dict[str, list[str]]:
        return {task: list(self.params) for task in TASKS}


FAMILIES = {
    "learned": Family("test", LEARNED, lambda task, seed, kind, demos: learned_policy(task, kind, demos, seed=seed)),
    "scripted": Family("development", SCRIPTED, Scripted),
    "partial": Family("development", PARTIAL, Scripted),
    "wander": Family("test", WANDER, Wander),
}
SPLITS = ("development", "test")


def family_of(variant: str) -> str | None:
    """The family a variant belongs to, None for none."""
    return next((name for name, f in FAMILIES.items() if variant in f.params), None)


def variants(split: str | None = None, tasks=TASKS) -> list[str]:
    """The families' variants (of one split, or all), every one defined for every task, in order."""
    if split is not None and split not in SPLITS:
        raise ValueError(f"unknown split {split!r} (known: {', '.join(SPLITS)})")
    return [v for f in FAMILIES.values() if split in (None, f.split) for v in f.params
            if all(v in f.variants.get(t, ()) for t in tasks)]


def _prepare_job(job) -> None:
    task, variant = job
    make_policy(task, variant, 0)


def prepare(tasks, variants, workers: int) -> None:
    """The cloned policies among `variants` trained (or found in the cache) for `tasks` in
    `workers` processes, before a study measures and serves them."""
    import multiprocessing

    jobs = [(t, v) for t in tasks for v in variants if family_of(v) == "learned"]
    if jobs:
        with multiprocessing.get_context("spawn").Pool(max(1, min(workers, len(jobs)))) as pool:
            pool.map(_prepare_job, jobs)


def clones_digest(tasks, variants) -> str | None:
    """A digest of the arrays of the cloned policies among `variants` (trained first if absent),
    None when there are none: what a study's truth of them was measured with."""
    learned = [(t, v) for t in tasks for v in variants if family_of(v) == "learned"]
    if not learned:
        return None
    h = hashlib.sha256()
    for t, v in learned:
        p = FAMILIES["learned"].params[v]
        arrays = model(t, p["kind"], p["demos"])
        for name in sorted(arrays):
            h.update(name.encode())
            h.update(np.ascontiguousarray(arrays[name]).tobytes())
    return h.hexdigest()


def check(task: str, variant: str) -> None:
    """Raises ValueError naming the known names unless `variant` is a family's for `task`."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r} (known: {', '.join(TASKS)})")
    name = family_of(variant)
    if name is None or variant not in FAMILIES[name].variants[task]:
        raise ValueError(f"unknown family variant {variant!r} for {task} (known: {', '.join(variants(tasks=[task]))})")


def make_policy(task: str, variant: str, seed: int):
    """A family variant's policy for one episode: act(image, state, n) -> float32[n, 4]."""
    check(task, variant)
    f = FAMILIES[family_of(variant)]
    return f.make(task, seed, **f.params[variant])


def measure_truth(task: str, variant: str, seeds, horizon: int = 120, chunk: int = 24, resolution: int = 64) -> list:
    """Per seed, a family variant's episode in the simulator without its frames (policies.run), as
    variants.measure_truth measures it."""
    return [policies.run(make_policy(task, variant, seed), task, seed, horizon, chunk, resolution) for seed in seeds]


if __name__ == "__main__":
    import argparse
    from multiprocessing import get_context

    parser = argparse.ArgumentParser(description="True success rate of every family variant in the simulator")
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=list(FAMILIES))
    parser.add_argument("--variants", nargs="+", help="only these")
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--seed-start", type=int, default=100000)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--horizon", type=int, default=120)
    parser.add_argument("--chunk", type=int, default=24)
    parser.add_argument("--resolution", type=int, default=64, help="of the simulator's frames")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--json", help="also write the rates here")
    parser.add_argument("--list", choices=("development", "test"),
                        help="print that split's variants, comma-separated, and measure nothing")
    args = parser.parse_args()
    if args.list:
        print(",".join(variants(args.list)))
        raise SystemExit(0)
    known = variants()
    if unknown := [v for v in args.variants or [] if v not in known]:
        parser.error(f"unknown variant(s) {', '.join(unknown)} (known: {', '.join(known)})")
    if args.workers < 1 or args.episodes < 1:
        parser.error("--workers and --episodes must be at least 1")
    seeds = list(range(args.seed_start, args.seed_start + args.episodes))
    jobs = [(task, v) for name in args.families for v in FAMILIES[name].params for task in args.tasks
            if not args.variants or v in args.variants]
    for task, v in jobs:  # train the cloned policies first, one at a time
        make_policy(task, v, 0)
    rates = {}
    with get_context("spawn").Pool(args.workers) as pool:
        runs = [pool.apply_async(measure_truth, (task, v, seeds, args.horizon, args.chunk, args.resolution)) for task, v in jobs]
        for (task, v), run in zip(jobs, runs):
            episodes = run.get()
            rate = rates.setdefault(task, {})[v] = sum(e.first is not None for e in episodes) / len(episodes)
            print(f"{task:26s} {family_of(v):9s} {v:15s} {100 * rate:5.1f}%", flush=True)
    if args.json:
        write_json(args.json, rates)
