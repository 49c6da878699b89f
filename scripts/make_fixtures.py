#!/usr/bin/env python3
"""Writes tiny robot datasets with known values and colors, in the formats bwm-data reads, with
the formats' own tools: pyarrow (parquet), the ffmpeg CLI (mp4: libx264, and libsvtav1 as
LeRobot v3 uses by default), h5py and OpenCV (RoboTwin HDF5 with cv2.imencode JPEGs).

    make_fixtures.py OUT_DIR

OUT_DIR/
  lerobot_v21/       LeRobot v2.1: 3 episodes (10, 12, 9 frames), cameras top (64x48) and wrist (64x32), H.264
  lerobot_v21_bad/   LeRobot v2.1 with one usable episode and one of each defect (see BAD below)
  lerobot_v21_images/ LeRobot v2.1 with `image` features: camera top as PNG bytes in the parquet, wrist as PNG files
  lerobot_v30/       LeRobot v3.0: 3 episodes in 2 data/video files, cameras top and wrist (64x64), AV1
  robotwin/original/ RoboTwin 2.0 original layout: data/episode{0,1}.hdf5, instructions/episode{0,1}.json
  robotwin/v2026/    RoboTwin 2026 layout: episode{0,1}.hdf5

Known values (the Rust tests use the same formulas):
  LeRobot  observation.state[t][j] = 100*e + t + 0.1*j (6 values), action[t][j] = -(100*e + t) - 0.01*j
  frames   top half: the episode's color (camera top) or CAMERA2 (camera wrist);
           bottom half: gray 16 + 12*t
  RoboTwin joint_action/vector[t][k] = e + 0.1*t + 0.01*k (grippers at k = 6, 13 are t/(T-1));
           endpose left = [0.1t, 0.2, 0.3+e, quat(rpy = 0.05t, 0.1, -0.2)],
                   right = [-0.1t, -0.2, 0.5, quat(rpy = -0.05t, -0.1, 0.3 + 0.01t)], quat w-first;
           frames: left half red, right half blue (as RGB), bottom quarter gray 16 + 20*t,
           JPEG-encoded by cv2.imencode from the RGB array (so the file holds R and B swapped).
"""

import json
import math
import os
import shutil
import subprocess
import sys
import tempfile

import cv2
import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

FPS = 10
EPISODE_COLORS = [(200, 40, 40), (40, 200, 40), (40, 40, 200), (200, 200, 40), (40, 200, 200), (200, 40, 200),
                  (120, 60, 20), (20, 60, 120)]
CAMERA2 = (128, 128, 40)
TASKS = ["stack the red block", "open the drawer", "push the cup"]


