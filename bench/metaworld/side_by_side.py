"""A study's world-model episodes beside the simulator's frames of the same actions.

    python side_by_side.py --study runs/s8/study --task drawer-open-v3 --variant wrong \\
        [--episodes 0,1,2] --out DIR

For each chosen episode of one task and variant of a finished study (study.py): the actions its
policy sent through the world model's frames (eval-*/episodes.jsonl) are issued in the simulator
from the same placement (episode_seeds.json), every frame rendered at the study's resolution
(eval-*/evaluate.toml). Writes DIR/VARIANT-TASK-episode_NNN.png: where `bwm evaluate` wrote the
world model's contact sheet of that episode (its videos/, 24 frames a row, as `bwm` writes it
without FFmpeg; an MP4 is left out), its rows interleaved with the simulator's (world model, simulator, world model,
...); else the simulator's rows alone. Prints per episode, and writes to DIR/side_by_side.json:
the world model's verdict, the simulator's outcome of the same actions, how close the hand came
to the object there, with its offset at that moment (cm, world x, y, z), and where a sheet was
kept, the world model's frames against the simulator's (PSNR per chunk of 24 frames: where they
part). So one can see
whether the world model drew the hand where the actions put it, and what it drew happening.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from files import replacing, write_json  # noqa: E402

PER_ROW = 24  # frames per row of bwm's contact sheets (`write_mp4_or_sheet`'s in `bwm evaluate`)


def load_study(study: str, task: str, variant: str) -> tuple[dict[int, dict], list[int], int, list[str]]:
    """The records of `variant` on `task` by episode, the task's seeds, the frame size, and the
    eval folders they came from."""
    seeds_path = os.path.join(study, "episode_seeds.json")
    if not os.path.isfile(seeds_path):
        raise SystemExit(f"side_by_side: no {seeds_path} (is {study} a study.py folder?)")
    with open(seeds_path) as f:
        seeds = json.load(f)
    if task not in seeds:
        raise SystemExit(f"side_by_side: the study ran no {task} (it ran {', '.join(seeds)})")
    from study import read_estimates

    records, resolution, folders = {}, None, []
    for folder in sorted(glob.glob(os.path.join(study, "eval-*"))):
        # One folder at a time, so that each record knows where its video is; a folder without
        # episodes (a process that wrote none) is passed over as a cut study's is.
        mine = read_estimates([folder], cut=True).get(task, {}).get(variant, [])
        if not mine:
            continue
        folders.append(folder)
        for r in mine:
            r["_folder"] = folder
            records[int(r["episode"])] = r
        with open(os.path.join(folder, "evaluate.toml")) as f:
            found = re.search(r'^resolution\s*=\s*"(\d+)x(\d+)"', f.read(), re.M)
        if found:
            resolution = int(found.group(1))
    if not records:
        raise SystemExit(f"side_by_side: no episodes of {variant} on {task} in {study}/eval-*/episodes.jsonl")
    if resolution is None:
        raise SystemExit(f"side_by_side: no resolution in {', '.join(folders)}'s evaluate.toml")
    return records, seeds[task], resolution, folders


def sheet_rows(image: np.ndarray, size: int) -> list[np.ndarray]:
    """A contact sheet of `size`-pixel frames cut into its rows."""
    if image.shape[0] % size or image.shape[1] % size:
        raise ValueError(f"a sheet of {image.shape[1]}x{image.shape[0]} is not made of {size}x{size} frames")
    return [image[r : r + size] for r in range(0, image.shape[0], size)]


def sim_rows(frames: np.ndarray) -> list[np.ndarray]:
    """The simulator's frames after each command (x0 left out, as the world model's sheet starts
    with its first generated frame), laid out as bwm lays its sheets out."""
    frames = frames[1:]
    size = frames.shape[1]
    rows = []
    for start in range(0, len(frames), PER_ROW):
        row = np.zeros((size, PER_ROW * size, 3), np.uint8)
        for i, f in enumerate(frames[start : start + PER_ROW]):
            row[:, i * size : (i + 1) * size] = f
        rows.append(row)
    return rows


def sheet_frames(rows: list[np.ndarray], size: int, n: int) -> np.ndarray:
    """The first `n` frames of a contact sheet's rows, in order."""
    frames = [row[:, c : c + size] for row in rows for c in range(0, row.shape[1], size)]
    if len(frames) < n:
        raise ValueError(f"the sheet holds {len(frames)} frames, the episode {n}")
    return np.stack(frames[:n])


def psnr_by_chunk(world_model: np.ndarray, simulator: np.ndarray, chunk: int = PER_ROW) -> list[float | None]:
    """PSNR (dB) of the world model's frames against the simulator's over each chunk of `chunk`
    frames (of the chunk's mean squared error); None for a chunk drawn exactly."""
    err = ((world_model.astype(np.float64) - simulator.astype(np.float64)) ** 2).reshape(len(world_model), -1).mean(1)
    means = [float(err[start : start + chunk].mean()) for start in range(0, len(err), chunk)]
    return [None if m == 0 else round(10 * np.log10(255.0**2 / m), 2) for m in means]


