"""The closed-loop policy study: every policy variant (variants.py: policies.py's and families.py's) run in the world model through
`bwm evaluate` (policies served by policy_server.py, success decided by judge.py from the
generated frames) against its true success rate in the simulator on the same placements.

    python study.py --data VAL_DATASET --judge judge.pt --episodes 50 --out DIR --jobs 8 \\
        -- --checkpoint CKPT --vae VAE --stats STAT.json --stats-group observation.state \\
           --history 8 --future 24 --sample-steps 20 --device cuda

Episodes: the first --episodes episodes of each task in the held-out dataset; episode k of a task
starts from that episode's frame 0 and pose, and the policy's per-episode randomness and the
simulator's placement both follow that episode's seed (its `seed` in meta/episodes.jsonl).
Truth: variants.measure_truth over the same seeds (cached in DIR/truth.json: per episode the step
of its first success, null for a failure, and the closest the hand came to the object before it,
in cm; measured again when the seeds, the variants, the cloned policies or the bytes of
policies.py, families.py, variants.py, calibration.json or mw.py differ from the cached one's, so a
variant changed under its name is not scored against its old truth; a cached truth of more variants,
otherwise the same, gives these variants' rates, as does DIR/judged.json below). The variants are
split over --jobs `bwm evaluate` processes that share the servers (a variant's episodes stay in
one process, in order, so that the policy server hands out seeds in the dataset's order).

Judge on the simulator: the same episodes run again in the simulator with every frame rendered and
judged as the world model's are (cached in DIR/judged.json), so that the judge's own error is
measured apart from the world model's.

Writes DIR/study.json (rates and agreement: Pearson r, Spearman rank correlation, MAE, per task
and over all variants; whether the best variant is ranked first; the same for the judge on the
simulator's frames; the episodes per task by the hand's closest approach to the object, with how
many succeeded and how many the world model drew; and, where `bwm evaluate` kept each episode's
actions, those actions replayed in the simulator from the same placement, under "replayed": the
world model's outcomes against the simulator's for the same actions, its own error, apart from
the policies acting otherwise on its frames than on the simulator's, and how clearly it drew them:
the judge's probability on its frames by both outcomes; per rate each replay's outcome, closest
approach and the hand's offset there, `replayed_episodes`, which contact_map.py maps), DIR/study.csv,
DIR/study.svg (estimated against true rates) and each process's evaluate output in DIR/eval-*/.
Everything after `--` goes to `bwm evaluate` (the world model's flags). With --rescore, a finished
study in DIR is scored again from its eval-*/episodes.jsonl and judged.json (after a change to the
scoring), without the world model, the judge or `--`; a study cut before its study.json (a machine
taken back) is scored over the episodes it finished, each rate against the truth of the same
episodes (a rate or a task without any left out, the mean over tasks only over the variants
finished in every task scored), and says so (study.json "cut"). With --judged-only, the judge on the
simulator's frames alone (DIR/judged.json, cached for the study that follows): the recipe runs it
beside training, where the study would otherwise begin with it.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import multiprocessing
import os
import shlex
import shutil
import subprocess
import sys
import time

import numpy as np

import families
import policies
from files import read_json, replacing, write_json, write_text
from mw import simulator_versions
import variants as known_variants

HERE = os.path.dirname(os.path.abspath(__file__))
# What the simulator's outcome of a policy variant follows beside its seeds: the variants and
# their perception (policies.py, families.py, variants.py, calibration.json) and the simulator's wrapper (mw.py). The truth
# and the judge's verdicts on the simulator's frames are cached under their bytes, so a variant
# changed under the same name is measured again.
TRUTH_SOURCES = [os.path.join(HERE, name) for name in ("policies.py", "families.py", "variants.py", "calibration.json", "mw.py")]
# The judge's probability at or above which an episode counts as a success (evaluate.toml's
# judge.threshold, and the same rule on the simulator's frames).
THRESHOLD = 0.5


# --- the held-out episodes -----------------------------------------------------------------------
def dataset_episodes(root: str, tasks: list[str], per_task: int | None = None, behaviours: list[str] | None = None,
                     need: int = 1, tool: str = "study") -> dict[str, list[dict]]:
    """Per task, the metadata (meta/episodes.jsonl) of a generate.py dataset's first `per_task`
    episodes (all with None) whose generator behaviour is among `behaviours` (any with None), in
    episode order, each with its `position` in the dataset. Fewer than `need` of a task end the
    program, in `tool`'s name."""
    import judge

    path = os.path.join(root, "meta", "episodes.jsonl")
    if not os.path.isfile(path):
        raise SystemExit(f"{tool}: {root} is not a generate.py dataset (no meta/episodes.jsonl)")
    out: dict[str, list[dict]] = {t: [] for t in tasks}
    for position, e in enumerate(sorted(judge.read_jsonl(path), key=lambda e: e["episode_index"])):
        if "seed" not in e or (behaviours is not None and "behaviour" not in e):
            raise SystemExit(f"{tool}: {path}: episode {e['episode_index']} has no seed or behaviour (not written by generate.py)")
        for t in tasks:
            if e.get("tasks") == [t] and (behaviours is None or e["behaviour"] in behaviours) and (per_task is None or len(out[t]) < per_task):
                out[t].append(dict(e, position=position))
    for t, eps in out.items():
        if len(eps) < need:
            which = f" of behaviour {', '.join(behaviours)}" if behaviours else ""
            raise SystemExit(f"{tool}: {root} holds {len(eps) or 'no'} episodes of {t}{which}" + (f"; {need} are needed" if need > 1 else ""))
    return out


def episodes_by_task(root: str, tasks: list[str], per_task: int) -> dict[str, list[tuple[int, int]]]:
    """Per task: (dataset position, seed) of its first `per_task` episodes."""
    return {t: [(e["position"], int(e["seed"])) for e in eps] for t, eps in dataset_episodes(root, tasks, per_task, need=per_task).items()}


# --- truth -----------------------------------------------------------------------------------------
def _truth_job(job):
    task, variant, seeds, horizon, chunk, resolution = job
    episodes = known_variants.measure_truth(task, variant, seeds, horizon, chunk, resolution)
    return task, variant, [[e.first, round(e.approach_cm, 3)] for e in episodes]


