"""teacher.py's chunk layout, the actions it gives the world model, and its scoring, on hand-made
episodes (the recipe's toy run, tests/metaworld_bench.rs, runs it against a served world model)."""

import contextlib
import io
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import mw  # noqa: E402
import study  # noqa: E402
import teacher  # noqa: E402


def test_chunks_follow_the_evaluate_loops_layout():
    layout = teacher.chunk_layout(horizon=60, chunk=24, history=8)
    # x0 alone first; then x0 and the 8 frames before each chunk; the last chunk cut at the horizon.
    assert layout[0] == ([0], list(range(1, 25)))
    assert layout[1] == ([0] + list(range(17, 25)), list(range(25, 49)))
    assert layout[2] == ([0] + list(range(41, 49)), list(range(49, 61)))
    assert len(layout) == 3
    # A history longer than the frames so far starts at frame 1, never repeating x0.
    assert teacher.chunk_layout(horizon=10, chunk=4, history=8)[1] == ([0, 1, 2, 3, 4], [5, 6, 7, 8])


def test_x0_acts_with_the_initial_state_and_each_frame_with_its_command():
    commands = np.arange(12, dtype=np.float32).reshape(3, 4)
    actions = teacher.frame_actions("drawer-open-v3", commands)
    assert actions.shape == (4, 4) and actions.dtype == np.float32
    assert np.array_equal(actions[0], mw.initial_state("drawer-open-v3"))
    assert np.array_equal(actions[1:], commands)


def test_rates_count_an_episode_drawn_succeeding_in_any_chunk():
    episode = lambda first, real, drawn: {"seed": 0, "first": first, "real": real, "drawn": drawn}
    results = {"t": {
        # Both succeed; the model draws it a chunk late (chunk 0 missed, chunk 1 agrees).
        "a": [episode(20, [0.9, 0.9], [0.1, 0.8]), episode(30, [0.2, 0.9], [0.1, 0.9])],
        # Neither succeeds in the simulator; the model invents an opening in one chunk of one.
        "b": [episode(None, [0.1, 0.1], [0.1, 0.7]), episode(None, [0.0, 0.2], [0.3, 0.4])],
    }}
    s = teacher.summarize(results, ["t"], ["a", "b"])
    a, b = s["rates"]
    assert (a["true"], a["judged_simulator"], a["teacher_forced"], a["chunks_missed"], a["chunks_invented"]) == (1.0, 1.0, 1.0, 1, 0), a
    assert (b["true"], b["judged_simulator"], b["teacher_forced"], b["chunks_missed"], b["chunks_invented"]) == (0.0, 0.0, 0.5, 0, 1), b
    counts = {k: s["chunks"][k] for k in ("invented", "missed", "both_success", "both_fail")}
    assert counts == {"invented": 1, "missed": 1, "both_success": 2, "both_fail": 4}, s["chunks"]
    assert s["chunks"]["n"] == 8 and s["chunks"]["agreement"] == 6 / 8, s["chunks"]
    assert s["all"]["teacher_forced"]["mae"] == 0.25 and s["all"]["judged_simulator"]["mae"] == 0.0, s["all"]
    assert s["per_task"]["t"]["teacher_forced"]["best_ranked_first"], s["per_task"]


def test_episodes_asked_at_once_come_back_in_their_order_with_their_own_seeds():
    class Served:
        def __init__(self):
            self.seeds = []

        def chunk(self, frames, actions, seed):
            self.seeds.append(seed)
            # The chunk drawn: the last given frame held (the fake judge reads its value).
            return np.repeat(frames[-1:], 24, axis=0)

    class Judge:
        def judge(self, ask):
            return {"success_probability": float(ask["frames"].mean()) / 255}

    layout = teacher.chunk_layout(horizon=48, chunk=24, history=8)
    recorded = [(seed, None, np.full((49, 2, 2, 3), 10 * k, np.uint8), np.zeros((49, 4), np.float32), np.array([k, -k, 0.5]))
                for k, seed in enumerate([7, 3, 9, 1, 5])]
    positions = {("drawer-open-v3", seed): p for p, seed in enumerate([7, 3, 9, 1, 5])}
    served = Served()
    out = teacher.teacher_forced("drawer-open-v3", "expert", recorded, served, Judge(), layout, positions, requests=3)
    assert [e["seed"] for e in out] == [7, 3, 9, 1, 5], out
    assert [e["drawn"] for e in out] == [[round(10 * k / 255, 4)] * 2 for k in range(5)], out
    assert [e["offset_at_closest_cm"] for e in out] == [[k, -k, 0.5] for k in range(5)], out
    assert sorted(served.seeds) == sorted(p * 1000 + c for p in range(5) for c in range(2)), served.seeds

