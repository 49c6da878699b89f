"""generate.py's expert behaviour per --spread, on its per-episode draws (no simulator)."""

import os
import sys
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import generate  # noqa: E402
from mw import ACTION_SCALE  # noqa: E402

TASK = "drawer-open-v3"


def behaviours(spread, n=300):
    return [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, 0.4, spread) for seed in range(n)]


def test_narrow_experts_are_quiet_and_at_full_speed():
    bs = behaviours("narrow")
    assert all(0.05 <= b.noise <= 0.4 and b.speed == 1.0 for b in bs)
    misses = [np.linalg.norm(b.offset) for b in bs if b.mode == "miss"]
    assert misses and max(misses) <= 0.12 + 1e-9


def test_wide_experts_spread_noise_and_speed():
    bs = behaviours("wide")
    noise = np.array([b.noise for b in bs])
    assert noise.min() >= 0.05 and noise.max() <= 1.2
    assert (noise > 0.6).mean() > 0.1, "log-uniform up to 1.2 puts about a fifth above 0.6"
    capped = [b.speed for b in bs if b.speed < 1.0]
    assert 0.2 < len(capped) / len(bs) < 0.4 and min(capped) >= 0.3
    misses = [np.linalg.norm(b.offset) for b in bs if b.mode == "miss"]
    assert max(misses) > 0.12 and max(misses) <= 0.15 + 1e-9


def test_an_unknown_spread_is_refused():
    try:
        generate.Behaviour(TASK, generate.episode_rng(TASK, 0), 120, 0.4, "Wide")
    except ValueError as e:
        assert "Wide" in str(e)
    else:
        raise AssertionError("an unknown spread was accepted")


def test_the_miss_range_is_where_misses_steer():
    near = [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, 0.4, "narrow", (0.01, 0.06)) for seed in range(300)]
    radii = np.array([np.linalg.norm(b.offset) for b in near if b.mode == "miss"])
    assert len(radii) > 20 and radii.min() >= 0.01 - 1e-9 and radii.max() <= 0.06 + 1e-9
    # The range changes no other draw: the same seeds give the same modes, noise and experts' offsets.
    default = behaviours("narrow")
    assert [b.mode for b in near] == [b.mode for b in default]
    assert all(a.noise == b.noise for a, b in zip(near, default))
    assert all((a.offset == b.offset).all() for a, b in zip(near, default) if a.mode != "miss")
    for bad in ((0.05, 0.01), (-0.01, 0.02)):
        try:
            generate.Behaviour(TASK, generate.episode_rng(TASK, 0), 120, 0.4, "narrow", bad)
        except ValueError as e:
            assert "miss range" in str(e)
        else:
            raise AssertionError(f"the miss range {bad} was accepted")


def test_miss_cm_is_parsed_in_cm():
    args = generate.parse_args(["--task", TASK, "--episodes", "1", "--out", "/nonexistent/x", "--miss-cm", "1,6"])
    assert args.miss_cm == (0.01, 0.06)
    assert generate.parse_args(["--task", TASK, "--episodes", "1", "--out", "/nonexistent/x"]).miss_cm is None
    for bad in ("6,1", "1", "a,b"):
        try:
            generate.parse_args(["--task", TASK, "--episodes", "1", "--out", "/nonexistent/x", "--miss-cm", bad])
        except SystemExit:
            pass
        else:
            raise AssertionError(f"--miss-cm {bad} was accepted")


