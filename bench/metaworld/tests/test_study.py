"""study.py's scoring on hand-made outcomes: success rates, their agreement, and the per-episode
agreement that tells whether the world model gets *which* episodes succeed."""

import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import study  # noqa: E402


def test_episode_agreement_counts_and_kappa():
    e = study.episode_agreement([True, True, False, False], [True, False, True, False])
    assert (e["both_success"], e["missed"], e["invented"], e["both_fail"]) == (1, 1, 1, 1), e
    assert e["agreement"] == 0.5 and e["chance"] == 0.5 and e["kappa"] == 0.0, e
    # Right rate, wrong episodes: the rates agree exactly, the episodes never do.
    e = study.episode_agreement([True, False], [False, True])
    assert e["agreement"] == 0.0 and e["kappa"] == -1.0, e
    e = study.episode_agreement([True, True], [True, True])
    assert e["agreement"] == 1.0 and e["kappa"] is None, e


def test_summarize_pairs_episodes_by_index():
    # The truth is each episode's first success step (None: a failure) and the hand's closest
    # approach to the object (cm).
    truth = {"t": {"a": [[30, 0.5], [None, 3.0], [100, 1.0], [None, 12.0]], "b": [[None, 9.5]] * 4}}
    record = lambda k, ok: {"episode": k, "success": ok, "error": None}
    estimates = {"t": {"a": [record(2, True), record(0, True), record(3, True), record(1, False)],
                       "b": [record(k, False) for k in range(4)]}}
    judged = {"t": {"a": [0.9, 0.1, 0.9, 0.1], "b": [0.1] * 4}}
    s = study.summarize(truth, estimates, judged, ["t"], ["a", "b"], chunk=24)
    a = s["rates"][0]["per_episode"]
    assert (a["both_success"], a["missed"], a["invented"], a["both_fail"]) == (2, 0, 1, 1), a
    assert s["rates"][0]["estimated"] == 0.75 and s["rates"][0]["true"] == 0.5
    assert s["per_episode"]["n"] == 8 and s["per_episode"]["agreement"] == 7 / 8, s["per_episode"]
    # Successes at steps 30 (chunk 1) and 100 (chunk 4) both drawn; one of six failures invented.
    assert s["by_success_chunk"] == {"chunk 1": {"true": 1, "drawn": 1}, "chunk 4": {"true": 1, "drawn": 1},
                                     "failures": {"true": 6, "drawn": 1}}, s["by_success_chunk"]
    assert list(s["rates"][0]["by_success_chunk"]) == ["chunk 1", "chunk 4", "failures"]
    # Episode 3 (a failure 12 cm off) is the one drawn as a success.
    assert s["by_approach"] == {"t": {"0-2 cm": {"episodes": 2, "true": 2, "drawn": 2}, "2-4 cm": {"episodes": 1, "true": 0, "drawn": 0},
                                      "8-10 cm": {"episodes": 4, "true": 0, "drawn": 0}, "10+ cm": {"episodes": 1, "true": 0, "drawn": 1}}}, s["by_approach"]


