"""generate.py's behaviour mix on its per-episode draws, and its modes' commands (no simulator
unless said)."""

import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import generate  # noqa: E402
from mw import ACTION_SCALE  # noqa: E402

TASK = "drawer-open-v3"
# The default mix without the pool of learned policies (which trains policies on first use).
NO_POOL = {k: v for k, v in generate.MIX.items() if k != "learned"}


def behaviours(n=300, task=TASK, mix=NO_POOL, frames=120):
    return [generate.Behaviour(task, generate.episode_rng(task, seed), frames, (1, 1), mix) for seed in range(n)]


def test_the_mix_sets_each_modes_share():
    bs = behaviours(2000)
    total = sum(NO_POOL.values())
    for mode, w in NO_POOL.items():
        share = np.mean([b.mode == mode for b in bs])
        assert abs(share - w / total) < 0.035, (mode, share, w / total)
    assert {b.mode for b in behaviours(50, mix={"idle": 1.0, "near": 0.0})} == {"idle"}
    # The default mix draws learned episodes too; their policy is only built when they act.
    drawn = [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120) for seed in range(200)]
    learned = [b for b in drawn if b.mode == "learned"]
    assert 20 < len(learned) < 60 and all(b.policy is None and b.learned is not None for b in learned), len(learned)
    for bad in ({"expert": -1.0}, {"expert": float("nan")}, {"expert": 0.0}, {"sideways": 1.0}):
        try:
            generate.Behaviour(TASK, generate.episode_rng(TASK, 0), 120, (1, 1), bad)
        except ValueError as e:
            assert "behaviour mix" in str(e), e
        else:
            raise AssertionError(f"the mix {bad} was accepted")


def test_mix_is_parsed_and_checked_on_the_command_line():
    args = ["--task", TASK, "--episodes", "1", "--out", "/nonexistent/x"]
    assert generate.parse_args(args).mix == generate.MIX
    assert generate.parse_args(args + ["--mix", "near=2,idle=0.5"]).mix == {"near": 2.0, "idle": 0.5}
    # The order the weights are given in changes neither the recorded settings nor the episodes.
    a, b = (generate.parse_args(args + ["--mix", m]).mix for m in ("idle=1,near=2,expert=1", "expert=1,near=2,idle=1"))
    assert list(a) == list(b) == ["expert", "near", "idle"], (a, b)
    modes = lambda mix: [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, (1, 1), mix).mode for seed in range(50)]
    assert modes({"idle": 1.0, "near": 2.0, "expert": 1.0}) == modes({"expert": 1.0, "near": 2.0, "idle": 1.0})
    for bad in ("near", "near=x", "near=-1", "near=1,near=2", "sideways=1", "near=0", "near=inf"):
        try:
            generate.parse_args(args + ["--mix", bad])
        except SystemExit:
            pass
        else:
            raise AssertionError(f"--mix {bad} was accepted")


def test_near_episodes_steer_off_at_graded_distances_in_every_direction():
    near = [b for b in behaviours(2000) if b.mode == "near"]
    flat = np.array([np.linalg.norm(b.offset[:2]) for b in near]) * 100
    assert flat.min() >= generate.NEAR_CM[0] and flat.max() <= generate.NEAR_CM[1] + 1e-9
    # Uniform in distance: every 3 cm band holds about a fifth of them.
    counts = np.histogram(flat, bins=5, range=generate.NEAR_CM)[0]
    assert counts.min() > 0.6 * len(near) / 5, counts
    angles = np.arctan2([b.offset[1] for b in near], [b.offset[0] for b in near])
    assert np.histogram(angles, bins=8, range=(-np.pi, np.pi))[0].min() > len(near) / 16
    heights = np.array([b.offset[2] for b in near])
    assert heights.min() >= -0.03 and heights.max() <= 0.03 and np.ptp(heights) > 0.04


