"""measure_boundary.py in the simulator: its brackets hold when simulated again, and the drawer's
outcome flips closer in front of the handle than beside it."""

import json
import os
import subprocess
import sys
import tempfile

import numpy as np

HERE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, HERE)
import boundary  # noqa: E402
import measure_boundary  # noqa: E402

TASK = "drawer-open-v3"
FRAMES = 100


def test_brackets_hold_and_the_report_loads():
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "boundary.json")
        subprocess.run([sys.executable, os.path.join(HERE, "measure_boundary.py"), "--tasks", TASK, "--directions", "4",
                        "--seeds", "900000:900001", "--max-cm", "16", "--tolerance-cm", "2", "--frames", str(FRAMES),
                        "--workers", "2", "--out", out], check=True)
        with open(out) as f:
            report = json.load(f)
        around = boundary.load(out, [TASK])
    row = report["tasks"][TASK]
    assert row["directions_deg"] == [0, 90, 180, 270], row
    for degrees, (found,) in zip(row["directions_deg"], row["brackets_cm"]):
        lo, hi = found
        assert hi is not None and 0 <= lo < hi <= lo + 2, found
        unit = np.array([np.cos(np.radians(degrees)), np.sin(np.radians(degrees)), 0.0])
        assert measure_boundary.succeeds(TASK, 900000, lo * unit, FRAMES), f"{degrees} deg: no success {lo} cm off"
        assert not measure_boundary.succeeds(TASK, 900000, hi * unit, FRAMES), f"{degrees} deg: a success {hi} cm off"
        assert np.isclose(around.radius(TASK, np.radians(degrees)), (lo + hi) / 200)
    # The handle is wide and the pull drags the hand along it: a hand 5 cm to its side still
    # catches it, one 5 cm in front (toward the robot, -y) does not.
    side, front = row["boundary_cm"][0], row["boundary_cm"][3]
    assert front < 5 < side, row


def test_bad_arguments_are_refused():
    for argv in (["--tasks", "nope"], ["--directions", "1"], ["--tolerance-cm", "20"], ["--seeds", "5:5"]):
        p = subprocess.run([sys.executable, os.path.join(HERE, "measure_boundary.py"), *argv, "--out", "/nonexistent/x.json"],
                           capture_output=True, text=True)
        assert p.returncode == 2 and "error" in p.stderr, (argv, p.stderr)


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
