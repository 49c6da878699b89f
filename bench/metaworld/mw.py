"""Meta-World v3 tasks as the world model sees them: one fixed camera, upright frames, and an
absolute action interface.

State and command are [x, y, z, g]: the commanded hand (mocap) position in metres, world frame,
and the gripper command in [-1, 1] (-1 open, +1 closed). An episode starts from the task's
`HAND_INIT` position with g = -1 (the env's reset leaves the gripper actuators at [-1, 1]).
`next_state(state, command)` is exactly the mocap target the simulator then uses, so the state of
every frame is a pure function of the initial state and the commands.

Only numpy is imported at module level: policies import `next_state` where MuJoCo is absent.
"""

from __future__ import annotations

import atexit
import os
import subprocess
import sys

import numpy as np

TASKS = ("drawer-open-v3", "button-press-topdown-v3")
# Meta-World's frame_skip 5 x timestep 2.5 ms: one env step is 12.5 ms.
FPS = 80
CAMERA = "corner4"
ACTION_SCALE = np.float32(0.01)
# hand_low / hand_high of both tasks' envs (the mocap bounds); checked against the env in Sim.
MOCAP_LOW = np.array([-0.5, 0.40, 0.05], np.float32)
MOCAP_HIGH = np.array([0.5, 1.0, 0.5], np.float32)
HAND_INIT = {
    "drawer-open-v3": np.array([0.0, 0.6, 0.2], np.float32),
    "button-press-topdown-v3": np.array([0.0, 0.4, 0.2], np.float32),
}
GRIPPER_INIT = np.float32(-1.0)
# Each task's success rule as Meta-World v3 states it (evaluate_state): success while the object's
# distance to its goal, `obj_to_target` in metres, is at most this. The drawer: the handle's
# distance to where the drawer is fully open (0.19 m at reset, so open at least 16 cm); the button:
# its top's height above the pressed position (about 0.09 m at reset).
SUCCESS_DISTANCE = {"drawer-open-v3": 0.03, "button-press-topdown-v3": 0.024}


def simulator_versions() -> dict:
    """The installed versions of the simulator's packages (None where one is missing): part of
    every cache key of what the simulator measured, so that another Meta-World or MuJoCo measures
    afresh."""
    from importlib.metadata import PackageNotFoundError, version

    def of(name: str) -> str | None:
        try:
            return version(name)
        except PackageNotFoundError:
            return None

    return {name: of(name) for name in ("metaworld", "mujoco")}


def initial_state(task: str) -> np.ndarray:
    return np.append(HAND_INIT[task], GRIPPER_INIT).astype(np.float32)


def delta_action(state, command) -> np.ndarray:
    """The Meta-World action that moves the mocap from `state` towards `command`."""
    state, command = np.asarray(state, np.float32), np.asarray(command, np.float32)
    a = np.empty(4, np.float32)
    a[:3] = np.clip((command[:3] - state[:3]) / ACTION_SCALE, -1, 1)
    a[3] = np.clip(command[3], -1, 1)
    return a


def next_state(state, command) -> np.ndarray:
    """The state after issuing `command` in `state` (float32, as Sim computes it)."""
    state = np.asarray(state, np.float32)
    a = delta_action(state, command)
    xyz = np.clip(state[:3] + a[:3] * ACTION_SCALE, MOCAP_LOW, MOCAP_HIGH)
    return np.append(xyz, a[3]).astype(np.float32)


def select_gl() -> str:
    """MUJOCO_GL if set, else the first of egl and osmesa that can create a context here. Must
    run before mujoco is imported; probes in a subprocess because a backend cannot be switched
    once loaded."""
    if os.environ.get("MUJOCO_GL"):
        return os.environ["MUJOCO_GL"]
    if "mujoco" in sys.modules:
        raise RuntimeError("mujoco was imported before mw.select_gl() chose a GL backend: set MUJOCO_GL, or call select_gl() first")
    probe = "import mujoco; c = mujoco.GLContext(8, 8); c.make_current(); c.free()"
    for backend in ("egl", "osmesa"):
        env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
        if subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True).returncode == 0:
            os.environ.update(MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
            return backend
    raise RuntimeError("no offscreen OpenGL: neither EGL nor OSMesa works (Debian: libegl1 libegl-mesa0 libgl1-mesa-dri, or libosmesa6)")


_pool: dict[tuple[str, int], list] = {}
_built: list = []


def _build(task: str, resolution: int):
    import mujoco
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE

    # The goal-observable class resets its cached observation space (a class built directly
    # clips the goal to 0) and lets a seed fix the placement.
    env = ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE[f"{task}-goal-observable"](seed=0)
    env.max_path_length = 1 << 30
    assert np.allclose(env.mocap_low, MOCAP_LOW) and np.allclose(env.mocap_high, MOCAP_HIGH)
    assert np.allclose(env.hand_init_pos, HAND_INIT[task]) and env.action_scale == ACTION_SCALE
    assert np.array_equal(env._last_rand_vec, placement(env, 0)), "Meta-World no longer places objects as placement() assumes"
    model = env.model
    model.vis.quality.offsamples = 0
    model.vis.quality.shadowsize = 0
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, resolution)
    model.vis.global_.offheight = max(model.vis.global_.offheight, resolution)
    renderer = mujoco.Renderer(model, resolution, resolution)
    for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION, mujoco.mjtRndFlag.mjRND_SKYBOX):
        renderer.scene.flags[flag] = 0
    if not _built:
        # Registered after mujoco's own exit hook so that it runs first: left to __del__, or run
        # after EGL's termination, closing fails noisily.
        atexit.register(_close_all)
    _built.append((env, renderer))
    return env, renderer


