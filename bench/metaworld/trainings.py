"""Several trainings' closed-loop studies side by side: how far apart their estimates are, and how
much of their error they share.

    python trainings.py docs/fidelity/study-run34-d0.json docs/fidelity/study-run35-n2.json ... [--json OUT]

Each argument is a study.json written by study.py over the same episodes (every rate's truth must
agree; --families degraded,scripted keeps those families' rates alone, as where one family was
graded otherwise in some of the studies). Printed: per rate the truth, each training's estimate, their mean and range; per training
Pearson r over the rates; for each pair of trainings the mean absolute difference of their
estimates and the r of their averaged estimates (what an evaluator would report that rolls out half
of each rate's episodes in either world model); and the r of all trainings' averaged estimates. When
averaging does not lift r, the trainings' error is a bias they share, not their spread.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from agreement import write_json  # noqa: E402
import families as policy_families  # noqa: E402
import policies  # noqa: E402
from study import family_of, fmt, pearson  # noqa: E402


def label(path: str) -> str:
    """A study's name in the report: its file name without `study-` and `.json`, or its folder's
    name for a `study.json`."""
    base = os.path.basename(path)
    if base == "study.json":
        return os.path.basename(os.path.dirname(os.path.abspath(path)))
    stem = base[: -len(".json")] if base.endswith(".json") else base
    return stem[len("study-"):] if stem.startswith("study-") else stem


def _rates(name: str, study: dict) -> dict[tuple[str, str], tuple[float, float]]:
    try:
        return {(r["task"], r["variant"]): (float(r["true"]), float(r["estimated"])) for r in study["rates"]}
    except (KeyError, TypeError) as e:
        raise ValueError(f"{name}: not a study.json of study.py (its rates lack {e})") from None


def family(variant: str) -> str | None:
    """study.py's family name of a variant the code knows today; None for one it no longer knows
    (a variant since renamed or regraded, kept in an older study)."""
    if variant not in policy_families.variants() and not any(variant in v for v in policies.VARIANTS.values()):
        return None
    return family_of(variant)[0]


def compare(studies: dict[str, dict], families: list[str] | None = None) -> dict:
    """`studies`: name -> study.json, at least two, over the same rates and truth (those of the
    policy `families` alone, study.py's family names, when given)."""
    if len(studies) < 2:
        raise ValueError(f"compare needs at least two studies, got {len(studies)}")
    rates = {name: _rates(name, s) for name, s in studies.items()}
    if families is not None:
        rates = {name: {k: v for k, v in r.items() if family(k[1]) in families} for name, r in rates.items()}
        if not any(rates.values()):
            raise ValueError(f"the studies hold no rate of the families {', '.join(families)}")
    first, *rest = rates
    keys = list(rates[first])
    for name in rest:
        if set(rates[name]) != set(keys):
            only = sorted(set(rates[name]) ^ set(keys))
            raise ValueError(f"{name} and {first} score other rates ({', '.join('/'.join(k) for k in only)})")
        differ = [k for k in keys if abs(rates[name][k][0] - rates[first][k][0]) > 1e-9]
        if differ:
            raise ValueError(f"{name} and {first} hold another truth for {', '.join('/'.join(k) for k in differ)}: "
                             "studies of other episodes or policies cannot be compared rate for rate")
    true = np.array([rates[first][k][0] for k in keys])
    est = {name: np.array([rates[name][k][1] for k in keys]) for name in rates}
    names = list(est)
    mean = np.mean([est[n] for n in names], axis=0)
    rows = [{"task": t, "variant": v, "true": float(true[i]), "estimated": {n: float(est[n][i]) for n in names},
             "mean": float(mean[i]), "low": float(min(est[n][i] for n in names)), "high": float(max(est[n][i] for n in names)),
             "bias": float(mean[i] - true[i])} for i, (t, v) in enumerate(keys)]
    single = {n: pearson(true, est[n]) for n in names}
    pairs = [{"a": a, "b": b, "mean_abs_difference": float(np.mean(np.abs(est[a] - est[b]))),
              "pearson_r_of_mean": pearson(true, (est[a] + est[b]) / 2)} for a, b in itertools.combinations(names, 2)]

    def spread(values):
        values = [v for v in values if v is not None]
        return {"mean": float(np.mean(values)), "min": float(min(values)), "max": float(max(values))} if values else None

    return {"rates": rows, "pearson_r": single, "pairs": pairs,
            "single": spread(single.values()), "pair_means": spread(p["pearson_r_of_mean"] for p in pairs),
            "all_mean": {"pearson_r": pearson(true, mean), "mae": float(np.mean(np.abs(mean - true)))}}


def report(c: dict) -> str:
    names = list(c["pearson_r"])
    lines = ["rate: true; " + ", ".join(names) + "; mean (bias)"]
    for r in c["rates"]:
        lines.append(f"  {r['variant']}/{r['task']}: {fmt(r['true'])}; " + ", ".join(fmt(r["estimated"][n]) for n in names)
                     + f"; {fmt(r['mean'])} ({r['bias']:+.3f})")
    lines.append("pearson r: " + ", ".join(f"{n} {fmt(v)}" for n, v in c["pearson_r"].items()))
    for p in c["pairs"]:
        lines.append(f"  {p['a']} + {p['b']}: estimates {p['mean_abs_difference']:.3f} apart on average, "
                     f"r of their mean {fmt(p['pearson_r_of_mean'])}")
    s, pm = c["single"], c["pair_means"]
    if s and pm:
        lines.append(f"single trainings: r mean {fmt(s['mean'])} ({fmt(s['min'])}-{fmt(s['max'])}); "
                     f"pairs averaged: mean {fmt(pm['mean'])} ({fmt(pm['min'])}-{fmt(pm['max'])}); "
                     f"all {len(names)} averaged: {fmt(c['all_mean']['pearson_r'])} (MAE {fmt(c['all_mean']['mae'])})")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("studies", nargs="+", help="study.json files of study.py, over the same episodes")
    ap.add_argument("--json", help="also write the comparison here")
    ap.add_argument("--families", help="only the rates of these policy families, comma-separated (study.py's names: "
                                       "degraded, scripted, partial, learned, wander)")
    a = ap.parse_args(argv)
    families = a.families.split(",") if a.families else None
    studies = {}
    for path in a.studies:
        name = label(path)
        if name in studies:
            ap.error(f"two studies are named {name}; give them distinct file or folder names")
        try:
            with open(path) as f:
                studies[name] = json.load(f)
        except (OSError, json.JSONDecodeError) as e:
            ap.error(f"cannot read {path}: {e}")
    try:
        c = compare(studies, families)
    except ValueError as e:
        ap.error(str(e))
    print(report(c))
    if a.json:
        write_json(a.json, c)


if __name__ == "__main__":
    main()