def test_rates_are_scored_per_family_and_split():
    """policies.py's own variants are the development family `degraded`; families.py's carry their
    own family and split, each scored apart with its invented and missed successes."""
    record = lambda k, ok: {"episode": k, "success": ok, "error": None}
    variants = ["expert", "blind", "quit-50", "over-2cm", "wander-2cm", "bc-nn-1"]
    outcomes = {"expert": [True] * 4, "blind": [True, False, False, False], "quit-50": [False, False, False, True],
                "over-2cm": [True, True, True, False], "wander-2cm": [False] * 4, "bc-nn-1": [True, True, False, False]}
    truth = {"t": {v: [[20 if ok else None, 1.0] for ok in o] for v, o in outcomes.items()}}
    # The world model invents one success of bc-nn-1 and misses one of quit-50.
    drawn = {**outcomes, "bc-nn-1": [True, True, True, False], "quit-50": [False] * 4}
    estimates = {"t": {v: [record(k, ok) for k, ok in enumerate(o)] for v, o in drawn.items()}}
    judged = {"t": {v: [0.9 if ok else 0.1 for ok in o] for v, o in outcomes.items()}}
    s = study.summarize(truth, estimates, judged, ["t"], variants, chunk=24)
    families = s["per_family"]
    assert set(families) == {"degraded", "partial", "wander", "learned"}, families.keys()
    assert {k: f["split"] for k, f in families.items()} == {"degraded": "development", "partial": "development", "wander": "test", "learned": "test"}
    assert families["partial"]["n"] == 2 and families["partial"]["per_episode"]["missed"] == 1 and families["partial"]["per_episode"]["invented"] == 0
    assert families["learned"]["per_episode"]["invented"] == 1 and families["learned"]["mae"] == 0.25, families["learned"]
    assert families["degraded"]["pearson_r"] == 1.0 and families["degraded"]["judge_on_simulator_frames"]["pearson_r"] == 1.0
    splits = s["per_split"]
    assert splits["test"]["n"] == 2 and splits["development"]["n"] == 4, splits
    assert splits["test"]["per_episode"]["invented"] == 1 and splits["development"]["per_episode"]["missed"] == 1
    assert [r["family"] for r in s["rates"]] == ["degraded", "degraded", "partial", "partial", "wander", "learned"]


def test_r_comes_with_its_interval_over_redrawn_episodes():
    # Four rates of 20 episodes. A world model that draws every episode's outcome right keeps r = 1
    # in every redraw; one that draws the right rates on the wrong episodes moves with the draw.
    trues = [[k < n for k in range(20)] for n in (2, 8, 12, 18)]
    exact = [list(zip(t, t)) for t in trues]
    assert study.pearson_interval(exact) == [1.0, 1.0]
    shuffled = [list(zip(t, t[::-1])) for t in trues]
    lo, hi = study.pearson_interval(shuffled)
    assert 0.5 < lo < hi < 1.0, (lo, hi)
    assert study.pearson_interval(shuffled) == [lo, hi], "seeded: the same interval every time"
    fewer = [list(zip(t[::4], t[::-1][::4])) for t in trues]  # 5 episodes per rate
    assert study.pearson_interval(fewer)[0] < lo, "fewer episodes, a wider interval"
    assert study.pearson_interval(exact[:2]) is None, "two rates give no interval"
    # summarize reports it beside r, over all rates and per task.
    truth = {"t": {v: [[10 if ok else None, 1.0] for ok in t] for v, t in zip("abcd", trues)}}
    estimates = {"t": {v: [{"episode": k, "success": ok, "error": None} for k, ok in enumerate(t[::-1])] for v, t in zip("abcd", trues)}}
    judged = {"t": {v: [0.9 if ok else 0.1 for ok in t] for v, t in zip("abcd", trues)}}
    s = study.summarize(truth, estimates, judged, ["t"], list("abcd"), chunk=24)
    assert abs(s["all"]["pearson_r"] - 1.0) < 1e-9 and s["all"]["pearson_r_95"] == [lo, hi], s["all"]
    assert s["per_task"]["t"]["pearson_r_95"] == [lo, hi], s["per_task"]


