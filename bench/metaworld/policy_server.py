"""Serves policy variants (variants.py: policies.py's and families.py's) over openpi's websocket
protocol, one port per variant, all from one asyncio process, for `bwm evaluate`.

Protocol (openpi's WebsocketPolicyServer): on connect the server sends msgpack metadata; each
binary msgpack observation {image key: uint8 [H, W, 3], state key: float32 [4], prompt key: str}
is answered with {actions key: float32 [chunk, 4], "server_timing": {...}}: the next `chunk`
absolute commands [x, y, z, g]. A bad observation is answered with a text frame (the error) and
close code 1011, as openpi does on an exception; the server itself keeps running.

One connection is one episode (bwm evaluate reconnects for each). Its task is the served task
named in the prompt (the only one when one is served), and its seed is the task's next episode
seed: --episode-seeds FILE ({task: [seed, ...]}, e.g. the validation episodes' placement seeds
that study.py config writes) or --seed + k for the task's k-th episode, counted by first
observation. bwm evaluate starts a policy's episodes in the config's order and, with several
episodes in flight, sends their first observations in that order too, so a rerun gets the same seeds.

Usage: policy_server.py --variants expert,noisy --tasks drawer-open-v3 --base-port 8100 \
           --chunk 24 --ready ready.json       (--base-port 0: free ports, see the ready file)
The ready file, written once every port listens: {"host", "ports": {variant: port}, "pid", ...}.
"""

from __future__ import annotations

import argparse
import asyncio
import http
import json
import os
import signal
import sys
import threading
import time
import traceback

import numpy as np

from files import write_json
from msgpack_numpy import packb, unpackb

STATE_DIM = 4


class BadObservation(ValueError):
    pass


def task_of(prompt: str, tasks: list[str]) -> str:
    if len(tasks) == 1:
        return tasks[0]
    named = [t for t in tasks if t in prompt]
    if len(named) != 1:
        raise BadObservation(f"prompt {prompt!r} names {len(named)} of the served tasks ({', '.join(tasks)}); it must name one")
    return named[0]


def read_observation(obs, keys: dict) -> tuple[np.ndarray, np.ndarray, str]:
    if not isinstance(obs, dict):
        raise BadObservation(f"the observation is a {type(obs).__name__}, not a map")
    missing = [keys[k] for k in ("image", "state", "prompt") if keys[k] not in obs]
    if missing:
        raise BadObservation(f"observation lacks {', '.join(missing)} (has {', '.join(map(str, obs))})")
    image, state, prompt = obs[keys["image"]], obs[keys["state"]], obs[keys["prompt"]]
    if not (isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3):
        raise BadObservation(f"{keys['image']} must be a uint8 [H, W, 3] array, got {describe(image)}")
    if not (isinstance(state, np.ndarray) and state.shape == (STATE_DIM,) and state.dtype.kind == "f"):
        raise BadObservation(f"{keys['state']} must be a float [{STATE_DIM}] array (hand xyz, gripper), got {describe(state)}")
    if not np.isfinite(state).all():
        raise BadObservation(f"{keys['state']} holds NaN or infinite values: {state.tolist()}")
    if not isinstance(prompt, str):
        raise BadObservation(f"{keys['prompt']} must be a string, got {describe(prompt)}")
    return image, state.astype(np.float32), prompt


def describe(v) -> str:
    return f"{v.dtype} {list(v.shape)}" if isinstance(v, np.ndarray) else type(v).__name__


class EpisodeSeeds:
    def __init__(self, seed: int, per_task: dict[str, list[int]] | None):
        self.seed, self.per_task, self.started = seed, per_task, {}

    def next(self, task: str) -> int:
        k = self.started.get(task, 0)
        self.started[task] = k + 1
        if self.per_task is None:
            return self.seed + k
        seeds = self.per_task.get(task, [])
        if k >= len(seeds):
            raise BadObservation(f"episode {k} of {task}: the episode seeds list only {len(seeds)} for it")
        return seeds[k]