def test_own_episodes_are_the_datasets_frames_states_and_outcomes_placed_by_their_replay():
    import json
    import tempfile

    import pyarrow as pa
    import pyarrow.parquet as pq
    from PIL import Image

    import generate
    import policies

    task = "drawer-open-v3"
    with tempfile.TemporaryDirectory() as d:
        root = os.path.join(d, "data")
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            generate.main(["--tasks", task, "--episodes", "4", "--frames", "100", "--resolution", "32", "--mix", "near=1",
                           "--workers", "1", "--out", root])
        with open(os.path.join(root, "meta", "episodes.jsonl")) as f:
            meta = [json.loads(line) for line in f]
        misses = [e for e in meta if e["behaviour"] == "near"][:2]
        assert len(misses) == 2, meta
        picked = study.dataset_episodes(root, [task], 2, ["near"], tool="teacher")
        assert [e["episode_index"] for e in picked[task]] == [e["episode_index"] for e in misses], picked
        assert [e["position"] for e in picked[task]] == [meta.index(e) for e in misses], picked

        recorded = teacher.record_own(root, picked, 32, 2)
        assert list(recorded[task]) == ["near"], recorded.keys()
        for e, (seed, first, frames, actions, nearest) in zip(misses, recorded[task]["near"]):
            table = pq.read_table(os.path.join(root, f"data/chunk-000/episode_{e['episode_index']:06d}.parquet"))
            # The frames stay in their file until the world model draws from them.
            assert seed == e["seed"] and isinstance(frames, teacher.EpisodeFrames) and len(frames) == 100
            cells = table.column("observation.image").to_pylist()
            pixels = np.asarray(frames)
            assert pixels.shape == (100, 32, 32, 3) and pixels.dtype == np.uint8
            assert np.array_equal(pixels[-1], np.asarray(Image.open(io.BytesIO(cells[-1]["bytes"])).convert("RGB")))
            # Frames other than the dataset's meta/info.json promises are not drawn from.
            try:
                np.asarray(teacher.EpisodeFrames(frames.path, frames.column, 100, (64, 64)))
            except ValueError as err:
                assert "(100, 32, 32, 3)" in str(err) and "(64, 64)" in str(err), err
            else:
                raise AssertionError("frames of another size were taken")
            # The actions are what `bwm prepare` trains on; the truth is the dataset's own flags.
            assert np.array_equal(actions, np.asarray(table.column("observation.state").to_pylist(), np.float32))
            flags = table.column("success").to_pylist()
            assert first == (flags.index(True) if True in flags else None), (first, e)
            # The closest approach is the simulator's for this episode's commands: where the miss aimed.
            replayed = policies.replay(task, seed, np.asarray(table.column("action").to_pylist(), np.float32)[:99])
            assert np.array_equal(nearest, replayed.nearest_cm) and np.linalg.norm(nearest[:2]) > 0, nearest

        try:
            teacher.record_own(root, picked, 64, 1)
        except SystemExit as err:
            assert str(err) == f"teacher: {root}: frames of 32x32, but --resolution is 64", err
        else:
            raise AssertionError("frames of another resolution were taken")

        # An episode whose flags its commands do not reproduce is not this simulator's: refused by name.
        path = os.path.join(root, f"data/chunk-000/episode_{misses[0]['episode_index']:06d}.parquet")
        table = pq.read_table(path)
        flags = table.column("success").to_pylist()
        table = table.set_column(table.column_names.index("success"), "success", pa.array([not flags[-1]] * len(flags)))
        pq.write_table(table, path)
        try:
            teacher.record_own(root, picked, 32, 1)
        except SystemExit as err:
            assert f"episode {misses[0]['episode_index']}'s commands replayed" in str(err) and "not this simulator's episode" in str(err), err
        else:
            raise AssertionError("an episode with foreign success flags was taken")
        try:
            study.dataset_episodes(root, [task], 2, ["decoy"], tool="teacher")
        except SystemExit as err:
            assert str(err) == f"teacher: {root} holds no episodes of {task} of behaviour decoy", err
        else:
            raise AssertionError("no episodes of a behaviour went unnoticed")


def test_own_episodes_take_behaviours_not_variants():
    for args, message in ((["--own-episodes", "--variants", "expert"], "with --own-episodes pick the dataset's episodes by --behaviours"),
                          (["--behaviours", "near"], "--behaviours picks the dataset's own episodes (--own-episodes)")):
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                teacher.main(["--data", "x", "--judge", "y", "--out", "z", *args, "--", "--checkpoint", "c"])
        except SystemExit as e:
            assert e.code == 2, e
        else:
            raise AssertionError(f"ran with {args}")
        assert message in err.getvalue(), err.getvalue()


def test_the_world_models_flags_are_required():
    try:
        teacher.main(["--data", "x", "--judge", "y", "--out", "z"])
    except SystemExit as e:
        assert e.code == 2, e
    else:
        raise AssertionError("ran without the world model's flags")



def test_a_full_queue_is_asked_again_and_other_refusals_end_the_run():
    import http.server
    import threading

    answers = [(503, b"server busy"), (503, b"server busy"), (200, b"drawn"), (400, b"bad frames"), (503, b"server busy")]
    seen = []

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_POST(self):
            seen.append(self.rfile.read(int(self.headers["Content-Length"])))
            code, text = answers.pop(0)
            self.send_response(code)
            self.send_header("Content-Length", str(len(text)))
            self.end_headers()
            self.wfile.write(text)

        def log_message(self, *args):
            pass

    server = http.server.HTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_port}/v1/chunk"
        assert teacher.post(url, b"body") == b"drawn"
        assert seen == [b"body"] * 3, seen
        try:
            teacher.post(url, b"body")
        except SystemExit as e:
            assert str(e) == "teacher: bwm serve answered 400: bad frames", e
        else:
            raise AssertionError("a 400 was not an error")
        try:
            teacher.post(url, b"body", patience=0)
        except SystemExit as e:
            assert str(e) == "teacher: bwm serve answered 503: server busy", e
        else:
            raise AssertionError("a full queue was waited on past the patience")
    finally:
        server.shutdown()
        server.server_close()

def test_counts_below_one_are_refused_by_name():
    for flag in ("--chunk", "--history", "--episodes"):
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                teacher.main(["--data", "x", "--judge", "y", "--out", "z", flag, "0", "--", "--checkpoint", "c"])
        except SystemExit as e:
            assert e.code == 2, e
        else:
            raise AssertionError(f"ran with {flag} 0")
        assert f"argument {flag}: must be at least 1, got 0" in err.getvalue(), err.getvalue()
    assert study.split_flags(["--a", "1", "--", "--b", "--", "c"]) == (["--a", "1"], ["--b", "--", "c"])
    assert study.split_flags(["--a"]) == (["--a"], [])

if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
