#!/usr/bin/env python3
"""The sampler sweep's report (bench/metaworld/sweep.sh): for each (solver, steps) setting, the
open-loop fidelity (`bwm fidelity`'s PSNR/SSIM at each horizon, per task and over all) and the
closed-loop study's success estimates, against a baseline setting (50 Euler steps); and the
default the real-time issue asks for: the fewest steps whose PSNR at the chosen horizon stays
within --max-psnr-drop dB of the baseline's for every task and whose success estimates stay
within --max-rate-change of the baseline's: their mean absolute change over the studied rates
(--rate-statistic mean, the default) or every one of them (max). Both are reported. With 50
episodes per rate one episode moves a rate by 0.02, so `max` allows no more than one flipped
episode per variant, well inside a rate's own sampling error (about 0.07 at 0.5); the mean over
16 rates has noise of the bound's size.

usage: sweep.py ROOT [--baseline euler-50] [--horizon 32] [--max-psnr-drop 0.5] [--max-rate-change 0.02]
                     [--rate-statistic mean|max]
ROOT holds one folder per setting, named SOLVER-STEPS, SOLVER-STEPS-fp8SCALING (the DiT's
linears in FP8: reported, never the default) or either with -streamsN (the episodes in flight in
N lanes on CUDA streams of their own: the same sampler, timed; reported, never the default), each
with fidelity/fidelity.json and study/study.json, and timings.tsv (each stage's seconds, as
sweep.sh writes them) when there is one; writes ROOT/sweep.json and prints a table.
"""

import argparse
import json
import os
import re

from files import write_json


def load_setting(folder: str) -> dict | None:
    """The measurements of one setting folder; None when either is missing."""
    fid, study = os.path.join(folder, "fidelity", "fidelity.json"), os.path.join(folder, "study", "study.json")
    if not (os.path.isfile(fid) and os.path.isfile(study)):
        return None
    seconds = {}
    timings = os.path.join(folder, "timings.tsv")
    if os.path.isfile(timings):
        for line in open(timings):
            stage, _, value = line.strip().partition("\t")
            if value:
                seconds[stage] = float(value)  # the last time of each stage
    with open(fid) as f:
        fidelity = json.load(f)
    with open(study) as f:
        s = json.load(f)
    rates = {f"{r['variant']}/{r['task']}": r["estimated"] for r in s["rates"]}
    return {"fidelity": fidelity, "rates": rates, "pearson_r": s["all"]["pearson_r"],
            "best_ranked_first": s["all"]["best_ranked_first"], "seconds": seconds}


def horizon_psnr(fidelity: dict, horizon: str) -> dict:
    """PSNR at `horizon` per task and over all tasks ("all")."""
    out = {task: v["horizons"][horizon]["model"]["psnr"] for task, v in fidelity.get("tasks", {}).items()}
    out["all"] = fidelity["all"]["horizons"][horizon]["model"]["psnr"]
    return out


def compare(settings: dict, baseline: str, horizon: str, max_psnr_drop: float, max_rate_change: float,
            rate_statistic: str = "mean") -> dict:
    """Each setting against the baseline, and the default: the fewest steps without FP8 or lanes
    that stay within both bounds (ties: the smaller PSNR drop)."""
    if baseline not in settings:
        raise SystemExit(f"sweep: the baseline {baseline} was not measured (settings: {', '.join(sorted(settings)) or 'none'})")
    base = settings[baseline]
    base_psnr = horizon_psnr(base["fidelity"], horizon)
    rows = []
    for name, s in settings.items():
        m = re.fullmatch(r"(.+?)-(\d+)(?:-fp8(tensor|row))?(?:-streams(\d+))?", name)
        if not m:
            raise SystemExit(f"sweep: setting folder '{name}' is not SOLVER-STEPS, SOLVER-STEPS-fp8SCALING or either with -streamsN")
        psnr = horizon_psnr(s["fidelity"], horizon)
        drop = max(base_psnr[t] - psnr[t] for t in base_psnr)
        shared = sorted(set(base["rates"]) & set(s["rates"]))
        if not shared:
            raise SystemExit(f"sweep: {name} and {baseline} share no studied variant")
        changes = [abs(s["rates"][k] - base["rates"][k]) for k in shared]
        change = {"max": max(changes), "mean": sum(changes) / len(changes)}
        rows.append({"setting": name, "solver": m.group(1), "steps": int(m.group(2)), "fp8": m.group(3),
                     "streams": int(m.group(4) or 1), "seconds": s.get("seconds", {}), "psnr": psnr,
                     "psnr_drop": drop, "max_rate_change": change["max"], "mean_rate_change": change["mean"],
                     "pearson_r": s["pearson_r"], "best_ranked_first": s["best_ranked_first"],
                     "within": drop <= max_psnr_drop + 1e-9 and change[rate_statistic] <= max_rate_change + 1e-9})
    rows.sort(key=lambda r: (r["steps"], r["solver"], r["fp8"] or "", r["streams"]))
    if base_fp8 := rows[[r["setting"] for r in rows].index(baseline)]["fp8"]:
        raise SystemExit(f"sweep: the baseline {baseline} runs in FP8 ({base_fp8}); compare against an exact one")
    # The baseline is always within, so there is always a default.
    default = min((r for r in rows if r["within"] and r["fp8"] is None and r["streams"] == 1),
                  key=lambda r: (r["steps"], r["psnr_drop"]))["setting"]
    return {"baseline": baseline, "horizon": int(horizon), "max_psnr_drop": max_psnr_drop,
            "max_rate_change": max_rate_change, "rate_statistic": rate_statistic, "settings": rows, "default": default}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root")
    p.add_argument("--baseline", default="euler-50")
    p.add_argument("--horizon", default="32")
    p.add_argument("--max-psnr-drop", type=float, default=0.5)
    p.add_argument("--max-rate-change", type=float, default=0.02)
    p.add_argument("--rate-statistic", choices=["mean", "max"], default="mean",
                   help="which change of the success estimates --max-rate-change bounds")
    a = p.parse_args(argv)
    settings = {}
    for name in sorted(os.listdir(a.root)):
        s = load_setting(os.path.join(a.root, name))
        if s is not None:
            settings[name] = s
    report = compare(settings, a.baseline, a.horizon, a.max_psnr_drop, a.max_rate_change, a.rate_statistic)
    write_json(os.path.join(a.root, "sweep.json"), report)
    print(f"| setting | PSNR h={a.horizon} (all) | drop vs {a.baseline} (worst task) | success change, mean / largest | Pearson r | best first | within | fidelity / study seconds |")
    print("|---|---|---|---|---|---|---|---|")
    seconds = lambda r, k: format(r["seconds"][k], ".1f") if k in r["seconds"] else "-"
    for r in report["settings"]:
        print(f"| {r['setting']} | {r['psnr']['all']:.2f} | {r['psnr_drop']:+.2f} dB | {r['mean_rate_change']:.3f} / {r['max_rate_change']:.2f} | "
              f"{'n/a' if r['pearson_r'] is None else format(r['pearson_r'], '.3f')} | {'yes' if r['best_ranked_first'] else 'no'} | "
              f"{'yes' if r['within'] else 'no'} | {seconds(r, 'fidelity')} / {seconds(r, 'study')} |")
    print(f"sweep: default {report['default']} ({os.path.join(a.root, 'sweep.json')})")


if __name__ == "__main__":
    main()