def interleave(world_model: list[np.ndarray], simulator: list[np.ndarray]) -> np.ndarray:
    """Rows of both, world model first; the shorter sheet's missing rows left black."""
    width = max(r.shape[1] for r in world_model + simulator)
    blank = lambda r: np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)))
    out = []
    for k in range(max(len(world_model), len(simulator))):
        for rows in (world_model, simulator):
            out.append(blank(rows[k]) if k < len(rows) else np.zeros_like(blank(simulator[0])))
    return np.concatenate(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--study", required=True, help="a study.py folder with episode_seeds.json and eval-*/")
    ap.add_argument("--task", required=True)
    ap.add_argument("--variant", required=True)
    ap.add_argument("--episodes", help="comma-separated episode indices (default: those whose sheet the study kept, else the first 4)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    from PIL import Image

    import policies

    records, seeds, resolution, _ = load_study(a.study, a.task, a.variant)
    video = lambda r: os.path.join(r["_folder"], r["video"]) if r.get("video") else None
    # bwm writes an MP4 where it was built with FFmpeg, a PNG contact sheet otherwise.
    sheet = lambda r: video(r) if video(r) and video(r).endswith(".png") and os.path.isfile(video(r)) else None
    if a.episodes:
        try:
            chosen = [int(e) for e in a.episodes.split(",")]
        except ValueError:
            ap.error(f"--episodes takes comma-separated whole numbers, got {a.episodes!r}")
        if missing := [e for e in chosen if e not in records]:
            ap.error(f"no episode {', '.join(map(str, missing))} of {a.variant} on {a.task} in the study")
    else:
        chosen = [e for e in sorted(records) if sheet(records[e])] or sorted(records)[:4]
    os.makedirs(a.out, exist_ok=True)
    report = []
    for e in chosen:
        r = records[e]
        if "actions" not in r:
            raise SystemExit(f"side_by_side: episode {e} kept no actions (a `bwm evaluate` that did not record them)")
        if e >= len(seeds):
            raise SystemExit(f"side_by_side: episode {e} has no seed in episode_seeds.json ({len(seeds)} for {a.task})")
        replayed = policies.replay(a.task, seeds[e], r["actions"], resolution, record=True)
        rows = sim_rows(replayed.frames)
        path = sheet(r)
        drawn = path is not None
        why = f"its video {os.path.basename(video(r))} is not a PNG contact sheet" if video(r) and os.path.isfile(video(r)) else "no world-model sheet"
        psnr = None
        if drawn:
            try:
                wm_rows = sheet_rows(np.asarray(Image.open(path).convert("RGB")), resolution)
            except ValueError as err:
                raise SystemExit(f"side_by_side: {path}: {err}") from None
            image = interleave(wm_rows, rows)
            n = min(int(r.get("frames", len(r["actions"]))), len(replayed.frames) - 1)
            psnr = psnr_by_chunk(sheet_frames(wm_rows, resolution, n), replayed.frames[1 : n + 1])
        else:
            image = np.concatenate(rows)
        name = f"{a.variant}-{a.task}-episode_{e:03d}.png"
        with replacing(os.path.join(a.out, name), "wb") as f:
            Image.fromarray(image).save(f, format="PNG")
        row = {"episode": e, "seed": seeds[e], "world_model_success": bool(r["success"]), "simulator_first_success": replayed.first,
               "closest_approach_cm": round(replayed.approach_cm, 2), "offset_at_closest_cm": [round(float(v), 2) for v in replayed.nearest_cm],
               "world_model_sheet": drawn, "psnr_db_by_chunk": psnr, "image": name}
        report.append(row)
        print(f"side_by_side: {a.variant}/{a.task} episode {e} (seed {seeds[e]}): world model {'success' if row['world_model_success'] else 'failure'}, "
              f"simulator {'success at step %d' % replayed.first if replayed.first else 'failure'}; hand closest {row['closest_approach_cm']} cm "
              f"off (x, y, z {', '.join(map(str, row['offset_at_closest_cm']))})"
              f"{'; world model against simulator, PSNR by chunk ' + ', '.join('exact' if p is None else f'{p} dB' for p in psnr) if drawn else ''}"
              f"; {name}{'' if drawn else f' (the simulator alone: {why})'}",
              flush=True)
    write_json(os.path.join(a.out, "side_by_side.json"),
               {"study": os.path.abspath(a.study), "task": a.task, "variant": a.variant, "resolution": resolution, "episodes": report})


if __name__ == "__main__":
    main()
