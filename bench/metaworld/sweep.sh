#!/usr/bin/env bash
# The sampler sweep of the real-time issue on a trained recipe run ($RUN, default runs/metaworld):
# for each solver in SOLVERS and step count in STEPS, `bwm fidelity` on the first
# SWEEP_EPISODES held-out episodes of each task and the closed-loop study (recipe.sh's fidelity
# and study stages with SOLVER / SAMPLE_STEPS), into $RUN/sweep/SOLVER-STEPS/{fidelity,study};
# then sweep.py: a table and the default setting, the fewest steps whose PSNR at h = 32 stays
# within 0.5 dB (every task) and whose success estimates stay within 2 points of 50 Euler steps.
# EXTRA_SETTINGS names more, e.g. "dpm++2m-8-fp8row" (the DiT's linears in FP8 with row scaling)
# or "euler-4-streams2" (the episodes in flight of `bwm fidelity` and of each `bwm evaluate` in 2
# lanes on CUDA streams of their own: the same sampler, timed), measured after the rest. Each
# setting's stages are timed (by the recipe) into its folder's timings.tsv (the table's last column). Settings
# already measured on the same weights (their sha256 in the setting's folder, `model`) are skipped, so the sweep can run over several commands or sessions. SETTINGS (e.g. "euler-8 euler-12") measures those settings alone and
# leaves the table out: a share of the sweep for one GPU of several, e.g.
#   CUDA_VISIBLE_DEVICES=1 SETTINGS="euler-8 euler-12" bash bench/metaworld/sweep.sh &
# with the baseline among the shares; a last plain `bash bench/metaworld/sweep.sh` (STEPS and
# SOLVERS naming what was measured) then skips them all and writes the table.
# Usage (repository root, after recipe.sh's stages up to judge): bash bench/metaworld/sweep.sh;
# the recipe's variables apply (STUDY_EPISODES, STUDY_VARIANTS, DEVICE, BWM, PYTHON, ...).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
RUN="${RUN:-runs/metaworld}"
SOLVERS="${SOLVERS:-euler dpm++2m}"
STEPS="${STEPS:-4 8 12 16 20 30 50}"
SWEEP_EPISODES="${SWEEP_EPISODES:-20}"
PYTHON="${PYTHON:-python3}"
# data/val interleaves the tasks (episode e is task e mod T): the first T x N positions cover N
# episodes of each task; FIDELITY_EPISODES names other positions.
n_tasks=$("$PYTHON" -c 'import json, sys; print(json.load(open(sys.argv[1]))["total_tasks"])' "$RUN/data/val/meta/info.json")
episodes="${FIDELITY_EPISODES:-$(seq -s, 0 $((n_tasks * SWEEP_EPISODES - 1)))}"
baseline="${SWEEP_BASELINE:-euler-50}"
mkdir -p "$RUN/sweep"
# The weights measured: a setting measured on other weights (a model trained again into $RUN) is
# measured again.
model="$(cat "$RUN/checkpoints/latest") $(sha256sum < "$RUN/checkpoints/$(cat "$RUN/checkpoints/latest")/model.safetensors" | cut -c1-64)"
# The baseline first (every other setting is judged against it), then by step count, each
# solver in turn: a sweep cut short by the device's time still yields comparisons.
settings=("$baseline")
for steps in $STEPS; do
  for solver in $SOLVERS; do
    [ "$solver-$steps" = "$baseline" ] || settings+=("$solver-$steps")
  done
done
settings+=(${EXTRA_SETTINGS:-})
[ -z "${SETTINGS:-}" ] || settings=($SETTINGS)
for setting in "${settings[@]}"; do
  base=$setting streams=1 fp8=
  case "$base" in *-streams*) streams=${base##*-streams} base=${base%-streams*} ;; esac
  case "$base" in *-fp8*) fp8=${base##*-fp8} base=${base%-fp8*} ;; esac
  solver=${base%-*} steps=${base##*-}
  dir="$RUN/sweep/$setting"
  if [ -f "$dir/fidelity/fidelity.json" ] && [ -f "$dir/study/study.json" ] && [ "$(cat "$dir/model" 2>/dev/null)" = "$model" ]; then
    echo "sweep: $setting measured"; continue
  fi
  rm -f "$dir/model"
  echo "sweep: $solver, $steps steps${fp8:+, FP8 ($fp8 scaling)}$([ "$streams" = 1 ] || echo ", $streams streams") ($(date +%H:%M:%S))"
  # The simulator's outcomes and the judge's verdicts on its frames do not depend on the sampler:
  # the baseline's are reused (study.py keys them by seeds, variants, the policies' code and judge, and measures
  # afresh where the key differs).
  mkdir -p "$dir/study"
  for f in truth.json judged.json; do
    if [ ! -f "$dir/study/$f" ] && [ -f "$RUN/sweep/$baseline/study/$f" ]; then cp "$RUN/sweep/$baseline/study/$f" "$dir/study/$f"; fi
  done
  RUN="$RUN" SOLVER="$solver" SAMPLE_STEPS="$steps" FP8="$fp8" FIDELITY_DIR="$dir/fidelity" FIDELITY_EPISODES="$episodes" \
    FIDELITY_STREAMS="$streams" STUDY_STREAMS="$streams" STUDY_DIR="$dir/study" TIMINGS="$dir/timings.tsv" \
    bash bench/metaworld/recipe.sh fidelity study
  echo "$model" > "$dir/model"
done
[ -n "${SETTINGS:-}" ] && { echo "sweep: $SETTINGS measured; the table comes from a plain sweep.sh"; exit 0; }
"$PYTHON" bench/metaworld/sweep.py "$RUN/sweep" --baseline "$baseline"
# The pick travels with the weights it was measured on: `bwm sampler` records it beside the newest
# checkpoint (its input contract, contract.json), so that every world-model command on it (and `bwm export`'s copy)
# samples at this setting unless told otherwise.
BWM="${BWM:-${CARGO_TARGET_DIR:-target}/release/bwm}"
read -r pick_solver pick_steps < <("$PYTHON" -c '
import json, sys
r = json.load(open(sys.argv[1]))
row = next(s for s in r["settings"] if s["setting"] == r["default"])
print(row["solver"], row["steps"])' "$RUN/sweep/sweep.json")
"$BWM" sampler --checkpoint "$RUN/checkpoints/$(cat "$RUN/checkpoints/latest")" --steps "$pick_steps" --solver "$pick_solver" \
  --measured "bench/metaworld/sweep.sh: the fewest steps within 0.5 dB of $baseline at h = 32 (every task) and its success estimates within 2 points ($RUN/sweep/sweep.json)"