def frame(width, height, top, t):
    img = np.empty((height, width, 3), dtype=np.uint8)
    img[: height // 2] = top
    img[height // 2 :] = 16 + 12 * t
    return img


def encode_mp4(frames, path, codec):
    """Raw RGB frames piped into the ffmpeg CLI, as LeRobot's and RoboTwin's writers do."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    h, w, _ = frames[0].shape
    args = ["ffmpeg", "-y", "-loglevel", "error", "-f", "rawvideo", "-pixel_format", "rgb24", "-video_size", f"{w}x{h}",
            "-framerate", str(FPS), "-i", "-", "-pix_fmt", "yuv420p"]
    if codec == "h264":
        args += ["-vcodec", "libx264", "-crf", "18", "-g", "2"]
    else:
        args += ["-vcodec", "libsvtav1", "-crf", "30", "-g", "2"]
    proc = subprocess.run(args + [path], input=b"".join(f.tobytes() for f in frames), capture_output=True)
    if proc.returncode != 0:
        raise RuntimeError(f"ffmpeg failed for {path}: {proc.stderr.decode(errors='replace')}")


def duration(path):
    out = subprocess.run(["ffprobe", "-v", "error", "-show_entries", "format=duration", "-of", "csv=p=0", path],
                         capture_output=True, text=True, check=True)
    return float(out.stdout.strip())


def concat_mp4(parts, path):
    """ffmpeg's concat demuxer with stream copy, as LeRobot's concatenate_video_files does."""
    with tempfile.NamedTemporaryFile("w", suffix=".ffconcat", delete=False) as f:
        f.write("ffconcat version 1.0\n")
        for p in parts:
            f.write(f"file '{os.path.abspath(p)}'\n")
        listing = f.name
    try:
        subprocess.run(["ffmpeg", "-y", "-loglevel", "error", "-f", "concat", "-safe", "0", "-i", listing, "-c", "copy", path],
                       check=True, capture_output=True)
    finally:
        os.unlink(listing)


def state_rows(e, length):
    return np.array([[100 * e + t + 0.1 * j for j in range(6)] for t in range(length)], dtype=np.float32)


def action_rows(e, length):
    return np.array([[-(100 * e + t) - 0.01 * j for j in range(6)] for t in range(length)], dtype=np.float32)


def vector_type(n):
    # Hugging Face `datasets.Sequence(length=n)`, what LeRobot declares for shape (n,) features.
    return pa.list_(pa.float32(), n)


def episode_table(e, length, first_index, task_index, state=None):
    state = state_rows(e, length) if state is None else state
    return pa.table({
        "observation.state": pa.array(list(state), type=vector_type(6)),
        "action": pa.array(list(action_rows(e, length)), type=vector_type(6)),
        "timestamp": pa.array([t / FPS for t in range(length)], type=pa.float32()),
        "frame_index": pa.array(range(length), type=pa.int64()),
        "episode_index": pa.array([e] * length, type=pa.int64()),
        "index": pa.array(range(first_index, first_index + length), type=pa.int64()),
        "task_index": pa.array([task_index] * length, type=pa.int64()),
    })


def features(cameras, codec):
    f = {
        "observation.state": {"dtype": "float32", "shape": [6], "names": [f"s{j}" for j in range(6)]},
        "action": {"dtype": "float32", "shape": [6], "names": [f"a{j}" for j in range(6)]},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    for key, (w, h) in cameras.items():
        f[key] = {"dtype": "video", "shape": [h, w, 3], "names": ["height", "width", "channels"],
                  "info": {"video.height": h, "video.width": w, "video.codec": codec, "video.pix_fmt": "yuv420p",
                           "video.is_depth_map": False, "video.fps": FPS, "video.channels": 3, "has_audio": False}}
    return f


V21_DATA = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
V21_VIDEO = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"


def write_v21(root, lengths, cameras, tweak=None):
    """tweak(e, length) -> dict of overrides for one episode: state, video_frames, video (bytes|None),
    truncate_video (keep that share of the encoded file's bytes), parquet (bytes for the data file)."""
    os.makedirs(f"{root}/meta", exist_ok=True)
    index = 0
    episodes = []
    for e, length in enumerate(lengths):
        t = tweak(e, length) if tweak else {}
        task = TASKS[e % len(TASKS)]
        table = episode_table(e, length, index, e % len(TASKS), t.get("state"))
        path = f"{root}/" + V21_DATA.format(episode_chunk=0, episode_index=e)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        pq.write_table(table, path)
        if "parquet" in t:
            with open(path, "wb") as f:
                f.write(t["parquet"])
        for c, (key, (w, h)) in enumerate(cameras.items()):
            top = EPISODE_COLORS[e] if c == 0 else CAMERA2
            vpath = f"{root}/" + V21_VIDEO.format(episode_chunk=0, episode_index=e, video_key=key)
            n = t.get("video_frames", length)
            encode_mp4([frame(w, h, top, i) for i in range(n)], vpath, "h264")
            if "video" in t:
                if t["video"] is None:
                    os.remove(vpath)
                else:
                    with open(vpath, "wb") as f:
                        f.write(t["video"])
            if "truncate_video" in t:
                with open(vpath, "rb") as f:
                    data = f.read()
                with open(vpath, "wb") as f:
                    f.write(data[: int(len(data) * t["truncate_video"])])
        episodes.append({"episode_index": e, "tasks": [task], "length": length})
        index += length
    write_v21_meta(root, episodes, len(lengths) * len(cameras), V21_VIDEO, features(cameras, "h264"))


def write_v21_meta(root, episodes, total_videos, video_path, feats):
    """meta/info.json, episodes.jsonl and tasks.jsonl of a LeRobot v2.1 dataset."""
    info = {
        "codebase_version": "v2.1", "robot_type": "fixture", "total_episodes": len(episodes),
        "total_frames": sum(ep["length"] for ep in episodes), "total_tasks": len(TASKS), "total_videos": total_videos,
        "total_chunks": 1, "chunks_size": 1000, "fps": FPS, "splits": {"train": f"0:{len(episodes)}"},
        "data_path": V21_DATA, "video_path": video_path, "features": feats,
    }
    with open(f"{root}/meta/info.json", "w") as f:
        json.dump(info, f, indent=4)
    with open(f"{root}/meta/episodes.jsonl", "w") as f:
        f.writelines(json.dumps(ep) + "\n" for ep in episodes)
    with open(f"{root}/meta/tasks.jsonl", "w") as f:
        f.writelines(json.dumps({"task_index": i, "task": t}) + "\n" for i, t in enumerate(TASKS))


def write_v21_images(root, lengths, size):
    """LeRobot v2.1 with `image` features (no video): camera top as PNG bytes inside the parquet
    (Hugging Face `datasets.Image` cells: struct of bytes and path), camera wrist as PNG files the
    cells point to."""
    w, h = size
    os.makedirs(f"{root}/meta", exist_ok=True)
    image_type = pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    png = lambda img: cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))[1].tobytes()
    index = 0
    episodes = []
    for e, length in enumerate(lengths):
        table = episode_table(e, length, index, e % len(TASKS))
        top = [{"bytes": png(frame(w, h, EPISODE_COLORS[e], t)), "path": None} for t in range(length)]
        wrist = []
        for t in range(length):
            rel = f"images/wrist/episode_{e:06d}/frame_{t:06d}.png"
            os.makedirs(os.path.dirname(f"{root}/{rel}"), exist_ok=True)
            with open(f"{root}/{rel}", "wb") as f:
                f.write(png(frame(w, h, CAMERA2, t)))
            wrist.append({"bytes": None, "path": rel})
        table = table.append_column("observation.images.top", pa.array(top, type=image_type))
        table = table.append_column("observation.images.wrist", pa.array(wrist, type=image_type))
        path = f"{root}/" + V21_DATA.format(episode_chunk=0, episode_index=e)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        pq.write_table(table, path)
        episodes.append({"episode_index": e, "tasks": [TASKS[e % len(TASKS)]], "length": length})
        index += length
    feats = features({}, "h264")
    for key in ["observation.images.top", "observation.images.wrist"]:
        feats[key] = {"dtype": "image", "shape": [h, w, 3], "names": ["height", "width", "channel"]}
    write_v21_meta(root, episodes, 0, None, feats)


def write_v30(root, lengths, cameras, data_file_of):
    os.makedirs(f"{root}/meta/episodes/chunk-000", exist_ok=True)
    data_path = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    video_path = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    tmp = tempfile.mkdtemp()
    rows = {k: [] for k in ["episode_index", "tasks", "length", "data/chunk_index", "data/file_index",
                            "dataset_from_index", "dataset_to_index", "meta/episodes/chunk_index", "meta/episodes/file_index"]}
    for key in cameras:
        for c in ["chunk_index", "file_index", "from_timestamp", "to_timestamp"]:
            rows[f"videos/{key}/{c}"] = []
    tables = {}
    parts = {}
    index = 0
    for e, length in enumerate(lengths):
        file_index = data_file_of(e)
        tables.setdefault(file_index, []).append(episode_table(e, length, index, e % len(TASKS)))
        for k, v in [("episode_index", e), ("tasks", [TASKS[e % len(TASKS)]]), ("length", length), ("data/chunk_index", 0),
                     ("data/file_index", file_index), ("dataset_from_index", index), ("dataset_to_index", index + length),
                     ("meta/episodes/chunk_index", 0), ("meta/episodes/file_index", 0)]:
            rows[k].append(v)
        for c, (key, (w, h)) in enumerate(cameras.items()):
            top = EPISODE_COLORS[e] if c == 0 else CAMERA2
            part = f"{tmp}/{key}_{e}.mp4"
            encode_mp4([frame(w, h, top, i) for i in range(length)], part, "av1")
            previous = parts.setdefault((key, file_index), [])
            start = sum(duration(p) for p in previous)
            previous.append(part)
            rows[f"videos/{key}/chunk_index"].append(0)
            rows[f"videos/{key}/file_index"].append(file_index)
            rows[f"videos/{key}/from_timestamp"].append(start)
            rows[f"videos/{key}/to_timestamp"].append(start + duration(part))
        index += length
    for file_index, ts in tables.items():
        path = f"{root}/" + data_path.format(chunk_index=0, file_index=file_index)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        pq.write_table(pa.concat_tables(ts), path)
    for (key, file_index), ps in parts.items():
        path = f"{root}/" + video_path.format(video_key=key, chunk_index=0, file_index=file_index)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        concat_mp4(ps, path)
    shutil.rmtree(tmp)
    types = {"tasks": pa.list_(pa.string())}
    table = pa.table({k: pa.array(v, type=types.get(k, pa.float64() if k.endswith("timestamp") else pa.int64())) for k, v in rows.items()})
    pq.write_table(table, f"{root}/meta/episodes/chunk-000/file-000.parquet")
    pq.write_table(pa.table({"task_index": pa.array(range(len(TASKS)), type=pa.int64()), "task": TASKS}), f"{root}/meta/tasks.parquet")
    info = {
        "codebase_version": "v3.0", "robot_type": "fixture", "total_episodes": len(lengths), "total_frames": index,
        "total_tasks": len(TASKS), "chunks_size": 1000, "data_files_size_in_mb": 100, "video_files_size_in_mb": 200,
        "fps": FPS, "splits": {"train": f"0:{len(lengths)}"}, "data_path": data_path, "video_path": video_path,
        "features": features(cameras, "av1"),
    }
    with open(f"{root}/meta/info.json", "w") as f:
        json.dump(info, f, indent=4)


def quat_wxyz(roll, pitch, yaw):
    """Hamilton product qz(yaw) * qy(pitch) * qx(roll), (w, x, y, z)."""
    def mul(a, b):
        aw, ax, ay, az = a
        bw, bx, by, bz = b
        return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)
    qx = (math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0)
    qy = (math.cos(pitch / 2), 0.0, math.sin(pitch / 2), 0.0)
    qz = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    return mul(mul(qz, qy), qx)