def test_a_partial_pull_stops_where_it_was_drawn_to():
    """A partial episode's pull ends once the hand has pulled its drawn distance, then holds (or
    rises away); the press stops at its drawn depth."""
    from mw import next_state

    obj = np.array([0.0, 0.73, 0.09])
    pulls = []
    for b in behaviours(6, mix={"partial": 1.0}, frames=400):
        # Looking once, the expert takes the handle to follow its pull (without a simulator the handle
        # stays where it was).
        b.noise, b.offset, b.observe_every = 0.0, np.zeros(3), 1000
        state = np.array([0.0, 0.6, 0.2, -1.0], np.float32)
        start = None
        for t in range(399):
            state_before = state
            state = next_state(state, b.command(t, state, obj))
            if b.started_at is not None and start is None:
                start = b.started_at
            if b.stopped:
                break
        assert b.stopped, b.stop_after
        pulled = start - state_before[1]
        assert b.stop_after <= pulled + 1e-6 <= b.stop_after + 2 * ACTION_SCALE, (b.stop_after, pulled)
        pulls.append(b.stop_after)
        # Once stopped it stays stopped: still, or rising.
        after = next_state(state, b.command(399, state, obj))
        assert np.allclose(after[:2], state[:2]) and after[2] >= state[2] - 1e-7
    assert max(pulls) - min(pulls) > 0.05, pulls
    presses = [b.stop_after for b in behaviours(300, task="button-press-topdown-v3", mix={"partial": 1.0})]
    lo, hi = generate.PARTIAL_PRESS_CM
    assert lo / 100 <= min(presses) and max(presses) <= hi / 100 and np.ptp(presses) > 0.08


def test_exploration_stays_around_the_object_or_roams_the_table():
    from mw import next_state

    obj = np.array([0.0, 0.73, 0.09])
    seen = set()
    for b in [b for b in behaviours(200, mix={"explore": 1.0})][:10]:
        state = np.array([0.0, 0.6, 0.2, -1.0], np.float32)
        for t in range(120):
            state = next_state(state, b.command(t, state, obj))
            if b.around:
                assert np.abs(b.waypoint[:2] - obj[:2]).max() <= 0.15 + 1e-9, b.waypoint
        seen.add(b.around)
    assert seen == {True, False}


def test_the_learned_pool_acts_in_chunks_on_the_frame():
    """A learned episode asks its pool policy for a chunk of commands on the frame it is shown, and
    plays the chunk out before asking again."""

    class Recorder:
        calls = 0

        def act(self, image, state, n):
            Recorder.calls += 1
            return np.tile(np.append(state[:3] + 0.001, -1.0), (n, 1)).astype(np.float32)

    b = next(b for b in behaviours(300, mix={"learned": 1.0}) if b.mode == "learned")
    b.policy = Recorder()
    state, image = np.array([0.0, 0.6, 0.2, -1.0], np.float32), np.zeros((16, 16, 3), np.uint8)
    for t in range(2 * generate.LEARNED_CHUNK + 1):
        command = b.command(t, state, np.zeros(3), image)
        assert command.dtype == np.float32 and command.shape == (4,)
    assert Recorder.calls == 3
    try:
        b.queue = []
        b.command(0, state, np.zeros(3))
    except ValueError as e:
        assert "needs the frame" in str(e)
    else:
        raise AssertionError("a learned behaviour acted without a frame")


def test_between_looks_the_expert_takes_the_handle_to_follow_its_pull():
    """With --observe-every the expert sees the object only every few frames: a pull in front of a
    handle that stays behind (a miss) goes on as long as the look is away, where the expert that
    sees every frame stops it once the handle is 15 cm behind."""
    import tells
    from mw import next_state

    obj = np.array([0.0, 0.73, 0.09])

    def missed_pull(observe):
        b = generate.Behaviour(TASK, generate.episode_rng(TASK, 0), 120, observe, {"expert": 1})
        b.noise, b.explore[:], b.burst[:], b.offset = 0.0, False, False, np.array([0.0, -0.05, 0.0])
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
    drawn = [generate.Behaviour(TASK, generate.episode_rng(TASK, seed), 120, (1, 48), NO_POOL) for seed in range(100)]
    assert {b.observe_every for b in drawn} <= set(range(1, 49)) and len({b.observe_every for b in drawn}) > 20
    assert [b.mode for b in drawn] == [b.mode for b in behaviours(100)]
    for bad in ((0, 4), (5, 4)):
        try:
            generate.Behaviour(TASK, generate.episode_rng(TASK, 0), 120, bad)
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

    def make(out, *extra):
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            generate.main(["--task", TASK, "--episodes", "1", "--frames", "8", "--resolution", "16", "--workers", "1",
                           "--mix", "near=1,partial=2", "--observe-every", "8,40", "--out", out, *extra])
        return err.getvalue()

    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "data")
        make(out)
        with open(os.path.join(out, "meta", "generator.json")) as f:
            recorded = json.load(f)["settings"]
        assert recorded["observe_every"] == [8, 40] and recorded["tasks"] == [TASK] and recorded["frames"] == 8, recorded
        assert recorded["mix"] == {"near": 1.0, "partial": 2.0} and "families_py" not in recorded, recorded
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
