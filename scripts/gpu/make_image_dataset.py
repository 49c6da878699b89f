"""Writes the bundled episodes (data/bwm-demo) as a LeRobot v2.1 dataset whose frames are
JPEG images inside the parquet files (`image` features), for timing `bwm prepare` on the GPU
machines, which have no FFmpeg or HDF5 libraries to read the other formats.

    python3 scripts/gpu/make_image_dataset.py OUT_DIR [--width 640 --height 480 --frames 120]
"""
import argparse, json, os, sys

import cv2
import pyarrow as pa
import pyarrow.parquet as pq

p = argparse.ArgumentParser()
p.add_argument("out")
p.add_argument("--demo", default=os.path.join(os.path.dirname(__file__), "../../data/bwm-demo"))
p.add_argument("--width", type=int, default=640)
p.add_argument("--height", type=int, default=480)
p.add_argument("--frames", type=int, default=120)
a = p.parse_args()

os.makedirs(f"{a.out}/meta", exist_ok=True)
image_type = pa.struct([("bytes", pa.binary()), ("path", pa.string())])
manifest = [json.loads(l) for l in open(f"{a.demo}/demo.jsonl") if l.strip()]
index = 0
episodes = []
for e, ep in enumerate(manifest):
    table = pq.read_table(f"{a.demo}/{ep['action']}")
    n = min(a.frames, table.num_rows, ep["length"])
    cap = cv2.VideoCapture(f"{a.demo}/{ep['video']}")
    images = []
    while len(images) < n:
        ok, bgr = cap.read()
        if not ok:
            sys.exit(f"{ep['video']}: only {len(images)} frames")
        bgr = cv2.resize(bgr, (a.width, a.height), interpolation=cv2.INTER_AREA)
        images.append({"bytes": cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes(), "path": None})
    state = table.column("observation.state").to_pylist()[:n]
    action = table.column("action").to_pylist()[:n]
    width = len(state[0])
    out = pa.table({
        "observation.state": pa.array(state, type=pa.list_(pa.float32(), width)),
        "action": pa.array(action, type=pa.list_(pa.float32(), width)),
        "observation.images.head": pa.array(images, type=image_type),
        "timestamp": pa.array([t / 30.0 for t in range(n)], type=pa.float32()),
        "frame_index": pa.array(range(n), type=pa.int64()),
        "episode_index": pa.array([e] * n, type=pa.int64()),
        "index": pa.array(range(index, index + n), type=pa.int64()),
        "task_index": pa.array([0] * n, type=pa.int64()),
    })
    path = f"{a.out}/data/chunk-000/episode_{e:06d}.parquet"
    os.makedirs(os.path.dirname(path), exist_ok=True)
    pq.write_table(out, path)
    episodes.append({"episode_index": e, "tasks": [ep["task"]], "length": n})
    index += n
scalar = lambda t: {"dtype": t, "shape": [1], "names": None}
info = {
    "codebase_version": "v2.1", "robot_type": "aloha-agilex", "total_episodes": len(episodes), "total_frames": index,
    "total_tasks": 1, "total_videos": 0, "total_chunks": 1, "chunks_size": 1000, "fps": 30,
    "splits": {"train": f"0:{len(episodes)}"},
    "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet", "video_path": None,
    "features": {
        "observation.state": {"dtype": "float32", "shape": [width], "names": None},
        "action": {"dtype": "float32", "shape": [width], "names": None},
        "observation.images.head": {"dtype": "image", "shape": [a.height, a.width, 3], "names": ["height", "width", "channel"]},
        "timestamp": scalar("float32"), "frame_index": scalar("int64"), "episode_index": scalar("int64"),
        "index": scalar("int64"), "task_index": scalar("int64"),
    },
}
json.dump(info, open(f"{a.out}/meta/info.json", "w"), indent=2)
with open(f"{a.out}/meta/episodes.jsonl", "w") as f:
    f.writelines(json.dumps(x) + "\n" for x in episodes)
with open(f"{a.out}/meta/tasks.jsonl", "w") as f:
    f.write(json.dumps({"task_index": 0, "task": manifest[0]["task"]}) + "\n")
print(f"{len(episodes)} episodes, {index} frames of {a.width}x{a.height} in {a.out}")
