"""study.py's scoring on hand-made outcomes: success rates, their agreement, and the per-episode
agreement that tells whether the world model gets *which* episodes succeed."""

import os
import sys

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
    truth = {"t": {"a": [True, False, True, False], "b": [False, False, False, False]}}
    record = lambda k, ok: {"episode": k, "success": ok, "error": None}
    estimates = {"t": {"a": [record(2, True), record(0, True), record(3, True), record(1, False)],
                       "b": [record(k, False) for k in range(4)]}}
    judged = {"t": {"a": [0.9, 0.1, 0.9, 0.1], "b": [0.1] * 4}}
    s = study.summarize(truth, estimates, judged, ["t"], ["a", "b"])
    a = s["rates"][0]["per_episode"]
    assert (a["both_success"], a["missed"], a["invented"], a["both_fail"]) == (2, 0, 1, 1), a
    assert s["rates"][0]["estimated"] == 0.75 and s["rates"][0]["true"] == 0.5
    assert s["per_episode"]["n"] == 8 and s["per_episode"]["agreement"] == 7 / 8, s["per_episode"]


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