def robotwin_episode(e, length):
    vector = np.array([[e + 0.1 * t + 0.01 * k for k in range(14)] for t in range(length)], dtype=np.float64)
    grip = np.array([t / (length - 1) for t in range(length)])
    vector[:, 6] = grip
    vector[:, 13] = grip
    left = np.array([[0.1 * t, 0.2, 0.3 + e, *quat_wxyz(0.05 * t, 0.1, -0.2)] for t in range(length)])
    right = np.array([[-0.1 * t, -0.2, 0.5, *quat_wxyz(-0.05 * t, -0.1, 0.3 + 0.01 * t)] for t in range(length)])
    rgb = []
    for t in range(length):
        img = np.zeros((48, 64, 3), dtype=np.uint8)
        img[:, :32] = (255, 0, 0)
        img[:, 32:] = (0, 0, 255)
        img[36:] = 16 + 20 * t
        rgb.append(img)
    return vector, grip, left, right, rgb


def jpegs(frames):
    """RoboTwin's images_encoding: cv2.imencode on RGB arrays (OpenCV takes them as BGR)."""
    data = [cv2.imencode(".jpg", f)[1].tobytes() for f in frames]
    return data, max(len(d) for d in data)


def write_robotwin_original(root, e, length):
    vector, grip, left, right, rgb = robotwin_episode(e, length)
    os.makedirs(f"{root}/data", exist_ok=True)
    os.makedirs(f"{root}/instructions", exist_ok=True)
    with h5py.File(f"{root}/data/episode{e}.hdf5", "w") as f:
        ja = f.create_group("joint_action")
        ja.create_dataset("left_arm", data=vector[:, 0:6])
        ja.create_dataset("left_gripper", data=vector[:, 6])
        ja.create_dataset("right_arm", data=vector[:, 7:13])
        ja.create_dataset("right_gripper", data=vector[:, 13])
        ja.create_dataset("vector", data=vector)
        ep = f.create_group("endpose")
        ep.create_dataset("left_endpose", data=left)
        ep.create_dataset("left_gripper", data=grip)
        ep.create_dataset("right_endpose", data=right)
        ep.create_dataset("right_gripper", data=grip)
        obs = f.create_group("observation")
        for cam, frames in [("head_camera", rgb), ("left_camera", [np.ascontiguousarray(x[::-1]) for x in rgb])]:
            g = obs.create_group(cam)
            data, n = jpegs(frames)
            g.create_dataset("rgb", data=data, dtype=f"S{n}")
            g.create_dataset("intrinsic_cv", data=np.tile(np.eye(3), (length, 1, 1)))
    with open(f"{root}/instructions/episode{e}.json", "w") as f:
        json.dump({"seen": [TASKS[e % len(TASKS)]], "unseen": ["something else"]}, f)


