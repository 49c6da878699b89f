"""Scripted openpi policy servers and an HTTP success judge for tests/evaluate.rs.

The websocket side follows openpi's `WebsocketPolicyServer` (src/openpi/serving/websocket_policy_server.py):
the server sends msgpack metadata first, answers each msgpack observation with a msgpack action
dict, and on an exception sends the traceback as a text frame and closes with 1011. It is built
on the PyPI `websockets` package; the msgpack-numpy hooks below are those of
`openpi_client/msgpack_numpy.py` (openpi-client 0.1.2), written out with `msgpack` + `numpy`
because openpi-client pins numpy < 2, which the project's virtualenv (torch) does not allow.

Scripted behaviour, keyed by the prompt (episodes carry their own prompts):
- a prompt containing "raise" makes the policy raise on the second request of the connection;
- a prompt containing "drop" makes the server drop the connection on the first request;
- otherwise each policy returns a fixed chunk built from the received state:
  `abs`: rows state + 0.001 * (j + 1), padded with two columns of 9.0;
  `delta`: rows of 0.002 with the grippers (6, 13) at 1.0 / 0.0.
Observations are checked (keys, dtypes, shapes); a wrong one raises, which fails the episode.

The judge answers POST /judge (msgpack-numpy {"frames": uint8 [T, H, W, 3], "task", "prompt",
"policy", "episode"}) with {"success_probability": p} from a plan: "policy/task/episode" -> p or
[p, min_frames] (p only once at least min_frames frames are shown, else 0).

Usage: openpi_server.py --out PORTS_JSON --log LOG_JSONL --plan PLAN_JSON [--lifetime S] [--ping S]
       --policy NAME:KIND:HORIZON:IMAGE_KEY:IMAGE_SHAPE ... (IMAGE_KEY "a.b" is nested)
"""

import argparse
import asyncio
import functools
import http
import json
import os
import threading
import time
import traceback
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import msgpack
import numpy as np
import websockets.asyncio.server
import websockets.frames


# --- openpi_client/msgpack_numpy.py -------------------------------------------------------------
def pack_array(obj):
    if (isinstance(obj, (np.ndarray, np.generic))) and obj.dtype.kind in ("V", "O", "c"):
        raise ValueError(f"Unsupported dtype: {obj.dtype}")

    if isinstance(obj, np.ndarray):
        return {
            b"__ndarray__": True,
            b"data": obj.tobytes(),
            b"dtype": obj.dtype.str,
            b"shape": obj.shape,
        }

    if isinstance(obj, np.generic):
        return {
            b"__npgeneric__": True,
            b"data": obj.item(),
            b"dtype": obj.dtype.str,
        }

    return obj


def unpack_array(obj):
    if b"__ndarray__" in obj:
        return np.ndarray(buffer=obj[b"data"], dtype=np.dtype(obj[b"dtype"]), shape=obj[b"shape"])

    if b"__npgeneric__" in obj:
        return np.dtype(obj[b"dtype"]).type(obj[b"data"])

    return obj


Packer = functools.partial(msgpack.Packer, default=pack_array)
packb = functools.partial(msgpack.packb, default=pack_array)
unpackb = functools.partial(msgpack.unpackb, object_hook=unpack_array)
# -------------------------------------------------------------------------------------------------

LOG_LOCK = threading.Lock()


def log(path, entry):
    with LOG_LOCK, open(path, "a") as f:
        f.write(json.dumps(entry) + "\n")


def lookup(obs, key):
    node = obs
    for part in key.split("."):
        node = node[part]
    return node


