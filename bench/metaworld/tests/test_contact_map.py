"""contact_map.py on hand-made side_by_side.py, study.py and teacher.py reports: episodes placed by where the hand came closest."""

import json
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
import contact_map  # noqa: E402


def episode(x, y, world_model, simulator):
    return {"offset_at_closest_cm": [x, y, -0.5], "world_model_success": world_model, "simulator_first_success": 90 if simulator else None}


def test_episodes_are_counted_by_axis_and_distance():
    wrong = ("drawer", "wrong", [episode(0.5, -5.0, True, False), episode(-1.0, -5.5, False, False), episode(0.2, -7.1, True, False)])
    blind = ("drawer", "blind", [episode(8.5, 1.0, True, False), episode(-8.9, -2.0, True, False), episode(1.0, 0.5, True, True)])
    button = ("button", "expert", [episode(0.1, 0.1, True, True)])
    m = contact_map.contact_map([wrong, blind, button], 2.0)
    drawer = m["drawer"]
    assert drawer["variants"] == ["wrong", "blind"]
    assert drawer["by_axis"]["-y"] == {"4-6": {"episodes": 2, "simulator": 0, "world_model": 1},
                                       "6-8": {"episodes": 1, "simulator": 0, "world_model": 1}}, drawer["by_axis"]["-y"]
    # Beside the object on either side (x) and in bands ordered by distance.
    assert list(drawer["by_axis"]["x"]) == ["0-2", "8-10"], drawer["by_axis"]["x"]
    assert drawer["by_axis"]["x"]["8-10"] == {"episodes": 2, "simulator": 0, "world_model": 2}
    assert drawer["by_axis"]["x"]["0-2"] == {"episodes": 1, "simulator": 1, "world_model": 1}
    assert drawer["by_axis"]["+y"] == {}
    assert m["button"]["by_axis"]["x"] == {"0-2": {"episodes": 1, "simulator": 1, "world_model": 1}}
    # Another band width regroups the same episodes.
    wide = contact_map.contact_map([wrong], 5.0)["drawer"]["by_axis"]["-y"]
    assert wide == {"5-10": {"episodes": 3, "simulator": 0, "world_model": 2}}, wide


def test_contact_outside_counts_far_inventions_and_near_misses():
    drawer = ("drawer", "blind", [episode(6.0, 0.0, True, False), episode(8.0, -3.0, True, True), episode(0.0, -9.0, False, False),
                                  episode(3.0, 4.0, False, True), episode(1.0, 1.0, True, True), episode(5.9, 0.0, True, False)])
    button = ("button", "noisy", [episode(0.0, 0.5, False, True), episode(0.0, 12.0, True, False)])
    out = contact_map.contact_outside([drawer, button], 6.0)
    # 6 cm on the line counts as far; 5.9 cm and the 5 cm of (3, 4) as near.
    assert out == {"beyond_cm": 6.0, "beyond": {"episodes": 4, "invented": 2}, "within": {"episodes": 4, "missed": 2}}, out
    assert contact_map.contact_outside([drawer], 5.0)["beyond"] == {"episodes": 5, "invented": 2}


