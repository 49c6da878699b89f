"""Client side of tests/serve.rs for `bwm serve` (the client of docs/serve.md).

  serve_client.py roundtrip URL T K D   one chunk from T given 32x32 frames and T + K actions, twice
                                        with the same seed; prints shapes, dtypes and whether the
                                        two replies are equal, as JSON
  serve_client.py bodies DIR T K D      request bodies for the error cases (and a good one) as files
  serve_client.py body FILE T H W K D   a good request body of T given HxW frames and T + K actions
"""

import json
import os
import sys
import urllib.error
import urllib.request

import msgpack
import numpy as np


# msgpack-numpy as openpi_client/msgpack_numpy.py encodes it (the marker keys are bytes).
def pack_array(obj):
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    return obj


def unpack_array(obj):
    if b"__ndarray__" in obj:
        return np.ndarray(buffer=obj[b"data"], dtype=np.dtype(obj[b"dtype"]), shape=obj[b"shape"])
    if b"__npgeneric__" in obj:
        return np.dtype(obj[b"dtype"]).type(obj[b"data"])
    return obj


def request_chunk(url, frames, actions, normalized=True, seed=None):
    """frames: uint8 (T, H, W, 3), frame 0 = x0; actions: float32 (T + n, d_a)."""
    body = {"frames": frames, "actions": actions, "normalized": normalized}
    if seed is not None:
        body["seed"] = seed
    req = urllib.request.Request(
        url + "/v1/chunk",
        data=msgpack.packb(body, default=pack_array),
        headers={"Content-Type": "application/msgpack"},
    )
    try:
        with urllib.request.urlopen(req, timeout=300) as resp:
            return msgpack.unpackb(resp.read(), object_hook=unpack_array)
    except urllib.error.HTTPError as e:
        raise RuntimeError(f"HTTP {e.code}: {json.loads(e.read())['error']}") from None


def inputs(t, k, d, h=32, w=32):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, size=(t, h, w, 3), dtype=np.uint8)
    actions = rng.uniform(-1, 1, size=(t + k, d)).astype(np.float32)
    return frames, actions


def roundtrip(url, t, k, d):
    frames, actions = inputs(t, k, d)
    a = request_chunk(url, frames, actions, normalized=True, seed=7)
    b = request_chunk(url, frames, actions, normalized=True, seed=7)
    print(
        json.dumps(
            {
                "frames": [list(a["frames"].shape), a["frames"].dtype.str],
                "actions": [list(a["actions"].shape), a["actions"].dtype.str],
                "actions_echoed": bool(np.array_equal(a["actions"], actions[t:])),
                "timings": sorted(a["timings"].keys()),
                "same_seed_same_frames": bool(np.array_equal(a["frames"], b["frames"])),
            }
        )
    )


def bodies(out, t, k, d):
    os.makedirs(out, exist_ok=True)
    frames, actions = inputs(t, k, d)

    def write(name, body):
        with open(os.path.join(out, name), "wb") as f:
            f.write(msgpack.packb(body, default=pack_array))

    write("good.msgpack", {"frames": frames, "actions": actions, "normalized": np.bool_(True), "seed": 3})
    write("wrong_shape.msgpack", {"frames": frames, "actions": np.zeros((t + k + 1, d), np.float32), "normalized": True})
    write("wrong_dtype.msgpack", {"frames": frames.astype(np.float32), "actions": actions, "normalized": True})
    bad = np.zeros((t, 33, 32, 3), np.uint8)
    write("bad_size.msgpack", {"frames": bad, "actions": actions, "normalized": True})
    nan, inf = actions.copy(), actions.copy()
    nan[1, 2], inf[0, 0] = np.nan, -np.inf
    write("nan_actions.msgpack", {"frames": frames, "actions": nan, "normalized": True})
    write("inf_actions.msgpack", {"frames": frames, "actions": inf, "normalized": True})

    def declared(shape, data):  # an ndarray whose declared shape is not the data's
        return {b"__ndarray__": True, b"data": data, b"dtype": "<f4", b"shape": shape}

    write("negative_dim.msgpack", {"frames": frames, "actions": declared([-(t + k), d], actions.tobytes()), "normalized": True})
    write("huge_dims.msgpack", {"frames": frames, "actions": declared([2**40, 2**40, d], actions.tobytes()), "normalized": True})
    write("huge_rows.msgpack", {"frames": frames, "actions": declared([2**31, d], actions.tobytes()), "normalized": True})
    with open(os.path.join(out, "malformed.bin"), "wb") as f:
        f.write(b"\x85\xa6frames\xc4\x10not msgpack at all")


if __name__ == "__main__":
    cmd, *rest = sys.argv[1:]
    if cmd == "roundtrip":
        roundtrip(rest[0], *map(int, rest[1:4]))
    elif cmd == "bodies":
        bodies(rest[0], *map(int, rest[1:4]))
    elif cmd == "body":
        t, h, w, k, d = map(int, rest[1:6])
        frames, actions = inputs(t, k, d, h, w)
        with open(rest[0], "wb") as f:
            f.write(msgpack.packb({"frames": frames, "actions": actions, "normalized": True}, default=pack_array))
    else:
        sys.exit(f"unknown command {cmd}")
