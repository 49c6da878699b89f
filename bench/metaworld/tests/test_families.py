"""families.py: every family's policies act within the mocap's bounds and repeat themselves for a
seed, the splits are as declared, unknown names are refused (through variants.py too, and
policies.py knows only its own variants: neither it nor families.py imports variants.py), a few real
simulator episodes per family come out as their variants say, and a cloned policy is trained once
and then read from the cache (cloned here from 1 or 2 demos, into a temporary cache)."""

import os
import re
import shutil
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
CACHE = tempfile.mkdtemp(prefix="bwm-families-")
os.environ["BWM_POLICY_CACHE"] = CACHE
import families  # noqa: E402
import mw  # noqa: E402
import policies  # noqa: E402
import variants  # noqa: E402

TINY = dict(demos=1, resolution=64, steps=300)


def first_frames():
    mw.select_gl()
    frames = {}
    for task in mw.TASKS:
        with mw.Sim(task, 100000, 64) as sim:
            frames[task] = sim.reset()
    return frames


FRAMES = first_frames()


def episode(task, policy, seed, horizon=120, chunk=24):
    """The first success step of `policy` in the simulator (None: none within the horizon)."""
    with mw.Sim(task, seed, 64) as sim:
        image, state = sim.reset()
        for t in range(0, horizon, chunk):
            for k, command in enumerate(policy.act(image, state, min(chunk, horizon - t))):
                image, state, done = sim.step(command, render=k == chunk - 1)
                if done:
                    return t + k + 1
    return None


def policies_of_every_family(task, seed):
    """One policy per variant (the cloned ones tiny), by variant name."""
    out = {}
    for name, f in families.FAMILIES.items():
        for v in f.params:
            if name == "learned":
                out[v] = families.learned_policy(task, f.params[v]["kind"], seed=seed, **TINY)
            else:
                out[v] = families.make_policy(task, v, seed)
    return out


def test_every_policy_acts_within_the_mocaps_bounds_and_repeats_itself_for_a_seed():
    for task, (image, state) in FRAMES.items():
        a, b, c = (policies_of_every_family(task, seed) for seed in (7, 7, 8))
        for v in a:
            for n in (24, 30, 5):  # more than a cloned chunk, then fewer
                x, y, z = a[v].act(image, state, n), b[v].act(image, state, n), c[v].act(image, state, n)
                assert x.shape == (n, 4) and x.dtype == np.float32, (v, x.shape, x.dtype)
                assert np.all(x[:, :3] >= mw.MOCAP_LOW) and np.all(x[:, :3] <= mw.MOCAP_HIGH), (v, x)
                assert np.all(np.abs(x[:, 3]) <= 1), (v, x)
                assert np.array_equal(x, y), f"{task} {v}: the same seed gave other commands"
                # (A lagging policy holds still the first steps of a chunk, whatever its seed.)
                assert n == 5 or not np.array_equal(x, z), f"{task} {v}: another seed gave the same commands"


def test_the_variants_come_in_their_splits_under_unique_safe_names():
    assert {n: f.split for n, f in families.FAMILIES.items()} == {
        "learned": "test", "scripted": "development", "partial": "development", "wander": "test"}
    test, development = families.variants("test"), families.variants("development")
    assert test == list(families.LEARNED) + list(families.WANDER), test
    assert development == list(families.SCRIPTED) + list(families.PARTIAL), development
    assert families.variants() == test[:6] + development + test[6:]
    every = families.variants()
    assert len(set(every)) == len(every), every
    assert not set(every) & {v for names in policies.VARIANTS.values() for v in names}
    for v in every:
        assert re.fullmatch(r"[a-z0-9][a-z0-9.-]*", v), v
        assert not policies.GRADED.fullmatch(v), v
        assert variants.check_variants(list(mw.TASKS), [v]) is None, v
        for task in mw.TASKS:
            assert v in families.FAMILIES[families.family_of(v)].variants[task], (task, v)
    for f in families.FAMILIES.values():
        assert 4 <= len(f.params) <= 6, f.params
    assert families.family_of("expert") is None and families.family_of("lag-6") == "scripted"
    assert variants.check_variants(list(mw.TASKS), ["expert", "wrong-2cm", "short-2cm", "bc-net-4"]) is None


def refused(fn, *words):
    try:
        fn()
    except ValueError as e:
        for w in words:
            assert w in str(e), (w, str(e))
    else:
        raise AssertionError(f"accepted: {fn}")