def write_robotwin_2026(root, e, length):
    """The layout of RoboTwin's create_xpolicylab_hdf5: states of frames 0..T-2, actions = next states."""
    vector, grip, left, right, rgb = robotwin_episode(e, length)
    os.makedirs(root, exist_ok=True)
    with h5py.File(f"{root}/episode{e}.hdf5", "w") as f:
        text = h5py.string_dtype(encoding="utf-8")
        f.attrs["source_format"] = "RoboTwin"
        f.attrs["source_path"] = "native_collection"
        f.create_dataset("data_format_version", data="v1.0", dtype=text)
        f.create_dataset("instructions", data=json.dumps([TASKS[e % len(TASKS)]]), dtype=text)
        f.create_group("additional_info").create_dataset("frequency", data=np.asarray(15, dtype=np.int32))
        state, action = f.create_group("state"), f.create_group("action")
        for name, values in [("left_arm_joint_states", vector[:, 0:6]), ("left_ee_joint_states", vector[:, 6:7]),
                             ("right_arm_joint_states", vector[:, 7:13]), ("right_ee_joint_states", vector[:, 13:14]),
                             ("left_ee_poses", left), ("right_ee_poses", right)]:
            values = values.astype(np.float32)
            state.create_dataset(name, data=values[:-1])
            action.create_dataset(name, data=values[1:])
        vision = f.create_group("vision")
        for cam, frames in [("cam_head", rgb), ("cam_left_wrist", [np.ascontiguousarray(x[::-1]) for x in rgb])]:
            g = vision.create_group(cam)
            data, n = jpegs(frames[:-1])
            g.create_dataset("colors", data=data, dtype=f"S{n}")
            g.create_dataset("shape", data=np.asarray(frames[0].shape, dtype=np.int32))


