"""Synthetic LeRobot v2.1 datasets in generate.py's layout (PNG frames in the parquet, state,
action, a per-frame success flag and, when given, the object's distance to its goal), for tests
that must not need MuJoCo."""

import io
import json
import os

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image


def write_dataset(root, episodes, fps=80):
    """episodes: (task text, frames uint8 [T, H, W, 3], state float32 [T, 4], success bool [T], seed
    [, obj_to_target float32 [T] in m]); the `obj_to_target` column is written when every episode
    gives it."""
    tasks = sorted({e[0] for e in episodes})
    distances = all(len(e) > 5 for e in episodes)
    os.makedirs(os.path.join(root, "meta"), exist_ok=True)
    index = 0
    with open(os.path.join(root, "meta", "episodes.jsonl"), "w") as meta:
        for i, (task, frames, state, success, seed, *rest) in enumerate(episodes):
            t = len(frames)
            png = []
            for f in frames:
                b = io.BytesIO()
                Image.fromarray(f).save(b, format="PNG")
                png.append({"bytes": b.getvalue(), "path": None})
            table = pa.table({
                "observation.image": pa.array(png, pa.struct([("bytes", pa.binary()), ("path", pa.string())])),
                "observation.state": pa.array(list(state.astype(np.float32)), pa.list_(pa.float32())),
                "action": pa.array(list(state.astype(np.float32)), pa.list_(pa.float32())),
                "next.success": pa.array(success.astype(bool)),
                "timestamp": pa.array(np.arange(t, dtype=np.float32) / fps),
                "frame_index": pa.array(np.arange(t)),
                "episode_index": pa.array(np.full(t, i)),
                "index": pa.array(np.arange(index, index + t)),
                "task_index": pa.array(np.full(t, tasks.index(task))),
                **({"obj_to_target": pa.array(np.asarray(rest[0], np.float32))} if distances else {}),
            })
            index += t
            path = os.path.join(root, "data", "chunk-000", f"episode_{i:06d}.parquet")
            os.makedirs(os.path.dirname(path), exist_ok=True)
            pq.write_table(table, path)
            meta.write(json.dumps({"episode_index": i, "tasks": [task], "length": t, "seed": seed}) + "\n")
    with open(os.path.join(root, "meta", "tasks.jsonl"), "w") as f:
        for i, t in enumerate(tasks):
            f.write(json.dumps({"task_index": i, "task": t}) + "\n")
    h, w = episodes[0][1].shape[1:3]
    info = {
        "codebase_version": "v2.1", "robot_type": "sawyer", "fps": fps, "total_episodes": len(episodes), "total_frames": index,
        "total_tasks": len(tasks), "total_videos": 0, "total_chunks": 1, "chunks_size": 1000, "splits": {"train": f"0:{len(episodes)}"},
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet", "video_path": None,
        "features": {
            "observation.image": {"dtype": "image", "shape": [h, w, 3], "names": ["height", "width", "channel"]},
            "observation.state": {"dtype": "float32", "shape": [4], "names": ["x", "y", "z", "gripper"]},
            "action": {"dtype": "float32", "shape": [4], "names": ["x", "y", "z", "gripper"]},
            "next.success": {"dtype": "bool", "shape": [1], "names": None},
            **({"obj_to_target": {"dtype": "float32", "shape": [1], "names": None}} if distances else {}),
        },
    }
    with open(os.path.join(root, "meta", "info.json"), "w") as f:
        json.dump(info, f, indent=2)


def synthetic_episode(task, seed, length=40, size=64):
    """A grey scene where a bright bar grows from the left; success once it passes mid-frame (a
    drawer opening). The bar's colour tells the tasks apart; some episodes never get there."""
    rng = np.random.default_rng(seed)
    speed = rng.uniform(0.3, 1.6)
    colour = (60, 200, 60) if "drawer" in task else (220, 200, 40)
    frames = np.full((length, size, size, 3), 90, np.uint8)
    frames += rng.integers(0, 12, frames.shape, dtype=np.uint8)
    reach = np.minimum(np.arange(length) * speed, size - 4).astype(int) + 4
    row = int(rng.integers(10, size - 20))
    for t in range(length):
        frames[t, row:row + 8, :reach[t]] = colour
    success = reach > size // 2 + 8
    state = np.tile(np.array([0.0, 0.6, 0.2, -1.0], np.float32), (length, 1))
    return task, frames, state, success, seed
