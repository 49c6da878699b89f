"""Where a world model's contact reaches: its episodes counted by where the hand was.

    python contact_map.py runs/X/study/study.json [sbs-wrong/side_by_side.json ...] [--band-cm 2] [--families F,G]
        [--beyond-cm 6] [--json OUT]

Each argument is a study.json (study.py; every rate's world-model episodes, their actions replayed
in the simulator), a side_by_side.json (side_by_side.py; one task and variant) or a teacher.json
(teacher.py; each episode's chunks drawn from the simulator's frames, an episode drawn succeeding
when any of its chunks is). Every episode is
placed by the hand's offset from the object at its closest approach in the simulator (replay): the
axis it lies along in the table plane (`axis`: in front of the object, -y; behind it, +y;
beside it, x) and its horizontal distance, in bands of --band-cm. Per task, axis and band: the
episodes, the simulator's successes and the world model's. Where the simulator's successes stop
and the world model's go on, the world model draws contact the simulator does not make (and the
other way round). Printed as a table; --json writes it. --families keeps those policy families'
variants alone (study.py's names, as trainings.py). Last, over every task and axis, the episodes
whose hand stayed --beyond-cm or more from the object (default 6, past where the simulator's
contact ends): those the world model draws succeeding that the simulator does not (invented
contact), and within it those the simulator succeeds with that the world model does not (missed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from files import write_json  # noqa: E402
from trainings import family  # noqa: E402


def axis(offset) -> str:
    """Which way an `offset` from the object (an aim, a closest approach) points in the table
    plane: "-y" or "+y" within 45 degrees of that axis, else "x" (either side). For the drawer, -y
    is in front of its handle (where its `wrong` variant aims) and x is beside it (where its
    `blind` hand misses a drawer placed off centre)."""
    x, y = float(offset[0]), float(offset[1])
    if abs(y) > abs(x):
        return "-y" if y < 0 else "+y"
    return "x"


AXES = ("-y", "+y", "x")


def bands(distances_cm, band_cm: float, **counted) -> dict:
    """Episodes by distance band of `band_cm` ("LO-HI" in cm, nearest first, empty bands left out):
    per band {"episodes": n, NAME: how many of them are true in the list NAME, ...} for each
    keyword list of flags, one per distance."""
    out = {}
    for i, d in enumerate(distances_cm):
        k = int(d // band_cm)
        cell = out.setdefault(k, {"episodes": 0, **{name: 0 for name in counted}})
        cell["episodes"] += 1
        for name, flags in counted.items():
            cell[name] += bool(flags[i])
    return {f"{k * band_cm:g}-{(k + 1) * band_cm:g}": out[k] for k in sorted(out)}


def load(path: str) -> list[tuple[str, str, list[dict]]]:
    """[(task, variant, episodes)] of a side_by_side.json, a study.json or a teacher.json, each
    episode with `offset_at_closest_cm`, `world_model_success` and `simulator_first_success`;
    ValueError naming `path` otherwise (a study from before the replays kept the hand's offset among
    them, a teacher.json from before its episodes kept it)."""
    try:
        with open(path) as f:
            report = json.load(f)
        if "settings" in report and isinstance(report.get("episodes"), dict):
            threshold = float(report["settings"]["threshold"])
            reports = []
            for task, by_variant in report["episodes"].items():
                for variant, episodes in by_variant.items():
                    if any("offset_at_closest_cm" not in e for e in episodes):
                        raise ValueError(f"{task} {variant}'s episodes keep no offsets (a teacher.py report from before they were kept)")
                    reports.append((str(task), str(variant), [{"offset_at_closest_cm": e["offset_at_closest_cm"],
                                                               "world_model_success": max(e["drawn"]) >= threshold,
                                                               "simulator_first_success": e["first"]} for e in episodes]))
        elif "rates" in report:
            out = []
            for r in report["rates"]:
                rows = r.get("replayed_episodes")
                if rows is None:
                    raise ValueError(f"{r['task']} {r['variant']} has no replayed episodes (a study without its world model's actions)")
                if any(len(row) < 5 for row in rows):
                    raise ValueError(f"{r['task']} {r['variant']}'s replays keep no offsets (study.py --rescore replays them again)")
                out.append((str(r["task"]), str(r["variant"]), [{"offset_at_closest_cm": row[4], "world_model_success": row[1],
                                                                 "simulator_first_success": row[2]} for row in rows]))
            reports = out
        else:
            reports = [(str(report["task"]), str(report["variant"]), report["episodes"])]
        for _, _, episodes in reports:
            for e in episodes:
                if len(e["offset_at_closest_cm"]) < 2:
                    raise ValueError("an offset needs x and y")
                bool(e["world_model_success"]), e["simulator_first_success"]
        return reports
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path} is not a study.py, side_by_side.py or teacher.py report: {e}") from None


def contact_map(reports: list[tuple[str, str, list[dict]]], band_cm: float) -> dict:
    """Per task: the variants counted, and per axis and band {episodes, simulator, world_model}
    (the simulator's and the world model's successes); bands named "LO-HI" in cm."""
    if not band_cm > 0:
        raise ValueError(f"the band width must be positive, got {band_cm}")
    tasks: dict[str, dict] = {}
    rows: dict[str, dict[str, list]] = {}  # per task and axis: (distance, simulator, world model) per episode
    for task, variant, episodes in reports:
        t = tasks.setdefault(task, {"variants": [], "by_axis": {}})
        by_axis = rows.setdefault(task, {a: [] for a in AXES})
        if variant in t["variants"]:
            raise ValueError(f"{task} {variant} is given twice")
        t["variants"].append(variant)
        for e in episodes:
            offset = np.asarray(e["offset_at_closest_cm"][:2], float)
            by_axis[axis(offset)].append((float(np.hypot(*offset)), e["simulator_first_success"] is not None, bool(e["world_model_success"])))
    for task, t in tasks.items():
        for a, placed in rows[task].items():
            distance, simulator, world_model = zip(*placed) if placed else ((), (), ())
            t["by_axis"][a] = bands(distance, band_cm, simulator=simulator, world_model=world_model)
    return tasks


def contact_outside(reports: list[tuple[str, str, list[dict]]], beyond_cm: float) -> dict:
    """Over every episode of `reports`: those whose hand came no closer than `beyond_cm` to the
    object, and how many of them the world model drew succeeding where the simulator did not
    (`invented`); those closer, and how many the simulator succeeded with and the world model did
    not (`missed`)."""
    far = near = invented = missed = 0
    for _, _, episodes in reports:
        for e in episodes:
            simulator, world_model = e["simulator_first_success"] is not None, bool(e["world_model_success"])
            if float(np.hypot(*np.asarray(e["offset_at_closest_cm"][:2], float))) >= beyond_cm:
                far += 1
                invented += world_model and not simulator
            else:
                near += 1
                missed += simulator and not world_model
    return {"beyond_cm": beyond_cm, "beyond": {"episodes": far, "invented": invented}, "within": {"episodes": near, "missed": missed}}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", nargs="+", help="study.json or side_by_side.json files")
    ap.add_argument("--band-cm", type=float, default=2.0, help="width of the distance bands (cm)")
    ap.add_argument("--families", help="only the variants of these policy families, comma-separated (study.py's names: "
                                       "degraded, scripted, partial, learned, wander)")
    ap.add_argument("--beyond-cm", type=float, default=6.0, help="where the summary's far episodes start (cm)")
    ap.add_argument("--json", help="also write the map here")
    a = ap.parse_args(argv)
    families = a.families.split(",") if a.families else None
    try:
        reports = [r for p in a.reports for r in load(p) if families is None or family(r[1]) in families]
        if not reports:
            raise ValueError(f"no variant of the families {a.families} in the reports")
        m = contact_map(reports, a.band_cm)
    except ValueError as e:
        ap.error(str(e))
    outside = contact_outside(reports, a.beyond_cm)
    for task, t in m.items():
        print(f"{task} ({', '.join(t['variants'])}): episodes, simulator successes, world-model successes by where the hand came closest")
        for axis in AXES:
            for band, c in t["by_axis"][axis].items():
                print(f"  {axis:>2} {band:>7} cm: {c['episodes']:4d} episodes, simulator {c['simulator']:4d}, world model {c['world_model']:4d}")
    b, w = outside["beyond"], outside["within"]
    print(f"hand {a.beyond_cm:g} cm or more from the object: {b['invented']} of {b['episodes']} episodes drawn succeeding "
          f"where the simulator does not; closer: {w['missed']} of {w['episodes']} succeeding in the simulator, not drawn")
    if a.json:
        write_json(a.json, {"band_cm": a.band_cm, "families": families, "tasks": m, "outside": outside})


if __name__ == "__main__":
    main()
