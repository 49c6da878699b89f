"""The realtime stage's table: each cheaper setting (fewer teacher steps, a distilled student, the
light decoder) against the reference (the teacher's most steps with the VAE's decoder), in the
open loop and in closed loop, and whether it lies within the real-time issue's bounds.

    python realtime.py RT_DIR [--reference t50-full] [--json OUT]

RT_DIR is recipe.sh's realtime folder: agreement.json (agreement.py over roll/SETTING/) and, for
the settings studied, study-SETTING/study.json (study.py on the same episodes, truth and judge).
Per setting: PSNR over the first h generated frames against the reference's frames and against the
recorded ones, the latter's change against the reference's; closed loop, Pearson r over every rate
and per family, MAE, invented / missed successes, r's change against the reference's. Within: the
recorded-frame PSNR at most 0.5 dB under the reference's and r at most 0.02 under it (the issue's
bounds): yes, no (either fails), or unchecked (a bound that could not be checked, as for a setting
not studied in closed loop)."""

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from files import write_json  # noqa: E402

PSNR_BOUND_DB = 0.5
R_BOUND = 0.02


def setting_name(path: str) -> str:
    """A rollout folder's setting: its last path component."""
    return os.path.basename(os.path.normpath(path))


def closed_loop(study: dict) -> dict:
    """A study.json's closed-loop summary: over every rate, per episode and per family (this
    table's, and transfer.sh's for each of its arms)."""
    episode = study["per_episode"]
    return {
        "pearson_r": study["all"]["pearson_r"],
        "spearman_rho": study["all"]["spearman_rho"],
        "mae": study["all"]["mae"],
        "best_ranked_first": study["all"]["best_ranked_first"],
        "invented": episode["invented"],
        "missed": episode["missed"],
        "episodes": episode["n"],
        "families": {name: f["pearson_r"] for name, f in study.get("per_family", {}).items()},
    }


def report(rt: str, reference: str) -> dict:
    path = os.path.join(rt, "agreement.json")
    if not os.path.isfile(path):
        raise SystemExit(f"realtime: no {path} (agreement.py over {rt}/roll/ writes it)")
    with open(path) as f:
        agreement = json.load(f)
    opened = {setting_name(p): r for p, r in agreement["settings"].items()}
    if reference not in opened:
        raise SystemExit(f"realtime: {path} has no setting {reference} (it has {', '.join(opened)})")
    ref_recorded = opened[reference].get("recorded_h")
    studies = {}
    for name in opened:
        p = os.path.join(rt, f"study-{name}", "study.json")
        if os.path.isfile(p):
            with open(p) as f:
                studies[name] = closed_loop(json.load(f))
    ref_r = studies.get(reference, {}).get("pearson_r")
    rows = {}
    for name, o in opened.items():
        row = {"open_loop": dict(o)}
        # Each bound True, False, or None where it cannot be checked (no recorded frames; a setting
        # or the reference not studied): within only when both hold, out when either fails.
        open_ok = closed_ok = None
        if ref_recorded is not None and "recorded_h" in o:
            row["open_loop"]["recorded_h_change"] = o["recorded_h"] - ref_recorded
            open_ok = row["open_loop"]["recorded_h_change"] >= -PSNR_BOUND_DB
        if name in studies:
            row["closed_loop"] = dict(studies[name])
            r = studies[name]["pearson_r"]
            if ref_r is not None and r is not None:
                row["closed_loop"]["pearson_r_change"] = r - ref_r
                closed_ok = row["closed_loop"]["pearson_r_change"] >= -R_BOUND
            elif ref_r is not None:
                # Every rate drawn alike (r undefined) where the reference's vary: no ranking left.
                closed_ok = False
        within = False if False in (open_ok, closed_ok) else True if open_ok and closed_ok else None
        row["within"] = within
        rows[name] = row
    return {"reference": reference, "horizon": agreement["horizon"], "psnr_bound_db": PSNR_BOUND_DB,
            "r_bound": R_BOUND, "settings": rows}


def number(v) -> str:
    """A correlation for the table; n/a where it is undefined."""
    return "  n/a" if v is None else f"{v:.3f}"


def table(result: dict) -> str:
    h = result["horizon"]
    lines = [f"setting      PSNR h={h} vs {result['reference']}  vs recorded (change)   r (change)       MAE    invented/missed  families r            within"]
    for name, row in result["settings"].items():
        o = row["open_loop"]
        recorded = f"{o['recorded_h']:6.2f} ({o.get('recorded_h_change', 0.0):+.2f})" if "recorded_h" in o else "     -         "
        c = row.get("closed_loop")
        if c:
            change = f"({c['pearson_r_change']:+.3f})" if "pearson_r_change" in c else "(n/a)   "
            closed = (f"{number(c['pearson_r'])} {change}  {c['mae']:.3f}  {c['invented']:4d}/{c['missed']:<4d}"
                      f"        {' '.join(f'{k} {number(v)}' for k, v in c['families'].items())}")
        else:
            closed = "not studied"
        verdict = {True: "yes", False: "no", None: "unchecked"}[row["within"]]
        lines.append(f"{name:12s} {o['reference_h']:8.2f}                {recorded}   {closed}   {verdict}")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rt", help="the realtime stage's folder")
    ap.add_argument("--reference", default="t50-full", help="the reference setting (default t50-full)")
    ap.add_argument("--json", help="write the table's figures here too")
    a = ap.parse_args(argv)
    result = report(a.rt, a.reference)
    print(table(result))
    if a.json:
        write_json(a.json, result)


if __name__ == "__main__":
    sys.exit(main())