def by_variant_in_processes(job, jobs: list, workers: int, show, initializer=None, initargs=()) -> dict:
    """{task: {variant: result}} of `job` over `jobs` (each job's first two items its task and
    variant; `job` returns (task, variant, result)) in spawned processes, `show(task, variant,
    result)` naming each result as it comes, printed with the count and seconds so far."""
    out: dict = {}
    start = time.time()
    with multiprocessing.get_context("spawn").Pool(min(workers, len(jobs)), initializer=initializer, initargs=initargs) as pool:
        for n, (task, variant, result) in enumerate(pool.imap_unordered(job, jobs), 1):
            out.setdefault(task, {})[variant] = result
            print(f"study: {show(task, variant, result)} {n}/{len(jobs)} ({time.time() - start:.0f} s)", flush=True)
    return out


def measure_truth(episodes, variants, horizon, chunk, resolution, workers) -> dict:
    """{task: {variant: [[first success step or None, closest approach in cm] per episode]}} in the
    simulator, episodes in parallel by variant."""
    jobs = [(t, v, [s for _, s in eps], horizon, chunk, resolution) for t, eps in episodes.items() for v in variants]
    return by_variant_in_processes(
        _truth_job, jobs, workers,
        lambda t, v, outcome: f"truth: {t} {v} {100 * np.mean([f is not None for f, _ in outcome]):.0f}%")


_judge = None


def _load_judge(path: str) -> None:
    global _judge
    import torch
    from judge import Judge

    torch.set_num_threads(1)
    _judge = Judge(path, "cpu", None)


def _judged_job(job):
    task, variant, seeds, horizon, chunk, resolution = job
    probs = []
    for seed in seeds:
        frames = known_variants.run_episode(task, variant, seed, horizon, chunk, resolution, record=True).frames
        probs.append(_judge.judge({"frames": frames, "task": task, "prompt": task, "final": True})["success_probability"])
    return task, variant, probs


def judge_simulator(episodes, variants, horizon, chunk, resolution, workers, judge: str) -> dict:
    """{task: {variant: [judge's success probability per episode]}} on the simulator's own frames
    of the same episodes: the judge's share of the study's error, apart from the world model's."""
    jobs = [(t, v, [s for _, s in eps], horizon, chunk, resolution) for t, eps in episodes.items() for v in variants]
    return by_variant_in_processes(
        _judged_job, jobs, workers,
        lambda t, v, probs: f"judge on simulator frames: {t} {v} {100 * np.mean([p >= THRESHOLD for p in probs]):.0f}%",
        initializer=_load_judge, initargs=(judge,))


def _replay_job(job):
    task, variant, runs, resolution = job
    return task, variant, {k: [e.first, round(e.approach_cm, 3), [round(float(v), 2) for v in e.nearest_cm]] for k, seed, actions in runs
                           for e in [policies.replay(task, seed, actions, resolution)]}


def replay_world_model(estimates: dict, episodes: dict, resolution: int, workers: int) -> dict | None:
    """{task: {variant: {episode: [first success step or None, closest approach in cm, the hand's
    offset from the object there (cm, x y z)]}}}: each
    world-model episode's actions (the commands its policy sent through the world model's frames)
    issued in the simulator from the same placement. Where the world model's outcome differs from
    this one it drew the wrong outcome of those actions; where this one differs from the truth the
    policy acted otherwise on the world model's frames than on the simulator's. None when the
    records hold no actions (a study of a `bwm evaluate` that did not keep them)."""
    records = [r for per in estimates.values() for rs in per.values() for r in rs]
    if not records or any("actions" not in r for r in records):
        return None
    jobs = [(t, v, [(r["episode"], episodes[t][r["episode"]][1], r["actions"]) for r in rs], resolution)
            for t, per in estimates.items() for v, rs in per.items()]
    return by_variant_in_processes(
        _replay_job, jobs, workers,
        lambda t, v, outcome: f"world model's actions replayed: {t} {v} {100 * np.mean([f is not None for f, *_ in outcome.values()]):.0f}%")


def cached(path: str, name: str, key: dict, measure):
    """`measure()`, or what the JSON file at `path` holds under `name` when it was measured for
    the same `key`, or for the same key over more variants (`covering`: those rates of it kept);
    written atomically with the seconds it took."""
    value = None
    found = read_json(path)
    if found is not None:
        if found.get("key") == key:
            return found[name]
        value = covering(found, name, key)
        if value is not None:
            print(f"study: {name} of {len(key['variants'])} variants taken from {path}, measured over {len(found['key']['variants'])}")
            seconds = 0.0
    if value is None:
        t0 = time.time()
        value = measure()
        seconds = time.time() - t0
    write_json(path, {"key": key, name: value, "seconds": seconds}, indent=None)
    return value


def covering(found: dict, name: str, key: dict) -> dict | None:
    """What `found` (a cached file's contents: {task: {variant: ...}} under `name`) holds of
    `key`'s variants when it was measured for the same key over more variants, with the same
    cloned policies among them (their digest taken again now); else None."""
    theirs = found.get("key")
    if not isinstance(theirs, dict) or set(theirs) != set(key) or not isinstance(found.get(name), dict):
        return None
    if any(theirs[k] != key[k] for k in key if k not in ("variants", "clones")):
        return None
    if not set(key["variants"]) <= set(theirs["variants"]):
        return None
    tasks = list(key["episodes"])
    if theirs["clones"] != families.clones_digest(tasks, theirs["variants"]):
        return None
    value = found[name]
    if any(v not in value.get(t, {}) for t in tasks for v in key["variants"]):
        return None
    return {t: {v: value[t][v] for v in key["variants"]} for t in tasks}


def truth_key(episodes: dict, horizon: int, chunk: int, resolution: int, variants: list[str], clones: str | None = None) -> dict:
    """What a study's cached truth (and, without "outcome", its judged simulator frames) was
    measured for: the episodes' seeds, the loop's settings, the variants, the bytes of
    TRUTH_SOURCES, the simulator's versions and those of the cloned policies among the variants
    (families.clones_digest: a network trained on another machine is another policy)."""
    return {"episodes": {t: [s for _, s in e] for t, e in episodes.items()}, "horizon": horizon, "chunk": chunk,
            "resolution": resolution, "variants": variants,
            "sources": {os.path.basename(p): file_digest(p) for p in TRUTH_SOURCES}, "simulator": simulator_versions(), "clones": clones,
            "outcome": "first success step, closest approach (cm)"}


def file_digest(path: str) -> str:
    import hashlib

    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


# --- agreement -------------------------------------------------------------------------------------
def pearson(x, y) -> float | None:
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 2 or x.std() == 0 or y.std() == 0:
        return None
    return float(np.corrcoef(x, y)[0, 1])


