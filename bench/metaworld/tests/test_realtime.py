"""realtime.py on hand-made agreement and study files: each setting's change against the reference
in the open and closed loop, the issue's bounds, settings not studied, and a missing reference."""

import json
import os
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
import realtime  # noqa: E402


def study(r, invented, missed, families):
    return {"all": {"pearson_r": r, "spearman_rho": r, "mae": 0.05, "best_ranked_first": True},
            "per_episode": {"n": 100, "invented": invented, "missed": missed},
            "per_family": {name: {"pearson_r": v} for name, v in families.items()}}


def write(rt, recorded, studies):
    """agreement.json over roll/NAME for NAME -> PSNR against the recorded frames (reference: the
    first), and study-NAME/study.json for NAME -> study."""
    names = list(recorded)
    settings = {os.path.join(rt, "roll", n): {"episodes": 2, "reference_h": 100.0 if i == 0 else 40.0,
                                                "reference_full": 90.0, "recorded_h": v, "recorded_full": v - 1}
                for i, (n, v) in enumerate(recorded.items())}
    with open(os.path.join(rt, "agreement.json"), "w") as f:
        json.dump({"reference": os.path.join(rt, "roll", names[0]), "horizon": 32, "settings": settings}, f)
    for name, s in studies.items():
        os.makedirs(os.path.join(rt, f"study-{name}"))
        with open(os.path.join(rt, f"study-{name}", "study.json"), "w") as f:
            json.dump(s, f)


def test_each_setting_against_the_reference_within_the_bounds_or_not():
    rt = tempfile.mkdtemp()
    try:
        write(rt, {"t50-full": 27.0, "s1-light": 26.7, "t1-full": 26.3, "s2-light": 27.1},
              {"t50-full": study(0.95, 10, 12, {"learned": 0.85, "wander": 0.99}),
               "s1-light": study(0.94, 11, 12, {"learned": 0.84, "wander": 0.98}),
               "s2-light": study(0.92, 20, 5, {"learned": 0.80, "wander": 0.97})})
        r = realtime.report(rt, "t50-full")
        rows = r["settings"]
        assert rows["t50-full"]["within"] and rows["t50-full"]["closed_loop"]["pearson_r_change"] == 0
        # 0.3 dB under and 0.01 r under the reference: within.
        assert abs(rows["s1-light"]["open_loop"]["recorded_h_change"] + 0.3) < 1e-9
        assert abs(rows["s1-light"]["closed_loop"]["pearson_r_change"] + 0.01) < 1e-9 and rows["s1-light"]["within"]
        # 0.7 dB under (open loop alone, not studied): out.
        assert "closed_loop" not in rows["t1-full"] and rows["t1-full"]["within"] is False
        # Better frames, r 0.03 under: out.
        assert rows["s2-light"]["within"] is False
        assert rows["s2-light"]["closed_loop"]["families"] == {"learned": 0.80, "wander": 0.97}
        assert (rows["s2-light"]["closed_loop"]["invented"], rows["s2-light"]["closed_loop"]["missed"]) == (20, 5)
        text = realtime.table(r)
        assert "not studied" in text and text.count("\n") == 4

        # Where every rate is drawn alike r is undefined: shown as such, and out where the
        # reference's rates vary.
        with open(os.path.join(rt, "study-s1-light", "study.json"), "w") as f:
            json.dump(study(None, 0, 0, {"learned": None}), f)
        rows = realtime.report(rt, "t50-full")["settings"]
        assert "pearson_r_change" not in rows["s1-light"]["closed_loop"] and rows["s1-light"]["within"] is False
        assert "n/a" in realtime.table(realtime.report(rt, "t50-full"))
        # Within the open loop's bound but not studied: unchecked, not within.
        with open(os.path.join(rt, "agreement.json")) as f:
            a = json.load(f)
        a["settings"][os.path.join(rt, "roll", "t2-full")] = dict(a["settings"][os.path.join(rt, "roll", "s1-light")])
        with open(os.path.join(rt, "agreement.json"), "w") as f:
            json.dump(a, f)
        report = realtime.report(rt, "t50-full")
        assert report["settings"]["t2-full"]["within"] is None and "unchecked" in realtime.table(report)
        # The reference not studied: no setting's closed loop can be checked.
        shutil.rmtree(os.path.join(rt, "study-t50-full"))
        rows = realtime.report(rt, "t50-full")["settings"]
        assert rows["s2-light"]["within"] is None and "pearson_r_change" not in rows["s2-light"]["closed_loop"]
        # Restored for the command below.
        os.makedirs(os.path.join(rt, "study-t50-full"))
        with open(os.path.join(rt, "study-t50-full", "study.json"), "w") as f:
            json.dump(study(0.95, 10, 12, {"learned": 0.85, "wander": 0.99}), f)
        with open(os.path.join(rt, "study-s1-light", "study.json"), "w") as f:
            json.dump(study(0.94, 11, 12, {"learned": 0.84, "wander": 0.98}), f)

        out = os.path.join(rt, "realtime.json")
        run = subprocess.run([sys.executable, os.path.join(HERE, "..", "realtime.py"), rt, "--json", out],
                             capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        with open(out) as f:
            assert json.load(f)["settings"]["s1-light"]["within"]
        # A reference the agreement does not hold is refused by name.
        run = subprocess.run([sys.executable, os.path.join(HERE, "..", "realtime.py"), rt, "--reference", "t20-full"],
                             capture_output=True, text=True)
        assert run.returncode != 0 and "no setting t20-full" in run.stderr, run.stderr
    finally:
        shutil.rmtree(rt)


def test_a_folder_without_the_agreement_is_refused():
    rt = tempfile.mkdtemp()
    try:
        run = subprocess.run([sys.executable, os.path.join(HERE, "..", "realtime.py"), rt], capture_output=True, text=True)
        assert run.returncode != 0 and "agreement.json" in run.stderr, run.stderr
    finally:
        shutil.rmtree(rt)


if __name__ == "__main__":
    test_each_setting_against_the_reference_within_the_bounds_or_not()
    test_a_folder_without_the_agreement_is_refused()
    print("ok")