class ScriptedPolicy:
    def __init__(self, name, kind, horizon, image_key, image_shape, log_path):
        self.name, self.kind, self.horizon = name, kind, horizon
        self.image_key, self.image_shape = image_key, tuple(image_shape)
        self.log_path = log_path
        self.connections = 0

    def infer(self, obs, conn, request):
        image = lookup(obs, self.image_key)
        state = obs["observation/state"]
        prompt = obs["prompt"]
        entry = {
            "policy": self.name,
            "conn": conn,
            "request": request,
            "prompt": prompt,
            "image": [list(image.shape), image.dtype.str],
            "state": [float(v) for v in state],
            "state_dtype": state.dtype.str,
        }
        if image.dtype != np.uint8 or image.shape != self.image_shape:
            raise ValueError(f"image {self.image_key}: {image.dtype} {image.shape}, expected uint8 {self.image_shape}")
        if state.dtype != np.float32 or state.shape != (14,):
            raise ValueError(f"state: {state.dtype} {state.shape}, expected float32 (14,)")
        if not isinstance(prompt, str):
            raise ValueError("prompt is not a str")
        if "raise" in prompt and request == 2:
            log(self.log_path, dict(entry, event="raise"))
            raise RuntimeError("scripted failure in the policy")
        j = np.arange(1, self.horizon + 1, dtype=np.float32)[:, None]
        if self.kind == "abs":
            actions = np.concatenate([state[None, :] + 0.001 * j, np.full((self.horizon, 2), 9.0, np.float32)], axis=1)
        else:
            actions = np.full((self.horizon, 14), 0.002, np.float32)
            actions[:, 6] = 1.0
            actions[:, 13] = 0.0
        log(self.log_path, dict(entry, event="reply", actions=actions.tolist()))
        return {"actions": actions.astype(np.float32), "state": state}

    async def handler(self, websocket):
        self.connections += 1
        conn = self.connections
        packer = Packer()
        await websocket.send(packer.pack({"policy": self.name, "action_horizon": self.horizon}))
        prev_total_time = None
        request = 0
        while True:
            try:
                start_time = time.monotonic()
                obs = unpackb(await websocket.recv())
                request += 1
                if "drop" in obs.get("prompt", "") and request == 1:
                    log(self.log_path, {"policy": self.name, "conn": conn, "request": request, "event": "drop"})
                    websocket.transport.abort()
                    return
                infer_time = time.monotonic()
                action = self.infer(obs, conn, request)
                infer_time = time.monotonic() - infer_time
                action["server_timing"] = {"infer_ms": infer_time * 1000}
                if prev_total_time is not None:
                    action["server_timing"]["prev_total_ms"] = prev_total_time * 1000
                await websocket.send(packer.pack(action))
                prev_total_time = time.monotonic() - start_time
            except websockets.ConnectionClosed:
                break
            except Exception:
                await websocket.send(traceback.format_exc())
                await websocket.close(
                    code=websockets.frames.CloseCode.INTERNAL_ERROR,
                    reason="Internal server error. Traceback included in previous frame.",
                )
                return


def health_check(connection, request):
    if request.path == "/healthz":
        return connection.respond(http.HTTPStatus.OK, "OK\n")
    return None


def judge_handler(plan, log_path):
    class Judge(BaseHTTPRequestHandler):
        def do_POST(self):
            body = self.rfile.read(int(self.headers["Content-Length"]))
            req = unpackb(body)
            frames = req["frames"]
            key = f'{req["policy"]}/{req["task"]}/{req["episode"]}'
            rule = plan.get(key, 0.0)
            p, min_frames = (rule, 0) if isinstance(rule, (int, float)) else rule
            p = p if frames.shape[0] >= min_frames else 0.0
            log(log_path, {"event": "judge", "key": key, "shape": list(frames.shape), "dtype": frames.dtype.str,
                           "prompt": req["prompt"], "p": p})
            out = json.dumps({"success_probability": p}).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(out)))
            self.end_headers()
            self.wfile.write(out)

        def log_message(self, *args):
            pass

    return Judge


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--log", required=True)
    ap.add_argument("--plan", required=True)
    ap.add_argument("--policy", action="append", default=[])
    ap.add_argument("--lifetime", type=float, default=600.0)
    # Keepalive ping interval and timeout in seconds (websockets' default is 20): short, so that a
    # client that stops reading while it generates video is dropped within the test.
    ap.add_argument("--ping", type=float, default=20.0)
    args = ap.parse_args()
    with open(args.plan) as f:
        plan = json.load(f)
    judge = ThreadingHTTPServer(("127.0.0.1", 0), judge_handler(plan, args.log))
    threading.Thread(target=judge.serve_forever, daemon=True).start()
    ports = {"judge": judge.server_address[1]}
    servers = []
    for spec in args.policy:
        name, kind, horizon, image_key, image_shape = spec.split(":")
        policy = ScriptedPolicy(name, kind, int(horizon), image_key, [int(v) for v in image_shape.split("x")], args.log)
        server = await websockets.asyncio.server.serve(
            policy.handler,
            "127.0.0.1",
            0,
            compression=None,
            max_size=None,
            process_request=health_check,
            ping_interval=args.ping,
            ping_timeout=args.ping,
        )
        servers.append(server)
        ports[name] = server.sockets[0].getsockname()[1]
    with open(args.out + ".tmp", "w") as f:
        json.dump(ports, f)
    os.replace(args.out + ".tmp", args.out)
    # Stops by itself should the test that started it never stop it.
    try:
        await asyncio.wait_for(asyncio.gather(*(s.serve_forever() for s in servers)), args.lifetime)
    except asyncio.TimeoutError:
        pass
    judge.shutdown()


if __name__ == "__main__":
    asyncio.run(main())