def ranks(v) -> np.ndarray:
    """Ranks from 1, ties sharing their mean rank."""
    v = np.asarray(v, float)
    order = np.argsort(v, kind="stable")
    r = np.empty(len(v))
    i = 0
    while i < len(v):
        j = i
        while j + 1 < len(v) and v[order[j + 1]] == v[order[i]]:
            j += 1
        r[order[i : j + 1]] = (i + j) / 2 + 1
        i = j + 1
    return r


def spearman(x, y) -> float | None:
    return pearson(ranks(x), ranks(y))


def agreement(names: list[str], estimated: list[float], true: list[float]) -> dict:
    est, tru = np.asarray(estimated), np.asarray(true)
    best_true = [n for n, t in zip(names, tru) if t == tru.max()]
    best_est = [n for n, e in zip(names, est) if e == est.max()]
    return {
        "n": len(names),
        "pearson_r": pearson(est, tru),
        "spearman_rho": spearman(est, tru),
        "mae": float(np.abs(est - tru).mean()),
        "best_true": best_true,
        "ranked_first": best_est,
        # The variant the world model ranks first is a truly best one (ties either way count).
        "best_ranked_first": bool(set(best_true) & set(best_est)),
    }


def pearson_interval(paired: list[list[tuple[bool, bool]]], draws: int = 2000, seed: int = 0) -> list[float] | None:
    """The 95% interval of Pearson r between the rates' estimates and truths when each rate's
    episodes (truth and world model together: one placement and policy seed) are drawn again with
    replacement: how far r moves with another draw of as many episodes. Deterministic (seeded);
    None when too few draws give an r (rates that cannot vary)."""
    if len(paired) < 3:
        return None
    rng = np.random.default_rng(seed)
    true, est = [], []
    for episodes in paired:
        a = np.asarray(episodes, float).reshape(-1, 2)
        picks = a[rng.integers(0, len(a), (draws, len(a)))]  # [draws, n, 2]
        true.append(picks[:, :, 0].mean(1))
        est.append(picks[:, :, 1].mean(1))
    t, e = np.stack(true, 1), np.stack(est, 1)  # [draws, rates]
    t, e = t - t.mean(1, keepdims=True), e - e.mean(1, keepdims=True)
    norm = np.sqrt((t * t).sum(1) * (e * e).sum(1))
    ok = norm > 0
    if ok.sum() < draws // 2:
        return None
    r = (t * e).sum(1)[ok] / norm[ok]
    return [float(np.percentile(r, 2.5)), float(np.percentile(r, 97.5))]


def episode_agreement(true: list[bool], estimated: list[bool]) -> dict:
    """Whether the world model gets *which* episodes succeed: the share of episodes whose outcome
    it draws as the simulator does, and Cohen's kappa (that share above what the two success
    rates alone would give by chance; None when chance already explains everything)."""
    t, e = np.asarray(true, bool), np.asarray(estimated, bool)
    observed = float((t == e).mean())
    chance = float(t.mean() * e.mean() + (1 - t.mean()) * (1 - e.mean()))
    kappa = (observed - chance) / (1 - chance) if chance < 1 else None
    return {"n": len(t), "agreement": observed, "chance": chance, "kappa": kappa,
            "both_success": int((t & e).sum()), "missed": int((t & ~e).sum()), "invented": int((~t & e).sum()), "both_fail": int((~t & ~e).sum())}


def by_success_chunk(first: list, drawn: list[bool], chunk: int) -> dict:
    """The simulator's successes by the chunk (0-based, of `chunk` steps) in which they came, with
    how many of each the world model drew, and the failures it drew as successes: where in an
    episode the world model's misses are. {"chunk K": {"true": n, "drawn": m}, "failures": ...}."""
    out: dict = {}
    for f, d in zip(first, drawn):
        name = "failures" if f is None else f"chunk {(f - 1) // chunk}"
        cell = out.setdefault(name, {"true": 0, "drawn": 0})
        cell["true"] += 1
        cell["drawn"] += int(d)
    return dict(sorted(out.items(), key=lambda kv: (kv[0] == "failures", len(kv[0]), kv[0])))


def by_approach(approach_cm: list[float], true: list[bool], drawn: list[bool], band: float = 2.0, last: float = 10.0) -> dict:
    """Episodes by how close the hand came to the object in the simulator (before any success),
    in bands of `band` cm up to `last`: how many succeeded there and how many the world model drew
    as successes. Where the two part is how far off a hand the world model still lets act.
    {"0-2 cm": {"episodes": n, "true": k, "drawn": m}, ..., "10+ cm": ...}."""
    out: dict = {}
    for d, t, e in zip(approach_cm, true, drawn):
        lo = min(math.floor(d / band) * band, last)
        name = f"{lo:g}+ cm" if lo >= last else f"{lo:g}-{lo + band:g} cm"
        cell = out.setdefault((lo, name), {"episodes": 0, "true": 0, "drawn": 0})
        cell["episodes"] += 1
        cell["true"] += int(t)
        cell["drawn"] += int(e)
    return {name: cell for (_, name), cell in sorted(out.items())}


PROBABILITY_BANDS = (0.0, 0.05, 0.2, 0.5, 0.8, 0.95, 1.0)


def by_probability(probability: list, true: list[bool], drawn: list[bool]) -> dict:
    """Episodes by the judge's success probability on the world model's frames, apart for each
    pair of outcomes (the simulator's, the world model's): how clearly the world model draws what
    it draws, and whether any threshold would part its successes from its inventions. Episodes
    without a probability (failed runs) are left out, the pairs named as episode_agreement counts
    them: {"both_success": {"0-0.05": n, ..., "0.95-1": n}, "missed": ..., "invented": ..., "both_fail": ...}."""
    names = {(True, True): "both_success", (True, False): "missed",
             (False, True): "invented", (False, False): "both_fail"}
    bands = [f"{lo:g}-{hi:g}" for lo, hi in zip(PROBABILITY_BANDS, PROBABILITY_BANDS[1:])]
    out = {name: dict.fromkeys(bands, 0) for name in names.values()}
    for p, t, d in zip(probability, true, drawn):
        if p is None:
            continue
        # Each band holds its lower edge; the last also 1.
        out[names[(bool(t), bool(d))]][bands[int(np.searchsorted(PROBABILITY_BANDS[1:-1], p, side="right"))]] += 1
    return out


