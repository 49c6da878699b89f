"""Checks a generate.py dataset against what the generator promises; prints a JSON summary.

    python check_dataset.py DATASET [DATASET ...]

Per episode: LeRobot v2.1 layout and metadata, frames of the declared size, one action per frame,
`observation.state` a pure function of the initial state and the actions (mw.next_state),
`action_delta` the Meta-World action that state change is, the success flags consistent with the
episode record and with `obj_to_target` under the task's success rule (mw.SUCCESS_DISTANCE). Across datasets: no seed of one task appears in two of them (the train and
validation splits are split by seed).
"""

import io
import json
import os
import sys

import numpy as np
import pyarrow.parquet as pq
from PIL import Image

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from mw import SUCCESS_DISTANCE, delta_action, initial_state, next_state  # noqa: E402


def check(root: str) -> dict:
    info = json.load(open(os.path.join(root, "meta", "info.json")))
    assert info["codebase_version"] == "v2.1", info["codebase_version"]
    size = info["features"]["observation.image"]["shape"]
    episodes = [json.loads(line) for line in open(os.path.join(root, "meta", "episodes.jsonl"))]
    stats = [json.loads(line) for line in open(os.path.join(root, "meta", "episodes_stats.jsonl"))]
    assert len(episodes) == len(stats) == info["total_episodes"]
    seeds, successes = {}, 0
    for e in episodes:
        task = e["tasks"][0]
        path = os.path.join(root, info["data_path"].format(episode_chunk=e["episode_index"] // info["chunks_size"], episode_index=e["episode_index"]))
        t = pq.read_table(path).to_pydict()
        n = e["length"]
        assert len(t["frame_index"]) == n and t["frame_index"] == list(range(n)), path
        image = np.asarray(Image.open(io.BytesIO(t["observation.image"][0]["bytes"])))
        assert list(image.shape) == size, (image.shape, size)
        state, action, delta = (np.array(t[k], np.float32) for k in ("observation.state", "action", "action_delta"))
        assert np.array_equal(state[0], initial_state(task)), (state[0], task)
        for i in range(n - 1):
            assert np.array_equal(state[i + 1], next_state(state[i], action[i])), (path, i)
            assert np.array_equal(delta[i], delta_action(state[i], action[i])), (path, i)
        flags = np.array(t["success"], bool)
        assert bool(flags.any() or t["next.success"][-1]) == e["success"], path
        # Meta-World's rule on the object's distance to its goal gives the flag of every frame
        # (frame 0's too: no task starts done).
        distance = np.array(t["obj_to_target"], np.float32)
        assert np.array_equal(flags, distance <= np.float32(SUCCESS_DISTANCE[task])), (path, flags, distance)
        successes += e["success"]
        seeds.setdefault(task, set()).add(e["seed"])
    return {"episodes": len(episodes), "frames": sum(e["length"] for e in episodes), "successes": successes,
            "tasks": sorted(seeds), "seeds": {k: sorted(v) for k, v in seeds.items()}}


def main() -> None:
    reports = {root: check(root) for root in sys.argv[1:]}
    roots = list(reports)
    for i, a in enumerate(roots):
        for b in roots[i + 1 :]:
            for task in set(reports[a]["seeds"]) & set(reports[b]["seeds"]):
                shared = set(reports[a]["seeds"][task]) & set(reports[b]["seeds"][task])
                assert not shared, f"{task}: seeds {sorted(shared)} are in both {a} and {b}"
    print(json.dumps(reports))


if __name__ == "__main__":
    main()