def test_the_command_line_keeps_the_families_asked_for():
    with tempfile.TemporaryDirectory() as d:
        study = os.path.join(d, "study.json")
        with open(study, "w") as f:
            json.dump({"rates": [{"task": "drawer-open-v3", "variant": "blind", "replayed_episodes": [[0, True, None, 8.6, [8.5, 1.0, 0.2]]]},
                                 {"task": "drawer-open-v3", "variant": "bc-nn-1", "replayed_episodes": [[0, True, None, 9.0, [9.0, 0.0, 0.2]],
                                                                                                       [1, True, None, 7.0, [7.0, 0.0, 0.2]]]}]}, f)
        out = os.path.join(d, "map.json")
        p = subprocess.run([sys.executable, os.path.join(HERE, "..", "contact_map.py"), study, "--families", "degraded,scripted", "--json", out],
                           capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        assert "hand 6 cm or more from the object: 1 of 1 episodes drawn succeeding where the simulator does not" in p.stdout, p.stdout
        with open(out) as f:
            m = json.load(f)
        assert m["tasks"]["drawer-open-v3"]["variants"] == ["blind"] and m["families"] == ["degraded", "scripted"], m
        assert m["outside"]["beyond"] == {"episodes": 1, "invented": 1}, m
        p = subprocess.run([sys.executable, os.path.join(HERE, "..", "contact_map.py"), study, "--families", "wander"], capture_output=True, text=True)
        assert p.returncode == 2 and "no variant of the families wander" in p.stderr, p.stderr


def test_the_command_line_reads_reports_and_refuses_bad_ones():
    with tempfile.TemporaryDirectory() as d:
        good = os.path.join(d, "good.json")
        with open(good, "w") as f:
            json.dump({"task": "drawer", "variant": "wrong", "episodes": [episode(0.0, -5.0, True, False)]}, f)
        out = os.path.join(d, "map.json")
        p = subprocess.run([sys.executable, os.path.join(HERE, "..", "contact_map.py"), good, "--json", out], capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        assert "-y     4-6 cm:    1 episodes, simulator    0, world model    1" in p.stdout, p.stdout
        with open(out) as f:
            assert json.load(f)["tasks"]["drawer"]["by_axis"]["-y"]["4-6"]["world_model"] == 1
        bad = os.path.join(d, "bad.json")
        with open(bad, "w") as f:
            json.dump({"task": "drawer", "variant": "wrong", "episodes": [{"offset_at_closest_cm": [1.0]}]}, f)
        for argv, what in (([bad], "bad.json is not a study.py, side_by_side.py or teacher.py report"), ([good, good], "drawer wrong is given twice"),
                           ([good, "--band-cm", "0"], "band width must be positive"), ([os.path.join(d, "none.json")], "none.json")):
            p = subprocess.run([sys.executable, os.path.join(HERE, "..", "contact_map.py"), *argv], capture_output=True, text=True)
            assert p.returncode == 2 and what in p.stderr, (argv, p.stderr)
        # A study.json: every rate's replayed episodes [episode, drawn, replay's first success, cm, offset].
        study = os.path.join(d, "study.json")
        with open(study, "w") as f:
            json.dump({"rates": [{"task": "drawer", "variant": "blind", "replayed_episodes": [[0, True, None, 8.6, [8.5, 1.0, 0.2]],
                                                                                               [1, True, 88, 1.1, [1.0, 0.5, 0.1]]]},
                                 {"task": "button", "variant": "wrong", "replayed_episodes": [[0, False, None, 15.0, [0.0, 0.0, 15.0]]]}]}, f)
        p = subprocess.run([sys.executable, os.path.join(HERE, "..", "contact_map.py"), study, good, "--json", out], capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        with open(out) as f:
            m = json.load(f)["tasks"]
        assert m["drawer"]["variants"] == ["blind", "wrong"], m
        assert m["drawer"]["by_axis"]["x"] == {"0-2": {"episodes": 1, "simulator": 1, "world_model": 1},
                                               "8-10": {"episodes": 1, "simulator": 0, "world_model": 1}}, m
        assert m["button"]["by_axis"]["x"] == {"0-2": {"episodes": 1, "simulator": 0, "world_model": 0}}, m
        # A study whose replays kept no offsets (before they did), or that has none, is refused.
        old = os.path.join(d, "old.json")
        with open(old, "w") as f:
            json.dump({"rates": [{"task": "drawer", "variant": "blind", "replayed_episodes": [[0, True, None, 8.6]]}]}, f)
        p = subprocess.run([sys.executable, os.path.join(HERE, "..", "contact_map.py"), old], capture_output=True, text=True)
        assert p.returncode == 2 and "--rescore" in p.stderr, p.stderr
        # A teacher.json: an episode is drawn succeeding when any chunk's probability reaches the threshold.
        teacher = os.path.join(d, "teacher.json")
        drawn = lambda first, drawn, x, y: {"seed": 0, "first": first, "real": [0.0] * len(drawn), "drawn": drawn, "offset_at_closest_cm": [x, y, 0.3]}
        report = {"settings": {"threshold": 0.5}, "rates": [],
                  "episodes": {"drawer": {"miss": [drawn(None, [0.1, 0.6], 0.5, -5.0), drawn(None, [0.1, 0.4], 0.2, -5.5), drawn(70, [0.2, 0.9], 1.0, 0.2)]}}}
        with open(teacher, "w") as f:
            json.dump(report, f)
        p = subprocess.run([sys.executable, os.path.join(HERE, "..", "contact_map.py"), teacher, "--json", out], capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        with open(out) as f:
            m = json.load(f)["tasks"]
        assert m["drawer"]["variants"] == ["miss"], m
        assert m["drawer"]["by_axis"]["-y"] == {"4-6": {"episodes": 2, "simulator": 0, "world_model": 1}}, m
        assert m["drawer"]["by_axis"]["x"] == {"0-2": {"episodes": 1, "simulator": 1, "world_model": 1}}, m
        # One from before teacher.py kept the offsets is refused.
        del report["episodes"]["drawer"]["miss"][0]["offset_at_closest_cm"]
        with open(teacher, "w") as f:
            json.dump(report, f)
        p = subprocess.run([sys.executable, os.path.join(HERE, "..", "contact_map.py"), teacher], capture_output=True, text=True)
        assert p.returncode == 2 and "keep no offsets" in p.stderr, p.stderr
        assert sorted(os.listdir(d)) == ["bad.json", "good.json", "map.json", "old.json", "study.json", "teacher.json"]


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
