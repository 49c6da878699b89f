"""tells.py: the drawer's pull and the button's press on hand-made paths, the commands-only rule,
and both over a generated dataset and policy episodes in the simulator."""

import contextlib
import io
import json
import os
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import tells  # noqa: E402

TASK = "drawer-open-v3"


def path(*moves, start=(0.0, 0.7, 0.05)):
    """A hand path from `start` by (dy, z) moves, 1 cm per step in y."""
    p = [np.array(start)]
    for dy, z in moves:
        p.append(np.array([p[-1][0], p[-1][1] + dy / 100, z]))
    return np.stack(p)


def test_a_pull_is_the_longest_low_stretch_toward_the_robot():
    assert abs(tells.pull_cm(path(*[(-1, 0.05)] * 12)) - 12) < 1e-6
    # Travel high above the handle is no pull; rising ends one, and so does moving back.
    assert tells.pull_cm(path(*[(-1, 0.3)] * 12, start=(0.0, 0.7, 0.3))) == 0.0
    assert abs(tells.pull_cm(path(*[(-1, 0.05)] * 5, (-1, 0.2), *[(-1, 0.05)] * 3)) - 5) < 1e-6
    assert abs(tells.pull_cm(path(*[(-1, 0.05)] * 4, (1, 0.05), *[(-1, 0.05)] * 7)) - 7) < 1e-6
    # Standing still keeps a pull going (a pause, not a new pull).
    assert abs(tells.pull_cm(path(*[(-1, 0.05)] * 4, (0, 0.05), *[(-1, 0.05)] * 3)) - 7) < 1e-6


def test_a_press_is_how_far_below_its_first_height_the_hand_goes():
    assert abs(tells.press_cm(path((0, 0.15), (0, 0.12), (0, 0.18), start=(0.0, 0.7, 0.2))) - 8) < 1e-6
    assert tells.press_cm(path((0, 0.25), (0, 0.3), start=(0.0, 0.7, 0.2))) == 0.0


def test_the_commands_rule_is_the_lowest_best_threshold_of_the_data():
    data = {"miss": {"succeeded": [30.0, 32.0], "failed": [10.0, 25.0]}, "expert": {"succeeded": [34.0], "failed": [29.0]}}
    rule = tells.rule(data, {"wrong": {"succeeded": [31.0], "failed": [29.5, 35.0]}})
    # 29 fails and 30 opens: the rule at 30 sorts all six (at 32 or 34 it would not).
    assert rule["threshold"] == 30.0 and rule["data_accuracy"] == 1.0 and rule["episodes"] == 6, rule
    assert rule["variants"] == {"wrong": {"rule": 2 / 3, "true": 1 / 3}}, rule
    # A long failing pull the rule cannot sort: the best threshold misreads one episode.
    data["expert"]["failed"].append(33.0)
    rule = tells.rule(data, {})
    assert rule["threshold"] == 30.0 and abs(rule["data_accuracy"] - 6 / 7) < 1e-12, rule
    # Without both outcomes there is nothing to read.
    assert tells.rule({"miss": {"succeeded": [30.0], "failed": []}}, {}) is None
    assert tells.rule({"miss": {"succeeded": [], "failed": [3.0]}}, {}) is None


def test_tells_of_a_dataset_and_of_policies_on_its_placements():
    import generate
    import mw
    import pyarrow.parquet as pq
    import variants

    tasks = list(tells.TELLS)
    with tempfile.TemporaryDirectory() as d:
        root = os.path.join(d, "data")
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            generate.main(["--tasks", ",".join(tasks), "--episodes", "3", "--frames", "100", "--resolution", "32",
                           "--mix", "expert=1,near=1", "--workers", "1", "--out", root])
        out = tells.measure(root, tasks, None, ["wrong"], None, 2, 100, 24, 2)
        with open(os.path.join(root, "meta", "episodes.jsonl")) as f:
            meta = [json.loads(line) for line in f]
        for task in tasks:
            measure = tells.TELLS[task].measure
            mine = [e for e in meta if e["tasks"] == [task]]
            # Every episode once, under its behaviour and outcome, measured on its own states.
            got = {(b, k): sorted(g[k]) for b, g in out[task]["dataset"].items() for k in ("succeeded", "failed") if g[k]}
            want: dict = {}
            for e in mine:
                table = pq.read_table(os.path.join(root, f"data/chunk-000/episode_{e['episode_index']:06d}.parquet"))
                hand = np.concatenate([np.asarray(table.column("observation.state").to_pylist()), np.asarray(table.column("action").to_pylist())[-1:]])
                want.setdefault((e["behaviour"], "succeeded" if e["success"] else "failed"), []).append(round(measure(hand), 3))
            assert got == {k: sorted(v) for k, v in want.items()}, (task, got, want)
            # The variant on the task's first two placements, as the study runs it, from the first state.
            episodes = [variants.run_episode(task, "wrong", e["seed"], 100, 24, 32, record=True) for e in mine[:2]]
            wrong = out[task]["variants"]["wrong"]
            hands = [np.concatenate([mw.initial_state(task)[None], e.commands]) for e in episodes]
            assert sorted(wrong["failed"] + wrong["succeeded"]) == sorted(round(measure(h), 3) for h in hands)
            assert len(wrong["failed"]) == sum(e.first is None for e in episodes)
            if out[task]["rule"] is not None:
                assert set(out[task]["rule"]["variants"]) == {"wrong"}
        text = tells.report(out)
        assert all(f"{t}: the {tells.TELLS[t].name}" in text for t in tasks), text
        # A dataset without the task asked is refused by name.
        solo = os.path.join(d, "button")
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            generate.main(["--task", "button-press-topdown-v3", "--episodes", "1", "--frames", "10", "--resolution", "32", "--mix", "expert=1", "--workers", "1", "--out", solo])
        try:
            tells.measure(solo, ["drawer-open-v3"], None, [], None, 2, 100, 24, 1)
        except SystemExit as e:
            assert str(e) == f"tells: {solo} holds no episodes of drawer-open-v3", e
        else:
            raise AssertionError("a dataset without drawer episodes was measured")


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