class VariantServer:
    """One variant: a policy per connection."""

    def __init__(self, variant: str, tasks: list[str], chunk: int, seeds: EpisodeSeeds, keys: dict, make_policy, log=print):
        self.variant, self.tasks, self.chunk, self.seeds, self.keys = variant, tasks, chunk, seeds, keys
        self.make_policy, self.log = make_policy, log

    def metadata(self) -> dict:
        return {"policy": self.variant, "tasks": self.tasks, "action_horizon": self.chunk, "action_dim": STATE_DIM,
                "actions": "absolute commands [x, y, z, gripper]"}

    async def handler(self, ws) -> None:
        import websockets

        await ws.send(packb(self.metadata()))
        policy, label, requests = None, "", 0
        try:
            while True:
                message = await ws.recv()
                t0 = time.monotonic()
                if isinstance(message, str):
                    raise BadObservation("expected a binary msgpack observation, got a text frame")
                try:
                    obs = unpackb(message)
                except Exception as e:
                    raise BadObservation(f"the message is not msgpack-numpy: {e}") from None
                image, state, prompt = read_observation(obs, self.keys)
                if policy is None:
                    task = task_of(prompt, self.tasks)
                    seed = self.seeds.next(task)
                    policy, label = self.make_policy(task, self.variant, seed), f"{self.variant} {task} seed {seed}"
                actions = np.asarray(policy.act(image, state, self.chunk), np.float32)
                requests += 1
                ms = (time.monotonic() - t0) * 1000
                await ws.send(packb({self.keys["actions"]: actions, "server_timing": {"infer_ms": ms}}))
        except websockets.ConnectionClosed:
            if policy is not None:
                self.log(f"{label}: {requests} requests")
        except Exception as e:
            text = f"{type(e).__name__}: {e}" if isinstance(e, BadObservation) else traceback.format_exc()
            self.log(f"{label or self.variant}: error: {text.strip().splitlines()[-1]}")
            try:
                await ws.send(text)
                await ws.close(code=1011, reason="policy error, see the previous frame")
            except websockets.ConnectionClosed:
                pass


def health_check(connection, request):
    if request.path == "/healthz":
        return connection.respond(http.HTTPStatus.OK, "OK\n")
    return None


async def serve(servers: list[VariantServer], host: str, base_port: int, ready: str | None, lifetime: float | None) -> None:
    import websockets.asyncio.server

    running, ports = [], {}
    for i, s in enumerate(servers):
        port = base_port + i if base_port else 0
        try:
            ws = await websockets.asyncio.server.serve(s.handler, host, port, compression=None, max_size=None,
                                                       process_request=health_check)
        except OSError as e:
            raise SystemExit(f"policy_server: cannot listen on {host}:{port} for {s.variant}: {e.strerror}")
        running.append(ws)
        ports[s.variant] = ws.sockets[0].getsockname()[1]
    for variant, port in ports.items():
        print(f"policy_server: {variant} on ws://{host}:{port}", flush=True)
    if ready:
        info = {"host": host, "ports": ports, "pid": os.getpid(), "tasks": servers[0].tasks, "chunk": servers[0].chunk}
        write_json(ready, info, indent=None)
    loop = asyncio.get_running_loop()
    stop = loop.create_future()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, lambda: stop.done() or stop.set_result(None))
    try:
        await asyncio.wait_for(stop, lifetime)
    except asyncio.TimeoutError:
        print(f"policy_server: lifetime of {lifetime:.0f} s reached", flush=True)
    for ws in running:
        ws.close()
        await ws.wait_closed()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description="policy variants (policies.py's and families.py's) over openpi's websocket "
                                             "protocol, one port each")
    ap.add_argument("--variants", help="comma-separated (default: every variant of policies.py the tasks share)")
    ap.add_argument("--tasks", help="comma-separated Meta-World tasks (default: all of policies.VARIANTS)")
    ap.add_argument("--task", dest="tasks", help="same as --tasks")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--base-port", type=int, default=8100, help="variant i listens on base + i; 0 picks free ports")
    ap.add_argument("--chunk", type=int, default=24, help="actions per reply (the world model's chunk K)")
    ap.add_argument("--seed", type=int, default=0, help="episode k of a task uses seed + k")
    ap.add_argument("--episode-seeds", help="JSON {task: [seed of episode 0, 1, ...]} instead of --seed")
    ap.add_argument("--image-key", default="observation/image")
    ap.add_argument("--state-key", default="observation/state")
    ap.add_argument("--prompt-key", default="prompt")
    ap.add_argument("--actions-key", default="actions")
    ap.add_argument("--ready", help="JSON file written once every port listens")
    ap.add_argument("--lifetime", type=float, help="exit after this many seconds")
    a = ap.parse_args(argv)
    from policies import VARIANTS
    from variants import check_variants, make_policy

    tasks = a.tasks.split(",") if a.tasks else list(VARIANTS)
    for t in tasks:
        if t not in VARIANTS:
            ap.error(f"unknown task {t!r} (known: {', '.join(VARIANTS)})")
    shared = [v for v in VARIANTS[tasks[0]] if all(v in VARIANTS[t] for t in tasks)]
    variants = a.variants.split(",") if a.variants else shared
    problem = check_variants(tasks, variants)
    if problem:
        ap.error(f"{problem} (shared named variants: {', '.join(shared)})")
    if a.chunk < 1:
        ap.error("--chunk must be at least 1")
    per_task = None
    if a.episode_seeds:
        with open(a.episode_seeds) as f:
            per_task = json.load(f)
    keys = {"image": a.image_key, "state": a.state_key, "prompt": a.prompt_key, "actions": a.actions_key}
    servers = [VariantServer(v, tasks, a.chunk, EpisodeSeeds(a.seed, per_task), keys, make_policy,
                             lambda m: print(f"policy_server: {m}", flush=True)) for v in variants]
    asyncio.run(serve(servers, a.host, a.base_port, a.ready, a.lifetime))


if __name__ == "__main__":
    sys.exit(main())
