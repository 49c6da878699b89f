"""The data engine, measured: does a behaviour-cloned policy improve when the world model's
generated demonstrations are added to its real ones? (recipe.sh's `engine` stage runs the three
steps in order; docs/fidelity.md, "The data engine", has the table.)

1. `plan`: new placements (seeds GENERATED_SEED_START + 1000 s + j for data seed s, j < M, never
   used by training, evaluation or any policy family): per placement the simulator's first frame
   x0 (the only real frame a generated episode gets), and the expert's commands planned from it
   open loop (policies.Policy "expert", which perceives the object in x0 by colour, then
   integrates its own commands): FRAMES commands, and the commanded states they drive as the
   actions CSV `bwm rollout --inputs` reads (row t: the state shown with frame t, row 0 x0's).
   Each plan's commands are also replayed in the simulator: the true outcome of the generated
   demonstration's actions (plan.json).
2. `bwm rollout --inputs PLAN/inputs.jsonl --drive file --out PLAN/generated` (the recipe's world
   model) draws each planned episode from its x0.
3. `measure`: per task, data seed s in 0..SEEDS-1 and real demonstration count N, a policy cloned
   (families.train_net, the `learned` family's network, seeded by s) from
   - `real`: N real demonstrations: the expert's episodes in the simulator on placements
     REAL_SEED_START + 1000 s + k, k < N;
   - `real+judged`: those and the generated episodes of seed s that the recipe's judge
     (judge.py, on the generated frames, the episode's end final) calls successes;
   - `real+generated`: those and every generated episode of seed s;
   - `real+real` (what generated data could reach at best): those and M more real
     demonstrations, on placements of their own (REAL_SEED_START + 1000 s + max(N) + j, j < M);
   each run in the simulator on the same EPISODES placements (EVAL_SEED_START + i) with the
   `learned` family's loop (policies.run: a frame every 24 steps, 120 steps, frames at the
   data's resolution), its success rate the share of them that succeed. Writes engine.json: every
   rate, their means and spreads over the data seeds, the judge's verdicts against the replayed
   truth, and the commands that made them.

    python engine.py plan --out DIR [--tasks T,..] [--seeds 3] [--generated 16] [--frames 120] [--resolution 128]
    python engine.py measure --plan DIR --generated DIR/generated --judge JUDGE.pt --out engine.json \\
        [--demos 2,4,8] [--episodes 100] [--net-steps 2000] [--workers N] [--device auto]
"""

from __future__ import annotations

import argparse
import io
import json
import multiprocessing
import os
import sys
import time

import numpy as np

import families
import policies
from files import write_json, write_text
from mw import TASKS, next_state

REAL_SEED_START = 700000
GENERATED_SEED_START = 710000
EVAL_SEED_START = 720000
SEED_STRIDE = 1000  # data seed s takes placements START + 1000 s + j
ARMS = ("real", "real+judged", "real+generated", "real+real")


def real_seed(s: int, k: int) -> int:
    return REAL_SEED_START + SEED_STRIDE * s + k


def generated_seed(s: int, j: int) -> int:
    return GENERATED_SEED_START + SEED_STRIDE * s + j


# -- plan --------------------------------------------------------------------------------------


def plan_episode(task: str, seed: int, frames: int, resolution: int) -> dict:
    """x0 (uint8 [H, W, 3]), the expert's `frames` commands planned from it, the commanded states
    before each (rows for the world model), and whether the commands succeed in the simulator."""
    from mw import Sim

    with Sim(task, seed, resolution) as sim:
        x0, state = sim.reset()
    commands = policies.Policy(task, "expert", seed).act(x0, state, frames)
    states = [np.asarray(state, np.float32)]
    for c in commands[:-1]:
        states.append(next_state(states[-1], c))
    outcome = policies.replay(task, seed, commands, resolution)
    return {"x0": np.asarray(x0), "commands": commands, "states": np.stack(states), "success_step": outcome.first}


def _plan_job(job):
    return job, plan_episode(*job)