def test_unknown_names_are_refused_naming_the_known_ones():
    task = "drawer-open-v3"
    refused(lambda: families.make_policy(task, "lag-7", 0), "'lag-7'", "lag-6", "bc-nn-1", "wander-2cm")
    refused(lambda: families.make_policy("door-open-v3", "lag-6", 0), "door-open-v3", task)
    refused(lambda: families.variants("train"), "'train'", "development", "test")
    refused(lambda: families.learned_policy(task, "svm", 1), "'svm'", "nn", "net")
    refused(lambda: variants.make_policy(task, "lag-7", 0), "'lag-7'", "expert", "wrong-<d>cm", "families:", "short-2cm")
    problem = variants.check_variants([task], ["expert", "short-9cm"])
    assert "'short-9cm'" in problem and "short-2cm" in problem, problem
    assert "door-open-v3" in variants.check_variants(["door-open-v3"], ["lag-6"])
    # policies.py alone knows (and names) its own variants only.
    try:
        policies.Policy(task, "lag-6", 0)
    except ValueError as e:
        assert "'lag-6'" in str(e) and "wrong-<d>cm" in str(e) and "families" not in str(e) and "bc-nn-1" not in str(e), str(e)
    else:
        raise AssertionError("policies.Policy accepted a family's variant")


def test_policies_and_families_do_not_import_the_variants_above_them():
    import subprocess

    here = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
    for module, absent in (("policies", ("families", "variants")), ("families", ("variants",))):
        code = f"import sys; import {module}; print([m for m in {absent!r} if m in sys.modules])"
        out = subprocess.run([sys.executable, "-c", code], cwd=here, capture_output=True, text=True, check=True).stdout
        assert out.strip() == "[]", (module, out)


def test_simulator_episodes_end_as_their_variants_say():
    for task in mw.TASKS:
        for seed in (100000, 100001):  # quit-50 goes past in the first, quits in the second
            # Past the boundary opens / presses; 5 cm short never does, nor do the straight
            # approach and a hand wandering within 2 cm; the wanderer that turns to the task at
            # step 80 succeeds.
            assert variants.run_episode(task, "over-2cm", seed).first is not None, (task, seed)
            for v in ("short-5cm", "straight", "wander-2cm"):
                e = variants.run_episode(task, v, seed)
                assert e.first is None, (task, v, seed, e.first)
            assert variants.run_episode(task, "wander-then-80", seed).first is not None, (task, seed)
            # A quitting policy fails exactly in the episodes it quits in, at least 2 cm short.
            quits = families.make_policy(task, "quit-50", seed).depth < families.BOUNDARY[task] - 0.019
            assert quits == (seed == 100001), (task, seed)
            assert (variants.run_episode(task, "quit-50", seed).first is None) == quits, (task, seed, quits)
            # The closest approach of a wandering hand: it touches the object.
            assert variants.run_episode(task, "wander-2cm", seed).approach_cm < 3, (task, seed)


def test_a_clone_of_one_demo_succeeds_where_the_demo_did_and_acts_elsewhere():
    for task in mw.TASKS:
        for kind in ("nn", "net"):
            clone = lambda seed: families.learned_policy(task, kind, seed=seed, **TINY)
            assert episode(task, clone(1), families.DEMO_SEED_START) is not None, (task, kind)
            episode(task, clone(2), 100000)


def test_a_clone_is_trained_once_then_read_from_the_cache():
    task, image, state = "button-press-topdown-v3", *FRAMES["button-press-topdown-v3"]
    args = dict(kind="net", demos=2, demo_seed_start=600000, resolution=32, steps=100)
    before = len(families.TRAINED)
    first = families.learned_policy(task, seed=3, **args).act(image, state, 24)
    made = families.TRAINED[before:]
    # One network and its two demos, each in its own file.
    assert len(made) == 3 and sum("demo-" in os.path.basename(p) for p in made) == 2, made
    stamps = {p: os.stat(p).st_mtime_ns for p in made}
    families._models.clear()  # as a fresh process would
    again = families.learned_policy(task, seed=3, **args).act(image, state, 24)
    assert len(families.TRAINED) == before + 3, families.TRAINED[before:]
    assert stamps == {p: os.stat(p).st_mtime_ns for p in made}
    assert np.array_equal(first, again)
    # A clone that shares demos trains only itself; another demo range is another clone.
    families.learned_policy(task, "nn", 2, 600000, resolution=32)
    assert len(families.TRAINED) == before + 4, families.TRAINED[before:]
    other = families.learned_policy(task, "nn", 1, 600001, seed=3, resolution=32)
    assert len(families.TRAINED) == before + 5 and not np.array_equal(other.act(image, state, 24), first)
    assert not any(name.endswith(".tmp") for name in os.listdir(CACHE)), os.listdir(CACHE)


def test_frames_of_any_resolution_shrink_alike():
    image = FRAMES["drawer-open-v3"][0]
    big = np.repeat(np.repeat(image, 2, 0), 2, 1)
    assert np.allclose(families.small(image), families.small(big), atol=1e-6)
    odd = np.full((50, 70, 3), 51, np.uint8)
    assert families.small(odd).shape == (families.SIZE, families.SIZE, 3)
    assert np.allclose(families.small(odd), 0.2, atol=1e-6)


if __name__ == "__main__":
    try:
        for name, fn in list(globals().items()):
            if name.startswith("test_"):
                fn()
                print(f"{name}: ok", flush=True)
    finally:
        shutil.rmtree(CACHE, ignore_errors=True)
