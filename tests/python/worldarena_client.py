"""A client of `bwm serve`'s WorldArena 2.0 environment API, written from that API's documentation
(WorldArena2/WorldArena-2.0, RL_env_benchmark/README.md, and RLinf's client of its HTTP world-model
env, `_WanHttpClient` in rlinf/envs/world_model/world_model_wan_http_env.py): GET /health, POST
/reset, POST /chunk_step, observations under main_images / wrist_images / states /
task_descriptions, the reward computed here, by the caller. The bodies are msgpack maps with
openpi's msgpack-numpy arrays where that server pickles them (docs/serve.md says why).

  worldarena_client.py episode URL N CHUNKS D   N environments from random 32x32 first frames and
                                                states, CHUNKS chunks of 4 raw actions each, twice
                                                from the same seed; prints what it saw as JSON
"""

import json
import sys
import urllib.error
import urllib.request

import msgpack
import numpy as np


def pack_array(obj):
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    return obj


def unpack_array(obj):
    if b"__ndarray__" in obj:
        return np.ndarray(buffer=obj[b"data"], dtype=np.dtype(obj[b"dtype"]), shape=obj[b"shape"])
    return obj


class WorldArenaHttpClient:
    """As RLinf's _WanHttpClient: one POST per call, the reply decoded; HTTP errors raised."""

    def __init__(self, server_url, timeout=600.0):
        self.server_url = server_url.rstrip("/")
        self.timeout = timeout

    def health(self):
        with urllib.request.urlopen(self.server_url + "/health", timeout=self.timeout) as resp:
            return json.loads(resp.read())

    def _post(self, path, payload):
        req = urllib.request.Request(
            self.server_url + path,
            data=msgpack.packb(payload, default=pack_array),
            headers={"Content-Type": "application/msgpack"},
        )
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                return msgpack.unpackb(resp.read(), object_hook=unpack_array)
        except urllib.error.HTTPError as e:
            raise RuntimeError(f"HTTP {e.code}: {json.loads(e.read())['error']}") from None

    def reset(self, main_images, states, task_descriptions, seed=None):
        payload = {"main_images": main_images, "states": states, "task_descriptions": task_descriptions}
        if seed is not None:
            payload["seed"] = seed
        return self._post("/reset", payload)

    def chunk_step(self, actions):
        return self._post("/chunk_step", {"actions": actions})


def episode(url, n, chunks, d):
    client = WorldArenaHttpClient(url)
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(n, 32, 32, 3), dtype=np.uint8)
    states = rng.uniform(-0.5, 0.5, size=(n, d)).astype(np.float32)
    plan = [rng.uniform(-0.5, 0.5, size=(n, 4, d)).astype(np.float32) for _ in range(chunks)]
    tasks = [f"task {i}" for i in range(n)]
    seen = {"health_before": client.health()}

    def run():
        reset = client.reset(images, states, tasks, seed=7)
        obs = reset["obs"]
        out = {
            "reset_obs": {k: (list(v.shape), v.dtype.str) if isinstance(v, np.ndarray) else v for k, v in obs.items()},
            "reset_images_are_the_first_frames": bool(np.array_equal(obs["main_images"], images)),
            "num_envs": reset["num_envs"],
            "frames": [],
            "rewards": [],
        }
        for actions in plan:
            step = client.chunk_step(actions)
            obs = step["obs"]
            frames = step["frames"]
            out["frames"].append(frames)
            out["elapsed_steps"] = step["elapsed_steps"]
            out["step_keys"] = sorted(step.keys())
            out["last_frame_is_main_image"] = bool(np.array_equal(frames[:, -1], obs["main_images"]))
            out["states_are_the_last_actions"] = bool(np.allclose(obs["states"], actions[:, -1]))
            # The reward is the caller's: here, how much each environment's image changed.
            out["rewards"].append(np.abs(frames[:, -1].astype(np.float32) - images.astype(np.float32)).mean(axis=(1, 2, 3)).tolist())
        out["frames_shape"] = [list(f.shape) for f in out["frames"]]
        return out

    first, second = run(), run()
    seen.update({k: v for k, v in first.items() if k != "frames"})
    seen["same_seed_same_frames"] = all(np.array_equal(a, b) for a, b in zip(first["frames"], second["frames"]))
    seen["health_after"] = client.health()
    try:
        client.chunk_step(plan[0][:1])
        seen["wrong_batch"] = "accepted"
    except RuntimeError as e:
        seen["wrong_batch"] = str(e)
    try:
        client._post("/reset", {"main_images": images, "task_descriptions": tasks})
        seen["no_states"] = "accepted"
    except RuntimeError as e:
        seen["no_states"] = str(e)
    print(json.dumps(seen))


if __name__ == "__main__":
    if sys.argv[1] == "episode":
        episode(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]))
    else:
        sys.exit(__doc__)