def plan(a) -> None:
    from PIL import Image

    tasks = a.tasks.split(",")
    for t in tasks:
        if t not in TASKS:
            raise SystemExit(f"engine: unknown task {t!r} (known: {', '.join(TASKS)})")
    if a.seeds < 1 or a.generated < 1 or a.frames < 2:
        raise SystemExit("engine: --seeds and --generated must be at least 1, --frames at least 2")
    os.makedirs(os.path.join(a.out, "x0"), exist_ok=True)
    os.makedirs(os.path.join(a.out, "actions"), exist_ok=True)
    jobs = [(t, generated_seed(s, j), a.frames, a.resolution) for s in range(a.seeds) for t in tasks for j in range(a.generated)]
    lines, episodes = [], []
    with multiprocessing.get_context("spawn").Pool(max(1, min(a.workers, len(jobs)))) as pool:
        for (task, seed, _, _), p in pool.imap(_plan_job, jobs):
            name = f"{task}-{seed}"
            Image.fromarray(p["x0"]).save(os.path.join(a.out, "x0", f"{name}.png"))
            with open(os.path.join(a.out, "actions", f"{name}.csv"), "w") as f:
                f.write("x,y,z,gripper\n")
                f.writelines(",".join(f"{v:.7g}" for v in row) + "\n" for row in p["states"])
            lines.append(json.dumps({"x0": f"x0/{name}.png", "actions": f"actions/{name}.csv", "task": task}))
            episodes.append({"task": task, "seed": seed, "data_seed": (seed - GENERATED_SEED_START) // SEED_STRIDE,
                             "commands": p["commands"].round(7).tolist(), "replayed_success_step": p["success_step"]})
    write_text(os.path.join(a.out, "inputs.jsonl"), "".join(line + "\n" for line in lines))
    record = {"tasks": tasks, "seeds": a.seeds, "generated": a.generated, "frames": a.frames, "resolution": a.resolution,
              "episodes": episodes}
    write_json(os.path.join(a.out, "plan.json"), record, indent=None)
    ok = sum(e["replayed_success_step"] is not None for e in episodes)
    print(f"engine: planned {len(episodes)} episodes in {a.out} (inputs.jsonl); their commands succeed in the simulator in {ok}")


# -- measure -----------------------------------------------------------------------------------