def test_replayed_actions_split_the_world_models_error_from_the_policies():
    truth = {"t": {"a": [[30, 0.5], [None, 6.0], [None, 7.0], [None, 12.0]]}}
    record = lambda k, ok, p: {"episode": k, "success": ok, "error": None, "actions": [], "success_probability": p}
    estimates = {"t": {"a": [record(0, True, 0.97), record(1, True, 0.6), record(2, True, 0.5), record(3, False, 0.0)]}}
    judged = {"t": {"a": [0.9, 0.1, 0.1, 0.1]}}
    # In the world model's loop the policy's hand came within 1 cm in episode 1 and succeeded in
    # the simulator too; episode 2's stayed 7 cm off: an opening the world model invented.
    replayed = {"t": {"a": {0: [40, 0.4, [0.4, 0.0, 0.0]], 1: [50, 1.0, [0.0, -1.0, 0.0]], 2: [None, 7.0, [0.0, -7.0, 0.0]], 3: [None, 11.0, [11.0, 0.0, 0.0]]}}}
    s = study.summarize(truth, estimates, judged, ["t"], ["a"], chunk=24, replayed=replayed)
    row = s["rates"][0]
    assert (row["true"], row["estimated"], row["replayed"]) == (0.25, 0.75, 0.5), row
    e = row["per_episode_replayed"]
    assert (e["both_success"], e["missed"], e["invented"], e["both_fail"]) == (2, 0, 1, 1), e
    assert s["replayed"]["per_episode"] == e
    # Each with the hand's offset at its closest (contact_map.py reads it).
    assert row["replayed_episodes"] == [[0, True, 40, 0.4, [0.4, 0.0, 0.0]], [1, True, 50, 1.0, [0.0, -1.0, 0.0]],
                                        [2, True, None, 7.0, [0.0, -7.0, 0.0]], [3, False, None, 11.0, [11.0, 0.0, 0.0]]]
    assert s["replayed"]["by_approach"] == {"t": {"0-2 cm": {"episodes": 2, "true": 2, "drawn": 2},
                                                  "6-8 cm": {"episodes": 1, "true": 0, "drawn": 1},
                                                  "10+ cm": {"episodes": 1, "true": 0, "drawn": 0}}}, s["replayed"]
    assert row["by_approach_replayed"] == s["replayed"]["by_approach"]["t"], row  # one variant: the task's
    assert s["replayed"]["replayed_vs_true"]["mae"] == 0.25 and s["replayed"]["estimated_vs_replayed"]["mae"] == 0.25
    # The judge's probabilities on the world model's frames, by the replay's outcome and its own.
    bands = s["replayed"]["by_probability"]["t"]
    assert bands["both_success"] == {"0-0.05": 0, "0.05-0.2": 0, "0.2-0.5": 0, "0.5-0.8": 1, "0.8-0.95": 0, "0.95-1": 1}, bands
    assert bands["invented"]["0.5-0.8"] == 1 and bands["both_fail"]["0-0.05"] == 1, bands
    assert sum(bands["missed"].values()) == 0, bands
    # Without replays (records without actions) nothing of it appears.
    plain = study.summarize(truth, estimates, judged, ["t"], ["a"], chunk=24)
    assert "replayed" not in plain and "replayed" not in plain["rates"][0] and "by_approach_replayed" not in plain["rates"][0]
    assert study.replay_world_model({"t": {"a": [{"episode": 0, "success": True}]}}, {"t": [(0, 1)]}, 64, 1) is None


def test_a_simulator_episodes_commands_replayed_give_its_outcome():
    import policies
    import variants

    for task, variant, seed in [("drawer-open-v3", "expert", 100000), ("button-press-topdown-v3", "wrong", 100001)]:
        ran = variants.run_episode(task, variant, seed, horizon=120, chunk=24, resolution=64)
        again = policies.replay(task, seed, ran.commands.tolist(), resolution=64)
        assert (again.first, again.approach_cm) == (ran.first, ran.approach_cm), (task, variant, ran, again)
        # The study's replay job keeps the same outcome, distance and offset.
        _, _, out = study._replay_job((task, variant, [(0, seed, ran.commands.tolist())], 64))
        assert out[0][:2] == [again.first, round(again.approach_cm, 3)], out
        assert np.allclose(out[0][2], again.nearest_cm, atol=0.006) and abs(np.linalg.norm(out[0][2]) - again.approach_cm) < 0.02, out
        assert len(ran.commands) == (ran.first or 120), (task, variant, len(ran.commands))
    # The expert's opening cut short of its success is a failure; on another placement its
    # commands miss the handle.
    assert ran.first is None
    expert = variants.run_episode("drawer-open-v3", "expert", 100000, resolution=64)
    assert expert.first is not None
    assert policies.replay("drawer-open-v3", 100000, expert.commands[: expert.first - 1], resolution=64).first is None
    elsewhere = [policies.replay("drawer-open-v3", s, expert.commands, resolution=64) for s in range(100002, 100010)]
    assert any(e.first is None for e in elsewhere), [e.approach_cm for e in elsewhere]