def bad_episode(e, length):
    """Episode 0 usable; 1 NaN state; 2 missing video; 3 video shorter than the rows; 4 too short; 5 garbage video;
    6 video cut off halfway, 7 parquet file cut off at two thirds (copies interrupted)."""
    if e == 1:
        s = state_rows(e, length)
        s[3, 2] = np.nan
        return {"state": s}
    if e == 2:
        return {"video": None}
    if e == 3:
        return {"video_frames": length - 2}
    if e == 5:
        return {"video": b"this is not an mp4 file" * 10}
    if e == 6:
        return {"truncate_video": 0.5}
    if e == 7:
        table = episode_table(e, length, 0, 0)
        sink = pa.BufferOutputStream()
        pq.write_table(table, sink)
        data = sink.getvalue().to_pybytes()
        return {"parquet": data[: len(data) * 2 // 3]}
    return {}


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    out = sys.argv[1]
    if os.path.exists(out):
        shutil.rmtree(out)
    os.makedirs(out)
    write_v21(f"{out}/lerobot_v21", [10, 12, 9], {"observation.images.top": (64, 48), "observation.images.wrist": (64, 32)})
    write_v21(f"{out}/lerobot_v21_bad", [12, 12, 12, 12, 3, 12, 12, 12], {"observation.images.top": (64, 48)}, bad_episode)
    write_v21_images(f"{out}/lerobot_v21_images", [6, 5], (64, 48))
    write_v30(f"{out}/lerobot_v30", [10, 12, 9], {"observation.images.top": (64, 64), "observation.images.wrist": (64, 64)},
              lambda e: 0 if e < 2 else 1)
    for e, length in enumerate([8, 10]):
        write_robotwin_original(f"{out}/robotwin/original", e, length)
        write_robotwin_2026(f"{out}/robotwin/v2026", e, length)
    print(f"fixtures written to {out}")


if __name__ == "__main__":
    main()