def read_generated(root: str) -> list[np.ndarray]:
    """The frames (uint8 [T, H, W, 3]) of every episode of a dataset `bwm rollout` wrote with PNG
    cells (--frame-storage image), in episode order."""
    import pyarrow.parquet as pq
    from PIL import Image

    info = json.load(open(os.path.join(root, "meta", "info.json")))
    keys = [k for k, f in info["features"].items() if f.get("dtype") == "image"]
    if len(keys) != 1:
        raise SystemExit(f"engine: {root} has no single image feature (write it with bwm rollout --frame-storage image)")
    out = []
    for e in range(info["total_episodes"]):
        path = os.path.join(root, info["data_path"].format(episode_chunk=e // info["chunks_size"], episode_index=e))
        cells = pq.read_table(path, columns=[keys[0]]).column(0).to_pylist()
        out.append(np.stack([np.asarray(Image.open(io.BytesIO(c["bytes"])).convert("RGB")) for c in cells]))
    return out


def _real_demo(job) -> None:
    families.demo(*job)


def _arm_job(job) -> dict:
    """One cloned policy: trained on the job's demonstrations, run on the evaluation placements."""
    task, n, arm, s, demos, episodes, resolution, steps = job
    x = np.concatenate([d["x"][: len(d["y"])] for d in demos])
    y = np.concatenate([d["y"] for d in demos]).reshape(len(x), -1)
    t0 = time.time()
    arrays = families.train_net(x, y, steps, seed=s)
    firsts = []
    for i in range(episodes):
        seed = EVAL_SEED_START + i
        e = policies.run(families.Cloned(task, arrays, seed), task, seed, families.HORIZON, families.CHUNK, resolution)
        firsts.append(e.first)
    rate = float(np.mean([f is not None for f in firsts]))
    return {"task": task, "real_demos": n, "arm": arm, "data_seed": s, "demonstrations": len(demos), "samples": len(x),
            "success_rate": rate, "episodes": episodes, "seconds": round(time.time() - t0, 1)}


def measure(a) -> None:
    record = json.load(open(os.path.join(a.plan, "plan.json")))
    tasks, seeds, resolution = record["tasks"], record["seeds"], record["resolution"]
    demos_n = [int(v) for v in a.demos.split(",")]
    generated = read_generated(a.generated)
    planned = record["episodes"]
    if len(generated) != len(planned):
        raise SystemExit(f"engine: {a.generated} holds {len(generated)} episodes, the plan {len(planned)} (was the rollout cut short?)")

    # The judge on each generated episode (its last frame ends the episode).
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import judge as judge_module

    judge = judge_module.Judge(a.judge, judge_module.pick_device(a.device), None)
    per_seed = {(t, s): {"judged": [], "all": []} for t in tasks for s in range(seeds)}
    verdicts = []
    for p, frames in zip(planned, generated):
        verdict = judge.judge({"frames": frames, "task": p["task"], "final": True})
        called = verdict["success_probability"] >= 0.5
        d = families.demo_arrays(p["task"], frames, np.asarray(p["commands"], np.float32)[: len(frames)])
        per_seed[(p["task"], p["data_seed"])]["all"].append(d)
        if called:
            per_seed[(p["task"], p["data_seed"])]["judged"].append(d)
        verdicts.append({"task": p["task"], "seed": p["seed"], "judged_success": called,
                         "success_probability": round(verdict["success_probability"], 4),
                         "replayed_success": p["replayed_success_step"] is not None})
    m = record["generated"]
    most = max(demos_n) + m
    with multiprocessing.get_context("spawn").Pool(max(1, a.workers)) as pool:
        # The real demonstrations recorded once (cached), before the policies that share them.
        pool.map(_real_demo, [(t, real_seed(s, k), resolution) for t in tasks for s in range(seeds) for k in range(most)])
        jobs = []
        for t in tasks:
            for s in range(seeds):
                for n in demos_n:
                    real = [families.demo(t, real_seed(s, k), resolution) for k in range(n)]
                    more = [families.demo(t, real_seed(s, max(demos_n) + j), resolution) for j in range(m)]
                    arms = {"real": real, "real+judged": real + per_seed[(t, s)]["judged"],
                            "real+generated": real + per_seed[(t, s)]["all"], "real+real": real + more}
                    jobs += [(t, n, arm, s, arms[arm], a.episodes, resolution, a.net_steps) for arm in ARMS]
        t0 = time.time()
        rows = []
        for r in pool.imap_unordered(_arm_job, jobs):
            rows.append(r)
            print(f"engine: {r['task']} N={r['real_demos']} {r['arm']} seed {r['data_seed']}: {r['success_rate']:.2f} "
                  f"({r['demonstrations']} demos; {len(rows)}/{len(jobs)}, {time.time() - t0:.0f} s)", flush=True)
    rows.sort(key=lambda r: (tasks.index(r["task"]), r["real_demos"], ARMS.index(r["arm"]), r["data_seed"]))
    summary = []
    for t in tasks:
        for n in demos_n:
            for arm in ARMS:
                rates = [r["success_rate"] for r in rows if (r["task"], r["real_demos"], r["arm"]) == (t, n, arm)]
                demos = [r["demonstrations"] for r in rows if (r["task"], r["real_demos"], r["arm"]) == (t, n, arm)]
                summary.append({"task": t, "real_demos": n, "arm": arm, "mean": float(np.mean(rates)), "std": float(np.std(rates)),
                                "rates": rates, "demonstrations": demos})
    judged = {}
    for t in tasks:
        v = [x for x in verdicts if x["task"] == t]
        judged[t] = {"generated": len(v), "judged_success": sum(x["judged_success"] for x in v),
                     "replayed_success": sum(x["replayed_success"] for x in v),
                     "judge_agrees": sum(x["judged_success"] == x["replayed_success"] for x in v)}
    report = {"plan": a.plan, "generated": a.generated, "judge": a.judge, "demos": demos_n, "generated_per_seed": m, "seeds": seeds,
              "eval_episodes": a.episodes, "eval_seeds": [EVAL_SEED_START, EVAL_SEED_START + a.episodes - 1],
              "resolution": resolution, "net_steps": a.net_steps, "arms": list(ARMS), "summary": summary,
              "judged": judged, "verdicts": verdicts, "rows": rows, "command": " ".join(sys.argv)}
    write_json(a.out, report)
    print(table(report))


def table(report: dict) -> str:
    """The success rates as a markdown table: a row per task and N, a column per arm (mean and
    spread over the data seeds)."""
    arms = report["arms"]
    lines = ["| task | N real | " + " | ".join(arms) + " |", "|---" * (len(arms) + 2) + "|"]
    for t in dict.fromkeys(r["task"] for r in report["summary"]):
        for n in report["demos"]:
            cells = []
            for arm in arms:
                r = next(x for x in report["summary"] if (x["task"], x["real_demos"], x["arm"]) == (t, n, arm))
                cells.append(f"{r['mean']:.2f} ± {r['std']:.2f} ({'/'.join(map(str, r['demonstrations']))})")
            lines.append(f"| {t} | {n} | " + " | ".join(cells) + " |")
    for t, j in report["judged"].items():
        lines.append(f"\n{t}: {j['generated']} generated, the judge calls {j['judged_success']} successes; "
                     f"their commands succeed in the simulator in {j['replayed_success']}; the judge agrees with that on {j['judge_agrees']}")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("plan", help="new placements' x0 and the expert's commands planned from it, for bwm rollout --inputs")
    p.add_argument("--out", required=True)
    p.add_argument("--tasks", default=",".join(TASKS))
    p.add_argument("--seeds", type=int, default=3, help="data seeds (each its own placements)")
    p.add_argument("--generated", type=int, default=16, help="generated episodes per task and data seed (M)")
    p.add_argument("--frames", type=int, default=families.HORIZON, help="frames per generated episode, x0 included")
    p.add_argument("--resolution", type=int, default=families.DEMO_RESOLUTION)
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    m = sub.add_parser("measure", help="clone policies with and without the generated episodes and run them in the simulator")
    m.add_argument("--plan", required=True, help="the plan's folder")
    m.add_argument("--generated", required=True, help="bwm rollout's output for the plan's inputs.jsonl (--frame-storage image)")
    m.add_argument("--judge", required=True, help="judge.py's model")
    m.add_argument("--out", required=True, help="engine.json")
    m.add_argument("--demos", default="2,4,8", help="real demonstration counts N")
    m.add_argument("--episodes", type=int, default=100, help="evaluation episodes per policy")
    m.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    m.add_argument("--net-steps", type=int, default=families.NET_STEPS, help="the cloned network's Adam steps")
    m.add_argument("--device", default="auto", help="the judge's: auto, cpu or cuda")
    a = ap.parse_args(argv)
    plan(a) if a.command == "plan" else measure(a)


if __name__ == "__main__":
    main()