def test_approach_bands_sort_numerically_and_end_open():
    b = study.by_approach([0.0, 1.99, 2.0, 10.0, 25.0, 4.5, 12.3], [True] * 7, [False] * 7)
    assert list(b) == ["0-2 cm", "2-4 cm", "4-6 cm", "10+ cm"], b
    assert b["0-2 cm"]["episodes"] == 2 and b["10+ cm"]["episodes"] == 3 and b["2-4 cm"]["true"] == 1, b
    assert study.by_approach([], [], []) == {}


def test_probability_bands_close_at_one_and_skip_failed_runs():
    b = study.by_probability([1.0, 0.0, 0.05, 0.2, None, 0.9499], [True, False, True, True, True, False], [True, False, False, False, True, True])
    assert b["both_success"]["0.95-1"] == 1 and b["both_fail"]["0-0.05"] == 1, b
    assert b["missed"]["0.05-0.2"] == 1 and b["missed"]["0.2-0.5"] == 1, b
    assert b["invented"]["0.8-0.95"] == 1 and sum(sum(k.values()) for k in b.values()) == 5, b


def test_variants_run_in_processes_by_task_and_variant():
    # Two variants' truth over one seed and a few steps, each in its own spawned process.
    episodes = {"button-press-topdown-v3": [(0, 100000)]}
    truth = study.measure_truth(episodes, ["expert", "wrong"], horizon=8, chunk=4, resolution=32, workers=2)
    assert set(truth) == {"button-press-topdown-v3"} and set(truth["button-press-topdown-v3"]) == {"expert", "wrong"}, truth
    for outcome in truth["button-press-topdown-v3"].values():
        assert len(outcome) == 1 and outcome[0][0] is None and outcome[0][1] > 0, outcome


def test_success_chunks_sort_numerically():
    b = study.by_success_chunk([250, 30, None, 24, 25], [False, True, True, True, False], chunk=24)
    assert list(b) == ["chunk 0", "chunk 1", "chunk 10", "failures"], b
    assert b["chunk 1"] == {"true": 2, "drawn": 1} and b["chunk 0"] == {"true": 1, "drawn": 1}, b