def placement(env, seed: int) -> np.ndarray:
    """The object placement Meta-World's goal-observable class draws at construction with `seed`:
    the second draw (its reset() resets the model twice) of numpy's legacy generator."""
    space, rng = env._random_reset_space, np.random.RandomState(seed)
    rng.uniform(space.low, space.high, size=space.low.size)
    return rng.uniform(space.low, space.high, size=space.low.size)


def _close_all() -> None:
    for env, renderer in _built:
        renderer.close()
        env.close()
    _built.clear()
    _pool.clear()


class Sim:
    """One Meta-World task with object/goal placement fixed by `seed`, rendered from `CAMERA` at
    `resolution` x `resolution` without shadows, reflections, skybox or MSAA. Environments are
    pooled per process (building one takes 0.4 s): close() hands it back."""

    def __init__(self, task: str, seed: int, resolution: int = 64):
        if task not in HAND_INIT:
            raise ValueError(f"unknown task {task!r} (known: {', '.join(HAND_INIT)})")
        select_gl()
        import mujoco

        self._mujoco = mujoco
        self.task, self.seed, self.resolution = task, seed, resolution
        free = _pool.setdefault((task, resolution), [])
        self.env, self.renderer = free.pop() if free else _build(task, resolution)
        self.env._last_rand_vec = placement(self.env, seed)
        self.env._freeze_rand_vec = True
        self.env.seed(seed)
        # The mocap goes exactly where next_state says (float32), not where the env's float64 sum would.
        self.env.set_xyz_action = self._set_mocap
        self.state = initial_state(task)
        self.last_action = np.zeros(4, np.float32)

    def _set_mocap(self, _action) -> None:
        self.env.data.mocap_pos[0] = self.state[:3]
        self.env.data.mocap_quat[0] = [1, 0, 1, 0]

    def render(self) -> np.ndarray:
        self.renderer.update_scene(self.env.data, camera=CAMERA)
        # corner4 is rolled 180 degrees: rotate (a vertical flip alone would mirror the scene).
        return np.ascontiguousarray(self.renderer.render()[::-1, ::-1])

    def reset(self):
        self.env.reset()
        # reset() moves the object without forward kinematics: without this the first frame
        # shows the previous placement.
        self._mujoco.mj_forward(self.env.model, self.env.data)
        self.state = initial_state(self.task)
        self.last_action = np.zeros(4, np.float32)
        assert np.array_equal(self.env.data.mocap_pos[0], self.state[:3].astype(np.float64))
        return self.render(), self.state.copy()

    def step(self, command, render: bool = True):
        """Issues the absolute command [x, y, z, g]; returns (image or None when not `render`,
        state, success). `last_action` holds the Meta-World delta action it became."""
        self.last_action = delta_action(self.state, command)
        self.state = next_state(self.state, command)
        _, _, _, _, info = self.env.step(self.last_action)
        return (self.render() if render else None), self.state.copy(), bool(info["success"])

    def obj_to_target(self) -> float:
        """Ground truth: the object's distance to its goal (m), the quantity Meta-World's success
        rule thresholds (SUCCESS_DISTANCE), measured by the env's own evaluate_state."""
        _, info = self.env.evaluate_state(self.env._get_obs(), self.last_action)
        return float(info["obj_to_target"])

    def object_pos(self) -> np.ndarray:
        """Ground truth: the drawer handle / the button top, world frame."""
        return np.array(self.env._get_pos_objects(), np.float64)

    def hand_pos(self) -> np.ndarray:
        """Ground truth: the end effector (it lags the commanded state)."""
        return np.array(self.env.tcp_center, np.float64)

    def close(self) -> None:
        if self.env is not None:
            del self.env.set_xyz_action
            _pool[(self.task, self.resolution)].append((self.env, self.renderer))
            self.env = self.renderer = None

    def __enter__(self):
        return self

    def __exit__(self, *_):
        self.close()