def summarize(truth: dict, estimates: dict, judged: dict, tasks: list[str], variants: list[str], chunk: int,
              replayed: dict | None = None) -> dict:
    """Agreement of the world model's estimates with the truth (per episode [first success step or
    None, closest approach in cm]); `judged` (the judge on the simulator's frames) adds that column
    and its own agreement, the judge's share of the error; `replayed` (replay_world_model) the
    simulator's outcome of the world model's own episodes, which splits the rest of the error."""
    rows, pooled_true, pooled_est, pooled_first = [], [], [], []
    paired_by_rate: list = []  # per row: its episodes' (true success, drawn success)
    approach: dict = {}
    # Per task, per world-model episode: (replay succeeded, drawn as a success, replay's closest
    # approach in cm, the judge's probability on the world model's frames).
    replayed_by_task: dict = {t: [] for t in tasks}
    for t in tasks:
        # A cut study may lack a variant in some task (study.json's "cut" names those rates).
        for v in [v for v in variants if v in estimates[t]]:
            est = estimates[t][v]
            # Episode k of a task is the k-th held-out placement and policy seed in both; a rate is
            # scored over the episodes the world model finished (all of them, unless a study was cut).
            by_episode = {e["episode"]: bool(e["success"]) for e in est}
            probability_of = {e["episode"]: e.get("success_probability") for e in est}
            done = [k for k in range(len(truth[t][v])) if k in by_episode]
            first = [truth[t][v][k][0] for k in done]
            true_ok = [f is not None for f in first]
            drawn_ok = [by_episode[k] for k in done]
            pooled_first += first
            pooled_true += true_ok
            pooled_est += drawn_ok
            paired_by_rate.append(list(zip(true_ok, drawn_ok)))
            near, succeeded, drawn = approach.setdefault(t, ([], [], []))
            near += [truth[t][v][k][1] for k in done]
            succeeded += true_ok
            drawn += drawn_ok
            row = {"task": t, "variant": v, "episodes": len(first), "true": float(np.mean(true_ok)),
                   "estimated": float(np.mean([e["success"] for e in est])), "errors": sum(e["error"] is not None for e in est),
                   "judged_simulator": float(np.mean([judged[t][v][k] >= THRESHOLD for k in done])),
                   "per_episode": episode_agreement(true_ok, drawn_ok),
                   "by_success_chunk": by_success_chunk(first, drawn_ok, chunk)}
            if replayed is not None:
                outcome = replayed[t][v]
                # Per world-model episode: [episode, drawn as a success, replay's first success step
                # or None, replay's closest approach in cm, the hand's offset there (cm, x y z; for
                # contact_map.py)].
                row["replayed_episodes"] = [[k, by_episode[k], *outcome[k]] for k in sorted(by_episode)]
                again = [(f is not None, d, cm, probability_of[k]) for k, d, f, cm, *_ in row["replayed_episodes"]]
                row["replayed"] = float(np.mean([a[0] for a in again]))
                row["per_episode_replayed"] = episode_agreement([a[0] for a in again], [a[1] for a in again])
                # Where this variant's hands went and what each world drew there (run 27's table).
                row["by_approach_replayed"] = by_approach([a[2] for a in again], [a[0] for a in again], [a[1] for a in again])
                replayed_by_task[t] += again
            rows.append(row)
    per_task = {}
    for t in tasks:
        mine = [r for r in rows if r["task"] == t]
        per_task[t] = agreement([r["variant"] for r in mine], [r["estimated"] for r in mine], [r["true"] for r in mine])
        per_task[t]["pearson_r_95"] = pearson_interval([p for r, p in zip(rows, paired_by_rate) if r["task"] == t])
    overall = agreement([f"{r['variant']}/{r['task']}" for r in rows], [r["estimated"] for r in rows], [r["true"] for r in rows])
    overall["pearson_r_95"] = pearson_interval(paired_by_rate)
    mean = lambda v, key: float(np.mean([r[key] for r in rows if r["variant"] == v]))
    # A mean over tasks needs the variant in every task.
    complete = [v for v in variants if all(v in estimates[t] for t in tasks)]
    by_variant = agreement(complete, [mean(v, "estimated") for v in complete], [mean(v, "true") for v in complete]) if complete else None
    judge_alone = agreement([f"{r['variant']}/{r['task']}" for r in rows], [r["judged_simulator"] for r in rows], [r["true"] for r in rows])
    out = {"rates": rows, "per_task": per_task, "all": overall, "variants_mean_over_tasks": by_variant,
           "judge_on_simulator_frames": judge_alone, "per_episode": episode_agreement(pooled_true, pooled_est),
           "by_success_chunk": by_success_chunk(pooled_first, pooled_est, chunk),
           "by_approach": {t: by_approach(*approach[t]) for t in tasks}}
    out["per_family"], out["per_split"] = by_family(rows, paired_by_rate)
    if replayed is not None:
        names = [f"{r['variant']}/{r['task']}" for r in rows]
        column = lambda eps, i: [a[i] for a in eps]
        pooled = [a for t in tasks for a in replayed_by_task[t]]
        out["replayed"] = {
            # The world model's outcomes against the simulator's for the same actions: its own error.
            "estimated_vs_replayed": agreement(names, [r["estimated"] for r in rows], [r["replayed"] for r in rows]),
            "per_episode": episode_agreement(column(pooled, 0), column(pooled, 1)),
            # The policies acting on the world model's frames instead of the simulator's: the rest.
            "replayed_vs_true": agreement(names, [r["replayed"] for r in rows], [r["true"] for r in rows]),
            "by_approach": {t: by_approach(column(eps, 2), column(eps, 0), column(eps, 1)) for t, eps in replayed_by_task.items()},
            # The judge's probability on the world model's frames by the replay's outcome and its own.
            "by_probability": {t: by_probability(column(eps, 3), column(eps, 0), column(eps, 1)) for t, eps in replayed_by_task.items()},
        }
    return out


def family_of(variant: str) -> tuple[str, str]:
    """(family, split) of a variant: families.py's, or `degraded` (development) for policies.py's
    own variants, the scripted expert degraded one way each."""
    found = families.family_of(variant)
    return (found, families.FAMILIES[found].split) if found is not None else ("degraded", "development")


