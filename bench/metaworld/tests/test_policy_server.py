"""policy_server.py over a real socket: handshake, replies, seeding per episode, bad messages.
Run: python bench/metaworld/tests/test_policy_server.py (or pytest)."""

import asyncio
import atexit
import json
import os
import shutil
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import policy_server  # noqa: E402
from msgpack_numpy import packb, unpackb  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

TASKS = ["drawer-open-v3", "button-press-topdown-v3"]


class FakePolicy:
    """Rows state + seed/1000 + j/100, so a reply shows the episode's seed."""

    def __init__(self, task, variant, seed):
        self.seed = seed

    def act(self, image, state, n):
        return state[None, :] + self.seed / 1000 + np.arange(n, dtype=np.float32)[:, None] / 100


def start(variants=("expert", "noisy"), seeds=None, make_policy=FakePolicy):
    folder = tempfile.mkdtemp(prefix="bwm-policy-server-")
    atexit.register(shutil.rmtree, folder, True)
    ready = os.path.join(folder, "ready.json")
    keys = {"image": "observation/image", "state": "observation/state", "prompt": "prompt", "actions": "actions"}
    servers = [policy_server.VariantServer(v, TASKS, 8, policy_server.EpisodeSeeds(100, seeds), keys, make_policy, lambda m: None)
               for v in variants]
    threading.Thread(target=asyncio.run, args=(policy_server.serve(servers, "127.0.0.1", 0, ready, 60),), daemon=True).start()
    for _ in range(100):
        if os.path.exists(ready):
            with open(ready) as f:
                return json.load(f)["ports"]
        time.sleep(0.05)
    raise TimeoutError("no ready file")


def obs(prompt="drawer-open-v3", state=(0.0, 0.6, 0.2, -1.0)):
    return {"observation/image": np.zeros((64, 64, 3), np.uint8), "observation/state": np.array(state, np.float32), "prompt": prompt}


def episode(port, messages):
    with connect(f"ws://127.0.0.1:{port}", max_size=None) as ws:
        meta = unpackb(ws.recv())
        replies = []
        for m in messages:
            ws.send(m if isinstance(m, (bytes, str)) else packb(m))
            r = ws.recv()
            replies.append(r if isinstance(r, str) else unpackb(r))
            if isinstance(r, str):
                try:
                    ws.recv()
                except Exception as e:
                    replies.append(getattr(getattr(e, "rcvd", None), "code", None))
                break
        return meta, replies


def test_replies_and_episode_seeds():
    ports = start()
    meta, replies = episode(ports["expert"], [obs(), obs()])
    assert meta["policy"] == "expert" and meta["action_horizon"] == 8
    a = replies[0]["actions"]
    assert a.dtype == np.float32 and a.shape == (8, 4)
    assert np.allclose(a[0], [0.1, 0.7, 0.3, -0.9]), "episode 0 of the task: seed 100"
    _, replies = episode(ports["expert"], [obs()])
    assert np.allclose(replies[0]["actions"][0, 0], 0.101), "episode 1: seed 101"
    _, replies = episode(ports["expert"], [obs("press the button-press-topdown-v3")])
    assert np.allclose(replies[0]["actions"][0, 0], 0.1), "each task counts its own episodes"
    _, replies = episode(ports["noisy"], [obs()])
    assert np.allclose(replies[0]["actions"][0, 0], 0.1), "each variant counts its own episodes"


def test_episode_seed_lists():
    ports = start(("expert",), {"drawer-open-v3": [7]})
    _, replies = episode(ports["expert"], [obs()])
    assert np.allclose(replies[0]["actions"][0, 0], 0.007)
    _, replies = episode(ports["expert"], [obs()])
    assert "only 1" in replies[0] and replies[1] == 1011


def test_bad_messages_are_answered_and_the_server_survives():
    ports = start(("expert",))
    port = ports["expert"]
    bad = [
        (obs(prompt="open something"), "names 0 of the served tasks"),
        ({"prompt": "drawer-open-v3"}, "lacks observation/image"),
        (dict(obs(), **{"observation/state": np.zeros(3, np.float32)}), "float [4]"),
        (dict(obs(), **{"observation/state": np.array([0, 0, np.nan, 0], np.float32)}), "NaN"),
        (dict(obs(), **{"observation/image": np.zeros((64, 64), np.uint8)}), "uint8 [H, W, 3]"),
        (b"\xc1garbage", "not msgpack-numpy"),
        ("hello", "text frame"),
        ([1, 2], "not a map"),
    ]
    for message, expected in bad:
        _, replies = episode(port, [message])
        assert isinstance(replies[0], str) and expected in replies[0], (expected, replies[0])
        assert replies[1] == 1011
    _, replies = episode(port, [obs()])
    assert replies[0]["actions"].shape == (8, 4)


def test_real_policies_answer_a_chunk():
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
    from variants import make_policy

    ports = start(("expert",), make_policy=make_policy)
    _, replies = episode(ports["expert"], [obs(), obs()])
    a = replies[1]["actions"]
    assert a.shape == (8, 4) and np.isfinite(a).all()


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
