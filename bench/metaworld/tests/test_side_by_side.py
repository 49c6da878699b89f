"""side_by_side.py on a hand-made study folder: the world model's sheet rows interleaved with the
simulator's frames of the same actions, and the simulator's outcome of them."""

import contextlib
import io
import json
import os
import shutil
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import policies  # noqa: E402
import side_by_side  # noqa: E402
import variants  # noqa: E402

TASK, SEEDS, SIZE = "drawer-open-v3", [100000, 100001], 32


def make_study(root: str, actions: list, sheet: np.ndarray | None = None) -> None:
    with open(os.path.join(root, "episode_seeds.json"), "w") as f:
        json.dump({TASK: SEEDS}, f)
    ev = os.path.join(root, "eval-0")
    os.makedirs(os.path.join(ev, "videos", "wrong", TASK))
    with open(os.path.join(ev, "evaluate.toml"), "w") as f:
        f.write(f'horizon = 120\nresolution = "{SIZE}x{SIZE}"\n')
    records = [{"policy": "wrong", "task": TASK, "episode": 0, "success": True, "actions": actions,
                "video": f"videos/wrong/{TASK}/episode_000.png"},
               {"policy": "wrong", "task": TASK, "episode": 1, "success": False, "actions": actions,
                "video": f"videos/wrong/{TASK}/episode_001.mp4"},
               {"policy": "expert", "task": TASK, "episode": 0, "success": True, "actions": actions}]
    with open(os.path.join(ev, "episodes.jsonl"), "w") as f:
        f.write("".join(json.dumps(r) + "\n" for r in records))
    # The world model's sheet of episode 0 (30 frames: a row of 24 and one of 6), one grey; episode
    # 1's is an MP4 (a bwm built with FFmpeg).
    open(os.path.join(ev, "videos", "wrong", TASK, "episode_001.mp4"), "wb").close()
    from PIL import Image

    if sheet is None:
        sheet = np.full((2 * SIZE, 24 * SIZE, 3), 200, np.uint8)
    Image.fromarray(sheet).save(os.path.join(ev, "videos", "wrong", TASK, "episode_000.png"))


def test_the_world_models_rows_alternate_with_the_simulators_of_the_same_actions():
    expert = variants.run_episode(TASK, "expert", SEEDS[0], resolution=SIZE)
    actions = expert.commands[:30].tolist()
    truth = policies.replay(TASK, SEEDS[0], actions, resolution=SIZE, record=True)
    assert truth.frames.shape == (31, SIZE, SIZE, 3) and len(truth.commands) == 30
    assert abs(float(np.linalg.norm(truth.nearest_cm)) - truth.approach_cm) < 1e-6, (truth.nearest_cm, truth.approach_cm)
    root, out = tempfile.mkdtemp(), tempfile.mkdtemp()
    try:
        make_study(root, actions)
        from PIL import Image

        side_by_side.main(["--study", root, "--task", TASK, "--variant", "wrong", "--out", out])
        with open(os.path.join(out, "side_by_side.json")) as f:
            report = json.load(f)
        assert report["resolution"] == SIZE and [e["episode"] for e in report["episodes"]] == [0], report
        e = report["episodes"][0]
        assert e["world_model_success"] and e["world_model_sheet"] and e["seed"] == SEEDS[0], e
        assert e["simulator_first_success"] == truth.first and e["closest_approach_cm"] == round(truth.approach_cm, 2), (e, truth)
        image = np.asarray(Image.open(os.path.join(out, e["image"])))
        assert image.shape == (4 * SIZE, 24 * SIZE, 3), image.shape
        rows = [image[k * SIZE : (k + 1) * SIZE] for k in range(4)]
        assert (rows[0] == 200).all() and (rows[2] == 200).all()
        # The simulator's rows: its frames after each command, 24 then 6 and black after them.
        assert np.array_equal(rows[1][:, :SIZE], truth.frames[1]) and np.array_equal(rows[3][:, 5 * SIZE : 6 * SIZE], truth.frames[30])
        assert not rows[3][:, 6 * SIZE :].any()
        assert not [n for n in os.listdir(out) if n.endswith(".tmp")]
        assert len(e["psnr_db_by_chunk"]) == 2 and all(p < 30 for p in e["psnr_db_by_chunk"]), e

        # A world model that drew the simulator's frames exactly, but for its second chunk.
        exact = np.concatenate([rows[1], rows[3]]).copy()
        exact[SIZE:, :SIZE] = 255 - exact[SIZE:, :SIZE]
        shutil.rmtree(root)
        os.makedirs(root)
        make_study(root, actions, exact)
        side_by_side.main(["--study", root, "--task", TASK, "--variant", "wrong", "--out", out])
        with open(os.path.join(out, "side_by_side.json")) as f:
            psnr = json.load(f)["episodes"][0]["psnr_db_by_chunk"]
        assert psnr[0] is None and psnr[1] is not None and psnr[1] < 30, psnr

        # An episode without a contact sheet: the simulator alone, and why.
        said = io.StringIO()
        with contextlib.redirect_stdout(said):
            side_by_side.main(["--study", root, "--task", TASK, "--variant", "wrong", "--episodes", "1", "--out", out])
        assert "episode_001.mp4 is not a PNG contact sheet" in said.getvalue(), said.getvalue()
        with open(os.path.join(out, "side_by_side.json")) as f:
            e = json.load(f)["episodes"][0]
        assert not e["world_model_sheet"] and not e["world_model_success"], e
        assert np.asarray(Image.open(os.path.join(out, e["image"]))).shape == (2 * SIZE, 24 * SIZE, 3)

        # What the study does not hold is named.
        for args, what in ((["--variant", "wrong", "--episodes", "5"], "no episode 5 of wrong"),
                           (["--variant", "blind"], "no episodes of blind"),
                           (["--variant", "wrong", "--task", "button-press-topdown-v3"], "ran no button-press-topdown-v3")):
            argv = ["--study", root, "--task", TASK, "--out", out, *args]
            err = io.StringIO()
            try:
                with contextlib.redirect_stderr(err):
                    side_by_side.main(argv)
            except SystemExit as x:
                said = f"{x.code} {err.getvalue()}"
                assert x.code != 0 and what in said, (argv, said)
            else:
                raise AssertionError(f"accepted {argv}")
    finally:
        shutil.rmtree(root)
        shutil.rmtree(out)


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