def by_family(rows: list[dict], paired_by_rate: list) -> tuple[dict, dict]:
    """Agreement per policy family and per split (development / test): over the rates of each, as
    `all` is over every rate, with the per-episode counts (invented and missed successes) and the
    judge's agreement on the simulator's frames of the same episodes."""
    groups: dict = {}
    for row, paired in zip(rows, paired_by_rate):
        family, split = family_of(row["variant"])
        row["family"], row["split"] = family, split
        for key in (("family", family), ("split", split)):
            groups.setdefault(key, []).append((row, paired))

    def score(members) -> dict:
        names = [f"{r['variant']}/{r['task']}" for r, _ in members]
        pairs = [p for _, ps in members for p in ps]
        out = agreement(names, [r["estimated"] for r, _ in members], [r["true"] for r, _ in members])
        out["pearson_r_95"] = pearson_interval([ps for _, ps in members])
        out["per_episode"] = episode_agreement([t for t, _ in pairs], [e for _, e in pairs])
        out["judge_on_simulator_frames"] = agreement(names, [r["judged_simulator"] for r, _ in members], [r["true"] for r, _ in members])
        return out

    families = {name: {"split": members[0][0]["split"], **score(members)} for (kind, name), members in groups.items() if kind == "family"}
    splits = {name: score(members) for (kind, name), members in groups.items() if kind == "split"}
    return families, splits


