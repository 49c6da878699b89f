"""sweep.py's choice of the default sampler setting on hand-made fidelity and study outputs."""

import json
import os
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import sweep  # noqa: E402


def write_setting(root, name, psnr, rates, pearson_r=0.9):
    """One setting folder: PSNR at h=32 per task, success estimates per variant of task t."""
    os.makedirs(os.path.join(root, name, "fidelity"))
    os.makedirs(os.path.join(root, name, "study"))
    h = lambda v: {"horizons": {"32": {"model": {"psnr": v, "ssim": 0.9}}}}
    fidelity = {"all": h(sum(psnr.values()) / len(psnr)), "tasks": {t: h(v) for t, v in psnr.items()}}
    study = {"rates": [{"task": "t", "variant": v, "estimated": r} for v, r in rates.items()],
             "all": {"pearson_r": pearson_r, "best_ranked_first": True}}  # None: rates without spread
    json.dump(fidelity, open(os.path.join(root, name, "fidelity", "fidelity.json"), "w"))
    json.dump(study, open(os.path.join(root, name, "study", "study.json"), "w"))


def test_the_default_is_the_fewest_steps_within_both_bounds():
    with tempfile.TemporaryDirectory() as root:
        write_setting(root, "euler-50", {"a": 30.0, "b": 28.0}, {"x": 0.50, "y": 0.90})
        # 4 steps: PSNR fine but one success estimate 6 points off.
        write_setting(root, "dpm++2m-4", {"a": 29.9, "b": 27.9}, {"x": 0.56, "y": 0.90})
        # 8 Euler steps: task b drops 0.7 dB (the mean over tasks only 0.35).
        write_setting(root, "euler-8", {"a": 30.0, "b": 27.3}, {"x": 0.50, "y": 0.90})
        # 8 DPM steps: within both bounds.
        write_setting(root, "dpm++2m-8", {"a": 29.8, "b": 27.7}, {"x": 0.52, "y": 0.89})
        write_setting(root, "euler-20", {"a": 30.0, "b": 28.0}, {"x": 0.50, "y": 0.90}, pearson_r=None)
        # 12 Euler steps: one estimate 4 points off, the mean change 2 points.
        write_setting(root, "euler-12", {"a": 30.0, "b": 28.0}, {"x": 0.54, "y": 0.90})
        # FP8 at 4 steps, within both bounds: reported, never the default; nor the same in lanes.
        write_setting(root, "dpm++2m-4-fp8row", {"a": 29.9, "b": 27.9}, {"x": 0.50, "y": 0.90})
        write_setting(root, "dpm++2m-4-fp8row-streams2", {"a": 29.9, "b": 27.9}, {"x": 0.50, "y": 0.90})
        # Two lanes at 8 DPM steps: the same estimates, its stages' times from timings.tsv (the last of each).
        write_setting(root, "dpm++2m-8-streams2", {"a": 29.8, "b": 27.7}, {"x": 0.52, "y": 0.89})
        with open(os.path.join(root, "dpm++2m-8-streams2", "timings.tsv"), "w") as f:
            f.write("fidelity\t70.0\nstudy\t90.0\nstudy\t61.5\n")
        os.makedirs(os.path.join(root, "euler-30"))  # not measured yet: left out
        sweep.main([root])
        report = json.load(open(os.path.join(root, "sweep.json")))
        assert report["default"] == "dpm++2m-8", report["default"]
        by = {r["setting"]: r for r in report["settings"]}
        assert set(by) == {"euler-50", "dpm++2m-4", "dpm++2m-4-fp8row", "dpm++2m-4-fp8row-streams2", "euler-8", "dpm++2m-8",
                           "dpm++2m-8-streams2", "euler-12", "euler-20"}, set(by)
        assert not by["dpm++2m-4"]["within"] and abs(by["dpm++2m-4"]["max_rate_change"] - 0.06) < 1e-9
        assert abs(by["dpm++2m-4"]["mean_rate_change"] - 0.03) < 1e-9
        assert not by["euler-8"]["within"] and abs(by["euler-8"]["psnr_drop"] - 0.7) < 1e-9
        assert by["euler-12"]["within"], "the mean change bounds by default"
        assert by["dpm++2m-4-fp8row"]["within"] and by["dpm++2m-4-fp8row"]["fp8"] == "row"
        assert by["dpm++2m-4-fp8row-streams2"]["fp8"] == "row" and by["dpm++2m-4-fp8row-streams2"]["streams"] == 2
        assert by["dpm++2m-8-streams2"]["within"] and by["dpm++2m-8-streams2"]["streams"] == 2 and by["dpm++2m-8"]["streams"] == 1
        assert by["dpm++2m-8-streams2"]["seconds"] == {"fidelity": 70.0, "study": 61.5} and by["dpm++2m-8"]["seconds"] == {}
        assert [r["steps"] for r in report["settings"]] == [4, 4, 4, 8, 8, 8, 12, 20, 50]
        # Every estimate bounded: 12 Euler steps fall outside.
        sweep.main([root, "--rate-statistic", "max"])
        strict = {r["setting"]: r for r in json.load(open(os.path.join(root, "sweep.json")))["settings"]}
        assert not strict["euler-12"]["within"] and strict["dpm++2m-8"]["within"]


def test_without_the_baseline_the_sweep_stops_with_a_message():
    with tempfile.TemporaryDirectory() as root:
        write_setting(root, "euler-8", {"a": 30.0}, {"x": 0.5})
        try:
            sweep.main([root])
        except SystemExit as e:
            assert "baseline euler-50 was not measured" in str(e), e
        else:
            raise AssertionError("no error without the baseline")


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