def test_decoys_steer_on_a_fresh_placement_and_weight_zero_changes_nothing():
    import policies

    lo, hi = policies.OBJECT_RANGE[TASK]
    with_decoys = [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, 0.4, "narrow", None, 3.0) for seed in range(300)]
    decoys = [b for b in with_decoys if b.mode == "decoy"]
    # 40% degraded, decoys 3 of the 12 weights among them: about 30 of 300.
    assert 15 <= len(decoys) <= 50, len(decoys)
    obj = np.array([0.05, 0.73, 0.09])
    for b in decoys:
        target = b.decoy.copy()
        assert ((target >= lo - 1e-12) & (target <= hi + 1e-12)).all(), target
        b.command(0, np.array([0.0, 0.6, 0.2, -1.0], np.float32), obj)
        assert np.allclose(obj + b.offset, target) and b.decoy is None
    # Their aims are spread over the range, not clustered at the object.
    assert np.ptp([obj[0] + b.offset[0] for b in decoys]) > 0.15
    default = behaviours("narrow")
    zero = [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, 0.4, "narrow", None, 0.0) for seed in range(300)]
    assert [b.mode for b in zero] == [b.mode for b in default] and "decoy" not in {b.mode for b in zero}
    assert all(a.noise == b.noise and (a.offset == b.offset).all() for a, b in zip(zero, default))
    bad_weights_are_refused("decoy")


def bad_weights_are_refused(mode):
    """A negative or non-finite weight of `mode` ("decoy" or "miss") is refused by Behaviour and
    on the command line."""
    for bad in (-1.0, float("nan"), float("inf")):
        weights = {"decoy_weight": 0.0, "miss_weight": 3.0, f"{mode}_weight": bad}
        try:
            generate.Behaviour(TASK, generate.episode_rng(TASK, 0), 120, 0.4, "narrow", None, **weights)
        except ValueError as e:
            assert f"{mode} weight" in str(e)
        else:
            raise AssertionError(f"the {mode} weight {bad} was accepted")
        try:
            generate.parse_args(["--task", TASK, "--episodes", "1", "--out", "/nonexistent/x", f"--{mode}-weight", str(bad)])
        except SystemExit:
            pass
        else:
            raise AssertionError(f"--{mode}-weight {bad} was accepted")


def test_a_speed_cap_bounds_the_experts_steps():
    b = next(b for b in behaviours("wide") if b.speed < 0.6 and b.mode == "expert")
    b.noise, b.explore[:] = 0.0, False
    # Far from the handle: the expert's gain saturates the action, so the cap is what limits a step.
    state, obj = np.array([-0.3, 0.4, 0.05, -1.0], np.float32), np.array([0.05, 0.73, 0.09])
    steps = []
    for t in range(30):
        command = b.command(t, state, obj)
        steps.append(np.abs(command[:3] - state[:3]).max())
        state = command
    assert max(steps) <= b.speed * ACTION_SCALE + 1e-6 and max(steps) > 0.9 * b.speed * ACTION_SCALE, (b.speed, max(steps))


def boundary_file(directory, radii_cm, degrees=None, max_cm=16.0, name="boundary.json"):
    import json

    path = os.path.join(directory, name)
    degrees = degrees if degrees is not None else [k * 360 / len(radii_cm) for k in range(len(radii_cm))]
    with open(path, "w") as f:
        json.dump({"max_cm": max_cm, "tasks": {TASK: {"directions_deg": degrees, "boundary_cm": radii_cm}}}, f)
    return path


def test_the_default_draws_are_those_the_recipe_was_measured_on():
    """Every option added to the generator since run 22 (2026-11-27) leaves the default episodes as
    they were: a digest of 1600 episodes' draws, taken with the generator of commit 6a58b7e."""
    import hashlib

    h = hashlib.sha256()
    for task in ("drawer-open-v3", "button-press-topdown-v3"):
        for spread in ("narrow", "wide"):
            for decoy in (0.0, 3.0):
                for seed in range(200):
                    b = generate.Behaviour(task, generate.episode_rng(task, seed), 120, 0.4, spread, None, decoy)
                    decoy_at = None if b.decoy is None else np.round(b.decoy, 12).tolist()
                    h.update(repr((b.mode, np.round(b.offset, 12).tolist(), round(b.noise, 12), round(b.speed, 12), b.explore.tolist(),
                                   b.hold.tolist(), b.burst.tolist(), decoy_at)).encode())
                    h.update(repr(b.rng.bit_generator.state).encode())
    assert h.hexdigest() == "46d4904554d8048bc019b932728dd1a8bd084c4cb8dbf6d8d5cc8c882627458b", h.hexdigest()


