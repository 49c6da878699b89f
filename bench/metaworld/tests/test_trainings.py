"""trainings.py on hand-made studies: averaging trainings lifts r only where their errors differ."""

import json
import os
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
import trainings  # noqa: E402

TRUE = [1.0, 0.8, 0.5, 0.2, 0.0]


def study(estimates, true=TRUE):
    return {"rates": [{"task": "t", "variant": f"v{i}", "true": t, "estimated": e}
                      for i, (t, e) in enumerate(zip(true, estimates))]}


def test_opposite_errors_cancel_in_the_average_and_a_shared_bias_does_not():
    c = trainings.compare({"a": study([1.0, 0.6, 0.8, 0.2, 0.0]), "b": study([1.0, 1.0, 0.2, 0.2, 0.0])})
    assert c["pearson_r"]["a"] < 0.95 and c["pearson_r"]["b"] < 0.95, c["pearson_r"]
    assert abs(c["pairs"][0]["pearson_r_of_mean"] - 1.0) < 1e-9, c["pairs"]
    assert abs(c["pairs"][0]["mean_abs_difference"] - 0.2) < 1e-9, c["pairs"]
    assert abs(c["all_mean"]["mae"]) < 1e-9
    # Both draw the failing rate at 0.6: the average keeps that error.
    shared = trainings.compare({"a": study([1.0, 0.8, 0.5, 0.2, 0.6]), "b": study([0.9, 0.8, 0.5, 0.3, 0.6])})
    assert shared["all_mean"]["pearson_r"] < 0.8, shared["all_mean"]
    row = shared["rates"][-1]
    assert (row["mean"], row["low"], row["high"]) == (0.6, 0.6, 0.6) and abs(row["bias"] - 0.6) < 1e-9, row
    assert shared["single"]["max"] < 0.8


def test_every_pair_and_the_mean_of_all_are_scored():
    c = trainings.compare({n: study([1.0, 0.8, 0.5, 0.2, x]) for n, x in (("a", 0.1), ("b", 0.2), ("c", 0.3))})
    assert [(p["a"], p["b"]) for p in c["pairs"]] == [("a", "b"), ("a", "c"), ("b", "c")]
    assert c["single"]["min"] == c["pearson_r"]["c"] and c["single"]["max"] == c["pearson_r"]["a"], c
    assert c["pair_means"]["min"] < c["pair_means"]["max"]
    assert abs(c["rates"][-1]["mean"] - 0.2) < 1e-9


def test_studies_of_other_episodes_are_refused():
    for other, what in ((study([0.0] * 5, true=[1.0, 0.8, 0.5, 0.2, 0.1]), "another truth for t/v4"),
                        ({"rates": study([0.0] * 5)["rates"][:4]}, "other rates (t/v4)"),
                        ({"rates": [{"task": "t"}]}, "not a study.json")):
        try:
            trainings.compare({"a": study([0.0] * 5), "b": other})
        except ValueError as e:
            assert what in str(e), e
        else:
            raise AssertionError(f"compared a study with {what}")
    try:
        trainings.compare({"a": study([0.0] * 5)})
    except ValueError as e:
        assert "at least two" in str(e), e
    else:
        raise AssertionError("compared one study")


def test_only_the_families_asked_for_are_compared():
    # policies.py's `expert` is of the degraded family, `lag-6` of scripted, `quit-50` of partial:
    # the partial rate's truth differs between the studies, as after a regrading.
    a = {"rates": [{"task": "t", "variant": v, "true": t, "estimated": e}
                   for v, t, e in (("expert", 1.0, 0.9), ("lag-6", 0.5, 0.7), ("quit-50", 0.5, 0.5))]}
    b = {"rates": [{"task": "t", "variant": v, "true": t, "estimated": e}
                   for v, t, e in (("expert", 1.0, 1.0), ("lag-6", 0.5, 0.3), ("quit-50", 0.2, 0.2))]}
    try:
        trainings.compare({"a": a, "b": b})
    except ValueError as e:
        assert "another truth for t/quit-50" in str(e), e
    else:
        raise AssertionError("compared studies of another truth")
    c = trainings.compare({"a": a, "b": b}, ["degraded", "scripted"])
    assert [r["variant"] for r in c["rates"]] == ["expert", "lag-6"], c["rates"]
    assert abs(c["rates"][1]["mean"] - 0.5) < 1e-9
    try:
        trainings.compare({"a": a, "b": b}, ["wander"])
    except ValueError as e:
        assert "no rate of the families wander" in str(e), e
    else:
        raise AssertionError("compared no rates")


def test_the_command_reads_files_and_writes_its_json():
    d = tempfile.mkdtemp()
    try:
        paths = []
        for name, est in (("study-x1.json", [1.0, 0.6, 0.8, 0.2, 0.0]), ("study-x2.json", [1.0, 1.0, 0.2, 0.2, 0.0])):
            paths.append(os.path.join(d, name))
            with open(paths[-1], "w") as f:
                json.dump(study(est), f)
        out = os.path.join(d, "compare.json")
        script = os.path.join(HERE, "..", "trainings.py")
        p = subprocess.run([sys.executable, script, *paths, "--json", out], capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        assert "x1 + x2: estimates 0.200 apart on average, r of their mean 1.000" in p.stdout, p.stdout
        with open(out) as f:
            assert set(json.load(f)["pearson_r"]) == {"x1", "x2"}
        assert not os.path.exists(out + ".tmp")
        # The same name twice, and a file that is not there, are named errors.
        p = subprocess.run([sys.executable, script, paths[0], paths[0]], capture_output=True, text=True)
        assert p.returncode == 2 and "two studies are named x1" in p.stderr, p.stderr
        p = subprocess.run([sys.executable, script, paths[0], os.path.join(d, "none.json")], capture_output=True, text=True)
        assert p.returncode == 2 and "cannot read" in p.stderr, p.stderr
    finally:
        shutil.rmtree(d)


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