def fmt(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def svg_scatter(rows: list[dict], tasks: list[str], title: str) -> str:
    """Estimated against true success rates, one colour per task, with the diagonal."""
    size, pad = 420, 50
    colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e"]
    px = lambda v: pad + v * (size - 2 * pad)
    py = lambda v: size - pad - v * (size - 2 * pad)
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{size}" font-family="sans-serif" font-size="11">',
           f'<rect width="{size}" height="{size}" fill="white"/>',
           f'<text x="{size / 2}" y="20" text-anchor="middle" font-size="13">{title}</text>',
           f'<line x1="{px(0)}" y1="{py(0)}" x2="{px(1)}" y2="{py(1)}" stroke="#bbb" stroke-dasharray="4 3"/>',
           f'<rect x="{px(0)}" y="{py(1)}" width="{px(1) - px(0)}" height="{py(0) - py(1)}" fill="none" stroke="black"/>']
    for k in range(0, 11, 2):
        v = k / 10
        out.append(f'<text x="{px(v)}" y="{py(0) + 15}" text-anchor="middle">{v:.1f}</text>')
        out.append(f'<text x="{px(0) - 6}" y="{py(v) + 4}" text-anchor="end">{v:.1f}</text>')
    out.append(f'<text x="{size / 2}" y="{size - 10}" text-anchor="middle">true success rate (simulator)</text>')
    out.append(f'<text x="14" y="{size / 2}" text-anchor="middle" transform="rotate(-90 14 {size / 2})">estimated (world model)</text>')
    for i, t in enumerate(tasks):
        c = colours[i % len(colours)]
        out.append(f'<text x="{px(0) + 8}" y="{py(1) + 16 + 14 * i}" fill="{c}">{t}</text>')
        for r in rows:
            if r["task"] == t:
                out.append(f'<circle cx="{px(r["true"]):.1f}" cy="{py(r["estimated"]):.1f}" r="4" fill="{c}" fill-opacity="0.8">'
                           f'<title>{r["variant"]}: true {r["true"]:.2f}, estimated {r["estimated"]:.2f}</title></circle>')
                out.append(f'<text x="{px(r["true"]) + 6:.1f}" y="{py(r["estimated"]) - 4:.1f}" fill="{c}" font-size="9">{r["variant"]}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


# --- servers and evaluate --------------------------------------------------------------------------
def wait_ready(proc: subprocess.Popen, ready: str, what: str, log: str, limit: float = 300.0) -> dict:
    start = time.time()
    while not os.path.exists(ready):
        if proc.poll() is not None:
            raise SystemExit(f"study: the {what} exited ({proc.returncode}) before listening; its log {log}:\n{tail(log)}")
        if time.time() - start > limit:
            raise SystemExit(f"study: the {what} did not listen within {limit:.0f} s; its log {log}:\n{tail(log)}")
        time.sleep(0.2)
    with open(ready) as f:
        return json.load(f)


def tail(path: str, lines: int = 20) -> str:
    try:
        with open(path, errors="replace") as f:
            return "".join(f.readlines()[-lines:])
    except OSError:
        return ""


def toml_str(s: str) -> str:
    return json.dumps(s)


def write_config(path: str, variants: list[str], ports: dict, judge_url: str, data: str, episodes: dict, a) -> None:
    lines = [
        "# Written by bench/metaworld/study.py.",
        f"horizon = {a.horizon}",
        f'resolution = "{a.resolution}x{a.resolution}"',
        "stop_on_success = true",
        "",
        "[observation]",
        'image_keys = ["observation/image"]',
        f'image_size = "{a.resolution}x{a.resolution}"',
        'state_key = "observation/state"',
        'actions_key = "actions"',
        "",
        "[judge]",
        'kind = "http"',
        f"url = {toml_str(judge_url)}",
        f"threshold = {THRESHOLD}",
        "",
    ]
    for v in variants:
        lines += ["[[policies]]", f"name = {toml_str(v)}", f'url = "ws://127.0.0.1:{ports[v]}"',
                  'adapter = { kind = "eef_abs", indices = [0, 1, 2, 3] }', ""]
    for t, eps in episodes.items():
        lines += ["[[tasks]]", f"name = {toml_str(t)}", f"prompt = {toml_str(t)}", f"dataset = {toml_str(os.path.abspath(data))}",
                  f"episodes = [{', '.join(str(p) for p, _ in eps)}]", 'pose_actions = "observation.state:0-3"', ""]
    write_text(path, "\n".join(lines))


def evaluate_env(wm: list[str], jobs: int, environ) -> dict:
    """The environment of each of `jobs` `bwm evaluate` processes given the world-model flags `wm`.
    On the CPU each gets its share of the cores for libtorch's CPU threads (by default every one
    would start a thread per core, and --jobs of them oversubscribe the machine); on a CUDA device
    bwm keeps its CPU pool to one thread by itself (spinning threads slow its launch-bound steps:
    docs/performance.md, "CPU threads beside the GPU"), unless OMP_NUM_THREADS says otherwise."""
    device = "auto"
    for i, w in enumerate(wm):
        if w == "--device" and i + 1 < len(wm):
            device = wm[i + 1]
        elif w.startswith("--device="):
            device = w.split("=", 1)[1]
    if device.startswith("cuda"):
        return dict(environ)
    return dict(environ, OMP_NUM_THREADS=str(max(1, (os.cpu_count() or 1) // jobs)))


def run_evaluations(groups, a, ports, judge_url, episodes) -> dict:
    """Runs one `bwm evaluate` per variant group at once; returns {task: {variant: [record]}}."""
    procs = []
    # An earlier study in this folder with more groups left eval-N folders this one does not write.
    written = {f"eval-{g}" for g in range(len(groups))}
    for stale in glob.glob(os.path.join(a.out, "eval-*")):
        if os.path.basename(stale) not in written:
            shutil.rmtree(stale)
    for g, variants in enumerate(groups):
        out = os.path.join(a.out, f"eval-{g}")
        os.makedirs(out, exist_ok=True)
        config = os.path.join(out, "evaluate.toml")
        write_config(config, variants, ports, judge_url, a.data, episodes, a)
        cmd = [a.bwm, "evaluate", "--config", config, "--out", out, "--episodes-in-flight", str(a.episodes_in_flight),
               "--streams", str(a.streams), *a.wm]
        log = open(os.path.join(out, "evaluate.log"), "w")
        print(f"study: evaluate {g}: {', '.join(variants)}: {shlex.join(cmd)}", flush=True)
        env = evaluate_env(a.wm, len(groups), os.environ)
        procs.append((g, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), log, out))
    total = sum(len(v) for v in groups) * sum(len(e) for e in episodes.values())
    start, last = time.time(), 0.0
    while any(p.poll() is None for _, p, _, _ in procs):
        time.sleep(1.0)
        if time.time() - last > 15:
            last = time.time()
            done = sum(count_lines(os.path.join(o, "episodes.jsonl")) for _, _, _, o in procs)
            print(f"study: {done}/{total} world-model episodes ({time.time() - start:.0f} s)", flush=True)
    failed = [(g, p.returncode, o) for g, p, _, o in procs if p.returncode != 0]
    for _, _, log, _ in procs:
        log.close()
    if failed:
        msg = "\n".join(f"evaluate {g} exited {rc}; {o}/evaluate.log ends:\n{tail(os.path.join(o, 'evaluate.log'))}" for g, rc, o in failed)
        raise SystemExit(f"study: {msg}")
    print(f"study: {total} world-model episodes in {time.time() - start:.0f} s", flush=True)
    return read_estimates([o for _, _, _, o in procs])


def read_estimates(dirs: list[str], cut: bool = False) -> dict:
    """{task: {variant: [record]}} from the episodes.jsonl that `bwm evaluate` wrote in each of `dirs`.
    `cut`: the study was stopped, so a process may have written no file yet, or half of its last line."""
    estimates: dict = {}
    for o in dirs:
        path = os.path.join(o, "episodes.jsonl")
        if not os.path.isfile(path):
            if cut:
                continue
            raise SystemExit(f"study: no {path} (was the study run in this folder?)")
        with open(path) as f:
            lines = f.read().split("\n")
        for i, line in enumerate(lines):
            if not line.strip():
                continue
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                if cut and i == len(lines) - 1:
                    continue
                raise SystemExit(f"study: line {i + 1} of {path} is not JSON")
            mine = estimates.setdefault(r["task"], {}).setdefault(r["policy"], [])
            if any(e["episode"] == r["episode"] for e in mine):
                raise SystemExit(f"study: episode {r['episode']} of {r['policy']}/{r['task']} appears twice in {', '.join(dirs)}")
            mine.append(r)
    return estimates


def count_lines(path: str) -> int:
    try:
        with open(path) as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


def at_least_one(text: str) -> int:
    """An argparse type: an integer of at least 1."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def split_flags(argv: list[str]) -> tuple[list[str], list[str]]:
    """The arguments before `--` and the world model's flags after it (none without `--`)."""
    if "--" not in argv:
        return argv, []
    i = argv.index("--")
    return argv[:i], argv[i + 1:]


def add_episode_arguments(ap: argparse.ArgumentParser) -> None:
    """The options naming the held-out episodes, the variants and how they run (study.py's and
    teacher.py's)."""
    ap.add_argument("--data", required=True, help="held-out dataset from generate.py (seeds never trained on)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--tasks", default=",".join(policies.VARIANTS))
    ap.add_argument("--variants", help="comma-separated (default: every variant the tasks share, families.py's too)")
    ap.add_argument("--episodes", type=at_least_one, default=50, help="per task and variant")
    ap.add_argument("--horizon", type=at_least_one, default=120, help="frames after x0, in the simulator and the world model")
    ap.add_argument("--chunk", type=at_least_one, default=24, help="actions per policy reply (the world model's K)")
    ap.add_argument("--resolution", type=at_least_one, default=64)
    ap.add_argument("--workers", type=at_least_one, default=os.cpu_count() or 1, help="processes running the simulator")
    ap.add_argument("--bwm", default=os.path.join(os.environ.get("CARGO_TARGET_DIR", "target"), "release", "bwm"))


def tasks_checked(ap: argparse.ArgumentParser, a) -> list[str]:
    """--tasks, each one the policies know."""
    tasks = a.tasks.split(",")
    for t in tasks:
        if t not in policies.VARIANTS:
            ap.error(f"unknown task {t!r} (known: {', '.join(policies.VARIANTS)})")
    return tasks


def tasks_and_variants(ap: argparse.ArgumentParser, a) -> tuple[list[str], list[str]]:
    """--tasks and --variants checked (every named variant exists for every task; by default the
    variants the tasks share, policies.py's in its order, then every family's of families.py)."""
    tasks = tasks_checked(ap, a)
    shared = [v for v in policies.VARIANTS[tasks[0]] if all(v in policies.VARIANTS[t] for t in tasks)] + families.variants(tasks=tasks)
    variants = a.variants.split(",") if a.variants else shared
    problem = known_variants.check_variants(tasks, variants)
    if problem:
        ap.error(f"{problem} (shared named variants: {', '.join(shared)})")
    return tasks, variants


def main(argv=None) -> None:
    argv, wm = split_flags(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--judge", help="judge.pt from judge.py train")
    add_episode_arguments(ap)
    ap.add_argument("--jobs", type=at_least_one, default=4, help="bwm evaluate processes at once (variants split among them)")
    ap.add_argument("--episodes-in-flight", type=at_least_one, default=1,
                    help="episodes each bwm evaluate process runs at once, its chunks generated as one batch")
    ap.add_argument("--streams", type=at_least_one, default=1,
                    help="lanes each bwm evaluate process splits its episodes in flight into, taking turns on CUDA streams "
                         "of their own (bwm evaluate --streams)")
    ap.add_argument("--truth-only", action="store_true", help="measure (or find cached) the true rates in DIR/truth.json and stop")
    ap.add_argument("--judged-only", action="store_true",
                    help="judge the simulator's frames of the episodes (or find them cached) in DIR/judged.json and stop")
    ap.add_argument("--rescore", action="store_true",
                    help="score the world-model episodes already in DIR/eval-*/ again (the truth measured again when its "
                         "cache is of another kind), without running the world model or the judge; a study cut before its "
                         "study.json is scored over the episodes it finished")
    a = ap.parse_args(argv)
    a.wm = wm
    tasks, variants = tasks_and_variants(ap, a)
    if sum([a.truth_only, a.judged_only, a.rescore]) > 1:
        ap.error("--truth-only, --judged-only and --rescore exclude each other")
    if a.truth_only or a.rescore:
        pass
    elif not a.judge or not os.path.isfile(a.judge):
        ap.error(f"no judge at {a.judge} (judge.py train writes it)")
    elif a.judged_only:
        pass
    elif not os.access(a.bwm, os.X_OK):
        ap.error(f"no bwm binary at {a.bwm} (make build, or pass --bwm)")
    elif not wm:
        ap.error("pass the world model's flags after `--` (--checkpoint, --vae, --stats, ...)")
    if a.judge and not (a.truth_only or a.rescore):
        # Read once here: a judge the worker processes could not load (another format) would
        # otherwise fail in their initializer, which a process pool retries without end.
        import judge

        try:
            judge.read_model(a.judge)
        except (ValueError, OSError) as e:
            ap.error(str(e))
    os.makedirs(a.out, exist_ok=True)
    episodes = episodes_by_task(a.data, tasks, a.episodes)
    if not a.rescore:
        # The cloned policies trained once here, in parallel, before the truth measures them and
        # the policy server serves them (which would otherwise train them inside its handlers).
        families.prepare(tasks, variants, a.workers)
    key = truth_key(episodes, a.horizon, a.chunk, a.resolution, variants, families.clones_digest(tasks, variants))
    truth_path = os.path.join(a.out, "truth.json")
    judged_path = os.path.join(a.out, "judged.json")
    # What the judge's verdicts depend on: the episodes, not the form of the truth.
    episodes_key = {k: v for k, v in key.items() if k != "outcome"}
    if a.rescore:
        # Everything checked before the truth is measured again (minutes) or its cache replaced.
        evals = sorted(glob.glob(os.path.join(a.out, "eval-*")))
        if not evals or not os.path.isfile(judged_path):
            raise SystemExit(f"study: --rescore needs a study in {a.out} (eval-*/, judged.json)")
        study_path = os.path.join(a.out, "study.json")
        cut = not os.path.isfile(study_path)
        before = {}
        if not cut:
            with open(study_path) as f:
                before = json.load(f)
        with open(judged_path) as f:
            found = json.load(f)
        # The judge's file is not needed again: its verdicts are kept with the episodes they judged.
        if {k: v for k, v in found["key"].items() if k not in ("judge", "outcome")} != episodes_key:
            raise SystemExit(f"study: {judged_path} was measured for other episodes or variants than --data/--episodes/--variants ask for, or under other policy code ({', '.join(os.path.basename(p) for p in TRUTH_SOURCES)})")
        estimates = read_estimates(evals, cut)
        missing = [f"{v}/{t}" for t in tasks for v in variants if v not in estimates.get(t, {})]
        finished = sum(len(rs) for per in estimates.values() for rs in per.values())
        planned = len(tasks) * len(variants) * a.episodes
        if missing and not cut:
            raise SystemExit(f"study: {a.out}/eval-*/ hold no episodes of {', '.join(missing)}")
        if cut:
            # Scored over what it finished: every rate with episodes (the mean over tasks only over
            # the variants with episodes in every task).
            variants = [v for v in variants if any(v in estimates.get(t, {}) for t in tasks)]
            estimates = {t: {v: rs for v, rs in estimates.get(t, {}).items() if v in variants} for t in tasks}
            tasks = [t for t in tasks if estimates[t]]
            if not tasks:
                raise SystemExit(f"study: the cut study in {a.out} finished no world-model episode")
            scored = sum(len(rs) for per in estimates.values() for rs in per.values())
            print(f"study: {a.out} was cut before its study.json: {finished} of {planned} world-model episodes finished, "
                  f"{scored} scored" + (f" (rates without episodes, left out: {', '.join(missing)})" if missing else ""))
    def judge_the_simulator():
        return cached(judged_path, "judged", {**episodes_key, "judge": file_digest(a.judge)},
                      lambda: judge_simulator(episodes, variants, a.horizon, a.chunk, a.resolution, a.workers, a.judge))

    if a.judged_only:
        judge_the_simulator()
        print(f"study: the judge on the simulator's frames in {judged_path}")
        return
    truth = cached(truth_path, "truth", key, lambda: measure_truth(episodes, variants, a.horizon, a.chunk, a.resolution, a.workers))
    if a.truth_only:
        print(f"study: true success rates in {truth_path}")
        return
    if a.rescore:
        replayed = replay_world_model(estimates, episodes, a.resolution, a.workers)
        summary = summarize(truth, estimates, found["judged"], tasks, variants, a.chunk, replayed)
        for k in ("episodes_per_rate", "horizon", "world_model_flags", "episodes_in_flight", "streams"):
            summary[k] = before.get(k)
        if cut:
            summary["cut"] = {"episodes_finished": finished, "episodes_scored": scored, "episodes_planned": planned,
                              "rates_without_episodes": missing}
        write_summary(a.out, summary, tasks, a.chunk)
        return
    judged = judge_the_simulator()

    # A study of these episodes starts: an earlier one's results in this folder go, so that a study
    # cut short is never read as complete (--rescore then sees it as cut).
    for name in ("study.json", "study.csv", "study.svg"):
        if os.path.exists(os.path.join(a.out, name)):
            os.remove(os.path.join(a.out, name))
    seeds_path = os.path.join(a.out, "episode_seeds.json")
    write_json(seeds_path, key["episodes"], indent=None)
    servers = []
    try:
        python = sys.executable
        for what, cmd, ready in [
            ("policy server", [python, os.path.join(HERE, "policy_server.py"), "--variants", ",".join(variants), "--tasks", ",".join(tasks),
                               "--base-port", "0", "--chunk", str(a.chunk), "--episode-seeds", seeds_path], "policy_ready.json"),
            ("judge", [python, os.path.join(HERE, "judge.py"), "serve", "--model", a.judge, "--port", "0"], "judge_ready.json"),
        ]:
            ready = os.path.join(a.out, ready)
            if os.path.exists(ready):
                os.remove(ready)
            log = ready.replace("_ready.json", ".log")
            proc = subprocess.Popen([*cmd, "--ready", ready], stdout=open(log, "w"), stderr=subprocess.STDOUT)
            servers.append(proc)
            servers_info = wait_ready(proc, ready, what, log)
            if what == "judge":
                judge_url = servers_info["url"]
            else:
                ports = servers_info["ports"]
        jobs = min(a.jobs, len(variants))
        groups = [variants[g::jobs] for g in range(jobs)]
        estimates = run_evaluations(groups, a, ports, judge_url, episodes)
    finally:
        for proc in servers:
            proc.terminate()
        for proc in servers:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()

    replayed = replay_world_model(estimates, episodes, a.resolution, a.workers)
    summary = summarize(truth, estimates, judged, tasks, variants, a.chunk, replayed)
    summary["episodes_per_rate"] = a.episodes
    summary["horizon"] = a.horizon
    summary["world_model_flags"] = wm
    summary["episodes_in_flight"] = a.episodes_in_flight
    summary["streams"] = a.streams
    write_summary(a.out, summary, tasks, a.chunk)


def write_summary(out: str, summary: dict, tasks: list[str], chunk: int) -> None:
    """DIR/study.json, study.csv and study.svg, and the tables on stdout."""
    # The table and the figure first, study.json last: its presence says the study is complete.
    with replacing(os.path.join(out, "study.csv")) as f:
        f.write("task,variant,episodes,true_success_rate,estimated_success_rate,errors,judge_on_simulator_rate,replayed_rate\n")
        for r in summary["rates"]:
            replayed = f"{r['replayed']:.4f}" if "replayed" in r else ""
            f.write(f"{r['task']},{r['variant']},{r['episodes']},{r['true']:.4f},{r['estimated']:.4f},{r['errors']},{r['judged_simulator']:.4f},{replayed}\n")
    a_ = summary["all"]
    title = f"r = {fmt(a_['pearson_r'])}, rho = {fmt(a_['spearman_rho'])}, MAE = {fmt(a_['mae'])}"
    write_text(os.path.join(out, "study.svg"), svg_scatter(summary["rates"], tasks, title))
    write_json(os.path.join(out, "study.json"), summary)
    print(f"{'task':26s} {'variant':10s} {'true':>6s} {'world model':>11s} {'judge on simulator':>18s} {'same outcome':>12s} {'kappa':>6s}"
          f" {'replayed':>8s}")
    for r in summary["rates"]:
        e = r["per_episode"]
        print(f"{r['task']:26s} {r['variant']:10s} {r['true']:6.2f} {r['estimated']:11.2f} {r['judged_simulator']:18.2f} "
              f"{e['agreement']:12.2f} {fmt(e['kappa']):>6s} {fmt(r.get('replayed')):>8s}")
    for name, g in [*summary["per_task"].items(), ("all variants x tasks", summary["all"]), ("variants (mean over tasks)", summary["variants_mean_over_tasks"]),
                    ("the judge alone, on the simulator's frames", summary["judge_on_simulator_frames"])]:
        if g is None:
            continue
        interval = g.get("pearson_r_95")
        within = f" (95% over redrawn episodes {interval[0]:.3f}-{interval[1]:.3f})" if interval else ""
        print(f"{name}: Pearson r {fmt(g['pearson_r'])}{within}, Spearman {fmt(g['spearman_rho'])}, MAE {fmt(g['mae'])}, "
              f"best {'/'.join(g['best_true'])} ranked first: {g['best_ranked_first']}")
    for kind in ("per_split", "per_family"):
        for name, g in summary[kind].items():
            interval, e, j = g.get("pearson_r_95"), g["per_episode"], g["judge_on_simulator_frames"]
            within = f" (95% {interval[0]:.3f}-{interval[1]:.3f})" if interval else ""
            label = f"{name} ({g['split']})" if kind == "per_family" else f"{name} families"
            print(f"{label}, {g['n']} rates: Pearson r {fmt(g['pearson_r'])}{within}, Spearman {fmt(g['spearman_rho'])}, MAE {fmt(g['mae'])}, "
                  f"best ranked first: {g['best_ranked_first']}; invented {e['invented']}, missed {e['missed']} of {e['n']} episodes; "
                  f"the judge on the simulator's frames r {fmt(j['pearson_r'])}")
    e = summary["per_episode"]
    print(f"per episode, pooled: the world model draws the simulator's outcome in {e['agreement']:.3f} of {e['n']} episodes "
          f"(chance {e['chance']:.3f}, kappa {fmt(e['kappa'])}; missed {e['missed']} successes, invented {e['invented']})")
    cells = ", ".join(f"{name} {c['drawn']}/{c['true']}" for name, c in summary["by_success_chunk"].items())
    print(f"drawn as successes, by the chunk of {chunk} steps in which the simulator succeeds (pooled): {cells}")
    for t, bands in summary["by_approach"].items():
        cells = ", ".join(f"{name} {c['true']}/{c['drawn']}/{c['episodes']}" for name, c in bands.items())
        print(f"{t}, by the hand's closest approach to the object in the simulator (true/drawn/episodes): {cells}")
    if "replayed" in summary:
        g, e = summary["replayed"]["estimated_vs_replayed"], summary["replayed"]["per_episode"]
        print(f"the world model's episodes replayed in the simulator: its rates against the replays' Pearson r {fmt(g['pearson_r'])}, "
              f"MAE {fmt(g['mae'])}; per episode the same outcome in {e['agreement']:.3f} (kappa {fmt(e['kappa'])}; "
              f"missed {e['missed']}, invented {e['invented']})")
        g = summary["replayed"]["replayed_vs_true"]
        print(f"the replays' rates against the truth (the policies on the world model's frames): Pearson r {fmt(g['pearson_r'])}, MAE {fmt(g['mae'])}")
        for t, bands in summary["replayed"]["by_approach"].items():
            cells = ", ".join(f"{name} {c['true']}/{c['drawn']}/{c['episodes']}" for name, c in bands.items())
            print(f"{t}, by the replayed hand's closest approach to the object (replay succeeds/drawn/episodes): {cells}")
        for t, kinds in summary["replayed"]["by_probability"].items():
            cells = "; ".join(f"{kind} {' '.join(str(n) for n in bands.values())}" for kind, bands in kinds.items())
            print(f"{t}, the judge's probability on the world model's frames in bands {' '.join(next(iter(kinds.values())))}: {cells}")
    print(f"study: wrote {os.path.join(out, 'study.json')}, study.csv, study.svg")


if __name__ == "__main__":
    main()