def test_misses_around_a_boundary_steer_as_far_off_as_it_is_in_their_direction():
    import tempfile

    import boundary

    with tempfile.TemporaryDirectory() as d:
        # 2 cm toward +x, 8 toward +y, 4 toward -x, 6 toward -y.
        around = boundary.load(boundary_file(d, [2.0, 8.0, 4.0, 6.0]), [TASK])
    assert np.isclose(around.radius(TASK, 0.0), 0.02) and np.isclose(around.radius(TASK, np.pi / 2), 0.08)
    assert np.isclose(around.radius(TASK, np.pi / 4), 0.05), "linear between measured directions"
    assert np.isclose(around.radius(TASK, 7 * np.pi / 4), 0.04) and np.isclose(around.radius(TASK, -np.pi / 4), 0.04), "wraps at 360 deg"
    bs = [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, 0.4, "narrow", around) for seed in range(300)]
    misses = [b.offset for b in bs if b.mode == "miss"]
    assert len(misses) > 20
    factors = [np.linalg.norm(o) / around.radius(TASK, np.arctan2(o[1], o[0])) for o in misses]
    assert min(factors) >= boundary.FACTOR[0] - 1e-9 and max(factors) <= boundary.FACTOR[1] + 1e-9, factors
    assert all(o[2] == 0 for o in misses)
    # Both sides of the boundary, in every quadrant.
    assert sum(f < 1 for f in factors) >= 3 and sum(f > 1 for f in factors) >= 3
    assert len({int(np.arctan2(o[1], o[0]) // (np.pi / 2)) for o in misses}) == 4
    # Where misses steer changes no other draw, now or later in the episode (the same number of
    # draws: the generator's state after them is the same).
    default = behaviours("narrow")
    assert [b.mode for b in bs] == [b.mode for b in default]
    assert all(a.noise == b.noise and (a.offset == b.offset).all() for a, b in zip(bs, default) if a.mode != "miss")
    assert all(a.rng.bit_generator.state == b.rng.bit_generator.state for a, b in zip(bs, default))
    # With a factor from 1.1 every miss lies beyond its direction's boundary, in every quadrant.
    beyond = replace(around, factor=(1.1, 2.0))
    outside = [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, 0.4, "narrow", beyond) for seed in range(300)]
    outside = [b.offset for b in outside if b.mode == "miss"]
    factors = [np.linalg.norm(o) / beyond.radius(TASK, np.arctan2(o[1], o[0])) for o in outside]
    assert len(outside) == len(misses) and min(factors) >= 1.1 - 1e-9 and max(factors) <= 2.0 + 1e-9, factors
    assert len({int(np.arctan2(o[1], o[0]) // (np.pi / 2)) for o in outside}) == 4
    # Never beyond the farthest distance measured: a boundary at it draws misses up to it, not past.
    with tempfile.TemporaryDirectory() as d:
        capped = boundary.load(boundary_file(d, [2.0, 8.0, 4.0, 6.0], max_cm=8.0), [TASK])
    rng = np.random.default_rng(0)
    reach = [np.linalg.norm(capped.draw(TASK, rng)) for _ in range(2000)]
    assert max(reach) <= 0.08 + 1e-12 and sum(r > 0.0799 for r in reach) > 100


def test_a_bad_boundary_file_is_refused():
    import json
    import tempfile

    import boundary

    with tempfile.TemporaryDirectory() as d:
        cases = {
            "non-positive": boundary_file(d, [2.0, 0.0, 4.0, 6.0], name="zero.json"),
            "past max_cm": boundary_file(d, [2.0, 20.0, 4.0, 6.0], name="far.json"),
            "boolean": boundary_file(d, [2.0, True, 4.0, 6.0], name="bool.json"),
            "uneven": boundary_file(d, [2.0, 3.0, 4.0], degrees=[0, 90, 180], name="uneven.json"),
            "lengths": boundary_file(d, [2.0, 3.0], degrees=[0, 90, 180], name="lengths.json"),
            "text directions": boundary_file(d, [2.0, 3.0], degrees=["a", "b"], name="text.json"),
            "no max_cm": boundary_file(d, [2.0, 3.0], max_cm=None, name="nomax.json"),
        }
        cases["not a report"] = os.path.join(d, "list.json")
        with open(cases["not a report"], "w") as f:
            f.write("[1, 2]")
        cases["missing"] = os.path.join(d, "missing.json")
        for name, path in cases.items():
            try:
                boundary.load(path, [TASK])
            except ValueError as e:
                assert path in str(e), e
            else:
                raise AssertionError(f"the {name} boundary file was accepted")
        good = boundary_file(d, [2.0, 8.0, 4.0, 6.0])
        # A task the file does not cover is refused, in the class and on the command line.
        try:
            boundary.load(good, [TASK, "button-press-topdown-v3"])
        except ValueError as e:
            assert "button-press-topdown-v3" in str(e)
        else:
            raise AssertionError("a boundary without the button was accepted for it")
        out = ["--episodes", "1", "--out", os.path.join(d, "x")]
        args = generate.parse_args(["--task", TASK, *out, "--miss-boundary", good])
        assert isinstance(args.miss, boundary.Boundary) and args.miss_cm is None and args.miss.factor == boundary.FACTOR
        args = generate.parse_args(["--task", TASK, *out, "--miss-boundary", good, "--miss-factor", "1.1,2"])
        assert args.miss.factor == (1.1, 2.0)
        for argv in (["--tasks", f"{TASK},button-press-topdown-v3", "--miss-boundary", good],
                     ["--task", TASK, "--miss-boundary", good, "--miss-cm", "2,12"],
                     ["--task", TASK, "--miss-boundary", cases["uneven"]],
                     ["--task", TASK, "--miss-boundary", ""],
                     ["--task", TASK, "--miss-factor", "1.1,2"],
                     ["--task", TASK, "--miss-boundary", good, "--miss-factor", "0,2"],
                     ["--task", TASK, "--miss-boundary", good, "--miss-factor", "2,1"],
                     ["--task", TASK, "--miss-boundary", good, "--miss-factor", "1,inf"],
                     ["--task", TASK, "--miss-boundary", good, "--miss-factor", "1.5"]):
            try:
                generate.parse_args([*argv, *out])
            except SystemExit:
                pass
            else:
                raise AssertionError(f"{argv} was accepted")


def test_the_miss_weight_sets_how_many_episodes_miss():
    default = behaviours("narrow")
    more = [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, 0.4, "narrow", None, 0.0, 9.0) for seed in range(300)]
    count = lambda bs: sum(b.mode == "miss" for b in bs)  # noqa: E731
    # 40% degraded: misses 3 of 9 weights (about 40 of 300), or 9 of 15 (about 72).
    assert count(more) > count(default) + 15, (count(more), count(default))
    assert [b.mode for b in more if b.mode == "expert"] and sum(b.mode == "expert" for b in more) == sum(b.mode == "expert" for b in default)
    bad_weights_are_refused("miss")
    assert generate.parse_args(["--task", TASK, "--episodes", "1", "--out", "/nonexistent/x", "--miss-weight", "9"]).miss_weight == 9.0


def test_between_looks_the_expert_takes_the_handle_to_follow_its_pull():
    """With --observe-every the expert sees the object only every few frames: a pull in front of a
    handle that stays behind (a miss) goes on as long as the look is away, where the expert that
    sees every frame stops it once the handle is 15 cm behind."""
    import tells
    from mw import next_state

    obj = np.array([0.0, 0.73, 0.09])

    def missed_pull(observe):
        b = generate.Behaviour(TASK, generate.episode_rng(TASK, 0), 120, 0.0, "narrow", observe_every=observe)
        b.noise, b.explore[:], b.offset = 0.0, False, np.array([0.0, -0.05, 0.0])
        state, states = np.array([0.0, 0.6, 0.2, -1.0], np.float32), []
        for t in range(120):
            states.append(state)
            state = next_state(state, b.command(t, state, obj))
            if t % b.observe_every == 0:
                assert np.array_equal(b.belief, obj), (t, b.belief)
        return b, tells.pull_cm(states)

    every, every_cm = missed_pull((1, 1))
    assert every.observe_every == 1 and 5 < every_cm < 18, every_cm
    chunked, chunked_cm = missed_pull((40, 40))
    assert chunked.observe_every == 40 and chunked_cm > every_cm + 5, (chunked_cm, every_cm)
    # Drawn per episode within the range, after every other draw.
    drawn = [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, 0.4, "narrow", observe_every=(1, 48)) for seed in range(100)]
    assert {b.observe_every for b in drawn} <= set(range(1, 49)) and len({b.observe_every for b in drawn}) > 20
    assert [b.mode for b in drawn] == [b.mode for b in behaviours("narrow", 100)]
    for bad in ((0, 4), (5, 4)):
        try:
            generate.Behaviour(TASK, generate.episode_rng(TASK, 0), 120, 0.4, "narrow", observe_every=bad)
        except ValueError as e:
            assert "observation interval" in str(e), e
        else:
            raise AssertionError(f"the interval {bad} was accepted")
    args = ["--task", TASK, "--episodes", "1", "--out", "/nonexistent/x"]
    assert generate.parse_args(args).observe_every == (1, 1)
    assert generate.parse_args(args + ["--observe-every", "8,40"]).observe_every == (8, 40)
    for bad in ("0,4", "5,4", "8", "a,b"):
        try:
            generate.parse_args(args + ["--observe-every", bad])
        except SystemExit:
            pass
        else:
            raise AssertionError(f"--observe-every {bad} was accepted")


def test_a_dataset_records_its_settings_and_is_reused_only_with_the_same():
    import contextlib
    import io
    import json
    import shutil
    import tempfile

    here = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "boundary.json")

    def make(out, *extra):
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            generate.main(["--task", TASK, "--episodes", "1", "--frames", "8", "--resolution", "16", "--workers", "1",
                           "--miss-boundary", here, "--observe-every", "8,40", "--out", out, *extra])
        return err.getvalue()

    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "data")
        make(out)
        with open(os.path.join(out, "meta", "generator.json")) as f:
            recorded = json.load(f)["settings"]
        assert recorded["observe_every"] == [8, 40] and recorded["tasks"] == [TASK] and recorded["frames"] == 8, recorded
        assert len(recorded["miss_boundary"]["sha256"]) == 64 and recorded["miss_cm"] is None, recorded
        parquet = os.path.join(out, "data", "chunk-000", "episode_000000.parquet")
        before = os.stat(parquet).st_mtime_ns

        # The same settings: kept as they are, whatever --workers.
        assert "exists, made with these settings" in make(out, "--reuse")
        assert os.stat(parquet).st_mtime_ns == before
        # Other settings: refused, naming what differs, and nothing touched.
        try:
            make(out, "--reuse", "--observe-every", "1,1")
        except SystemExit as e:
            assert str(e).startswith(f"generate.py: {out} was made with other settings (observe_every: [8, 40] there, [1, 1] asked)"), e
        else:
            raise AssertionError("data of other settings were reused")
        assert os.stat(parquet).st_mtime_ns == before
        # Without --reuse or --force an existing folder is refused; both at once are too.
        for extra in ((), ("--reuse", "--force")):
            try:
                with contextlib.redirect_stderr(io.StringIO()):
                    make(out, *extra)
            except SystemExit as e:
                assert e.code == 2, e
            else:
                raise AssertionError(f"{extra} over an existing dataset was accepted")
        # A dataset made before the settings were recorded is taken unchecked, and says so.
        os.remove(os.path.join(out, "meta", "generator.json"))
        assert "holds no meta/generator.json" in make(out, "--reuse", "--observe-every", "1,1")
        shutil.rmtree(out)


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