def test_evaluate_processes_share_the_cores_only_off_the_gpu():
    share = str(max(1, (os.cpu_count() or 1) // 2))
    base = {"PATH": "/bin"}
    assert study.evaluate_env(["--checkpoint", "c", "--device", "cpu"], 2, base) == {"PATH": "/bin", "OMP_NUM_THREADS": share}
    # auto is the CPU on a machine without CUDA: the share, which bwm leaves to libtorch.
    assert study.evaluate_env(["--checkpoint", "c"], 2, base)["OMP_NUM_THREADS"] == share
    for wm in (["--device", "cuda"], ["--device=cuda:1"], ["--vae", "v", "--device", "cuda:0", "--fp8", "tensor"]):
        assert study.evaluate_env(wm, 2, base) == base, wm
    assert study.evaluate_env(["--device", "cuda"], 2, {"OMP_NUM_THREADS": "3"}) == {"OMP_NUM_THREADS": "3"}
    assert "OMP_NUM_THREADS" not in base

def test_a_cut_study_is_scored_over_the_episodes_it_finished():
    import json
    import tempfile
    tasks, variants = ["drawer-open-v3", "button-press-topdown-v3"], ["expert", "wrong"]
    with tempfile.TemporaryDirectory() as d:
        data, out = os.path.join(d, "val"), os.path.join(d, "study")
        os.makedirs(os.path.join(data, "meta"))
        with open(os.path.join(data, "meta", "episodes.jsonl"), "w") as f:
            for i in range(6):
                f.write(json.dumps({"episode_index": i, "tasks": [tasks[i % 2]], "seed": 100000 + i}) + "\n")
        episodes = {"drawer-open-v3": [(0, 100000), (2, 100002), (4, 100004)], "button-press-topdown-v3": [(1, 100001), (3, 100003), (5, 100005)]}
        key = {k: v for k, v in study.truth_key(episodes, 48, 24, 64, variants).items() if k != "outcome"}
        # The expert succeeds in all three episodes of each task, `wrong` in none.
        truth = {t: {"expert": [[40, 0.5]] * 3, "wrong": [[None, 6.0]] * 3} for t in tasks}
        judged = {t: {"expert": [0.9] * 3, "wrong": [0.1] * 3} for t in tasks}
        os.makedirs(os.path.join(out, "eval-0"))
        os.makedirs(os.path.join(out, "eval-1"))  # a process that wrote nothing before the cut
        with open(os.path.join(out, "truth.json"), "w") as f:
            json.dump({"key": {**key, "outcome": "first success step, closest approach (cm)"}, "truth": truth}, f)
        with open(os.path.join(out, "judged.json"), "w") as f:
            json.dump({"key": {**key, "judge": "0" * 64}, "judged": judged}, f)
        record = lambda t, v, k, ok: json.dumps({"task": t, "policy": v, "episode": k, "success": ok, "error": None})
        with open(os.path.join(out, "eval-0", "episodes.jsonl"), "w") as f:
            # The expert's first two drawer episodes and one button episode; the drawer's `wrong`
            # once (drawn open); the button's `wrong` never; the last line half written.
            f.write("\n".join([record(tasks[0], "expert", 0, True), record(tasks[0], "expert", 1, False),
                               record(tasks[1], "expert", 2, True), record(tasks[0], "wrong", 1, True)]) + "\n")
            f.write(record(tasks[1], "wrong", 0, False)[:20])
        args = ["--data", data, "--out", out, "--tasks", ",".join(tasks), "--variants", ",".join(variants), "--episodes", "3",
                "--horizon", "48", "--resolution", "64", "--workers", "1", "--rescore"]
        study.main(args)
        with open(os.path.join(out, "study.json")) as f:
            s = json.load(f)
        # Every rate with episodes scored: the button's `wrong` (none finished) left out, the
        # drawer's kept; the mean over tasks only over the variant finished in both.
        assert s["cut"] == {"episodes_finished": 4, "episodes_scored": 4, "episodes_planned": 12,
                            "rates_without_episodes": ["wrong/button-press-topdown-v3"]}, s["cut"]
        rows = {(r["task"], r["variant"]): r for r in s["rates"]}
        assert set(rows) == {(t, "expert") for t in tasks} | {(tasks[0], "wrong")}, rows
        drawer = rows[(tasks[0], "expert")]
        assert (drawer["episodes"], drawer["true"], drawer["estimated"], drawer["judged_simulator"]) == (2, 1.0, 0.5, 1.0), drawer
        assert drawer["per_episode"]["missed"] == 1 and s["per_episode"]["n"] == 4, s["per_episode"]
        wrong = rows[(tasks[0], "wrong")]
        assert (wrong["episodes"], wrong["true"], wrong["estimated"]) == (1, 0.0, 1.0), wrong
        assert s["per_episode"]["invented"] == 1 and s["all"]["n"] == 3, s
        assert s["variants_mean_over_tasks"]["n"] == 1, s["variants_mean_over_tasks"]
        # Once scored it is a finished study: its processes' files must be whole.
        try:
            study.main(args)
        except SystemExit as e:
            assert str(e) == f"study: line 5 of {os.path.join(out, 'eval-0', 'episodes.jsonl')} is not JSON", e
        else:
            raise AssertionError("a finished study scored with a half-written episode")
        # A task without any finished episode is left out of the scores, not scored empty.
        os.remove(os.path.join(out, "study.json"))
        with open(os.path.join(out, "eval-0", "episodes.jsonl"), "w") as f:
            f.write(record(tasks[0], "expert", 0, True) + "\n" + record(tasks[0], "wrong", 1, False) + "\n")
        study.main(args)
        with open(os.path.join(out, "study.json")) as f:
            s = json.load(f)
        assert list(s["per_task"]) == [tasks[0]] and s["all"]["n"] == 2 and s["variants_mean_over_tasks"]["n"] == 2, s
        assert len(s["cut"]["rates_without_episodes"]) == 2, s["cut"]
        # A cut study that finished no episode is refused, not scored empty.
        os.remove(os.path.join(out, "study.json"))
        os.remove(os.path.join(out, "eval-0", "episodes.jsonl"))
        try:
            study.main(args)
        except SystemExit as e:
            assert "finished no world-model episode" in str(e), e
        else:
            raise AssertionError("scored a cut study without episodes")


def test_the_truth_is_measured_again_when_the_policies_code_changes():
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        sources = []
        for name in ("policies.py", "calibration.json", "mw.py"):
            sources.append(os.path.join(d, name))
            with open(sources[-1], "w") as f:
                f.write(name)
        kept, study.TRUTH_SOURCES = study.TRUTH_SOURCES, sources
        try:
            episodes = {"drawer-open-v3": [(0, 100000), (1, 100001)]}
            key = lambda: study.truth_key(episodes, 120, 24, 128, ["expert", "blind"])
            path, measured = os.path.join(d, "truth.json"), []
            measure = lambda: measured.append(1) or {"expert": len(measured)}
            assert study.cached(path, "truth", key(), measure) == {"expert": 1}
            assert study.cached(path, "truth", key(), measure) == {"expert": 1} and len(measured) == 1
            # A variant changed under the same name (its code, or the calibration it perceives by).
            for changed in (sources[0], sources[1]):
                with open(changed, "a") as f:
                    f.write(" changed")
                before = len(measured)
                assert study.cached(path, "truth", key(), measure) == {"expert": before + 1}
            assert key()["episodes"] == {"drawer-open-v3": [100000, 100001]}
        finally:
            study.TRUTH_SOURCES = kept


def test_a_study_of_fewer_variants_takes_their_rates_from_a_truth_over_more():
    import tempfile

    episodes = {"drawer-open-v3": [(0, 100000)], "button-press-topdown-v3": [(0, 100000)]}
    every = ["expert", "blind", "bc-nn-1"]
    measured_over = []

    def measure(variants):
        measured_over.append(list(variants))
        return {t: {v: [[None, float(i)]] for i, v in enumerate(variants)} for t in episodes}

    digest = {"now": "clones-a"}
    kept_digest = study.families.clones_digest
    study.families.clones_digest = lambda tasks, variants: digest["now"] if "bc-nn-1" in variants else None
    try:
        with tempfile.TemporaryDirectory() as d:
            path = os.path.join(d, "truth.json")
            key = lambda variants, horizon=120: study.truth_key(episodes, horizon, 24, 128, variants,
                                                                study.families.clones_digest(list(episodes), variants))
            full = study.cached(path, "truth", key(every), lambda: measure(every))
            # A subset: its rates from the file, nothing measured, and the file now of the subset's key.
            sub = study.cached(path, "truth", key(["blind"]), lambda: measure(["blind"]))
            assert sub == {t: {"blind": full[t]["blind"]} for t in episodes} and measured_over == [every]
            with open(path) as f:
                assert json.load(f)["key"] == key(["blind"])
            # A variant the file does not hold, or other settings: measured.
            study.cached(path, "truth", key(every), lambda: measure(every))
            study.cached(path, "truth", key(["blind", "slow"]), lambda: measure(["blind", "slow"]))
            assert measured_over[-1] == ["blind", "slow"]
            study.cached(path, "truth", key(every), lambda: measure(every))
            study.cached(path, "truth", key(["blind"], horizon=100), lambda: measure(["blind"]))
            assert measured_over[-1] == ["blind"] and len(measured_over) == 5
            # Cloned policies trained again since the file was measured: its rates are not theirs.
            study.cached(path, "truth", key(every), lambda: measure(every))
            digest["now"] = "clones-b"
            study.cached(path, "truth", key(["blind", "bc-nn-1"]), lambda: measure(["blind", "bc-nn-1"]))
            assert measured_over[-1] == ["blind", "bc-nn-1"] and len(measured_over) == 7
    finally:
        study.families.clones_digest = kept_digest


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
