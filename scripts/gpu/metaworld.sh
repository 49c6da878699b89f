#!/usr/bin/env bash
# bench/metaworld/recipe.sh on a lent GPU machine (device tool), from the repo root. Carry:
#   .whl          bench/metaworld's wheels for that machine's Python 3.12 (metaworld, mujoco,
#                 gymnasium, farama-notifications, pyopengl, websockets, safetensors; README of the
#                 device tool)
#   .gl           the GL loader debs (libegl1, libglvnd0, libopengl0, ...), for MuJoCo through EGL
#   .carry/bwm.xz the bwm binary built with --no-default-features (xz: the carry limit is 64 MiB)
# Usage: bash scripts/gpu/metaworld.sh [STAGE ...]; logs and timings go to $OUT, the run's small
# outputs to $OUT/run.tar.gz. With no stage, every stage (independent ones side by side); that
# takes longer than one device call, so run it detached:
#   bash scripts/gpu/detached.sh start mw bash scripts/gpu/metaworld.sh; bash scripts/gpu/detached.sh wait mw 570 runs/metaworld/study runs/metaworld/probe
# and the same `wait` in the calls that follow, back to back (a machine idle between calls goes
# back, and one held 30 minutes goes back when the call in flight ends). With the recipe's defaults
# (128x128, a DiT of width 768) data to trained model takes about 17 minutes on an H200, the study
# 5-6 more, the fidelity stage about 20 (beside the studies) and the probe about 4: four calls,
# the last started before minute 30 (run 12 of docs/fidelity.md). SKIP_FIDELITY=1 leaves out
# the fidelity stage (which otherwise runs beside the study and slows it); SKIP_PROBE=1 the probe
# (graded `wrong` variants, after the study). COMPARE_SOLVER=dpm++2m studies the same model a
# second time with that sampler ($RUN/study-dpm++2m); COMPARE_GUIDANCE="2 3" once more per
# action-guidance value ($RUN/study-g2, ...; the model trained with objective.action_dropout > 0);
# COMPARE_JUDGE=reconstructed once more with the judge that also learned from this run's VAE's
# round trips of training frames ($RUN/study-judge-reconstructed, its ceiling in
# $RUN/ceiling/judge-reconstructed.json; JUDGE_FRAMES=reconstructed makes it the study's own).
# `bash scripts/gpu/metaworld.sh transfer` runs bench/metaworld/transfer.sh (the base-versus-scratch
# study of the LoRA issue; its variables apply) instead, its small outputs in $OUT/run.tar.gz;
# `bash scripts/gpu/metaworld.sh sweep` runs bench/metaworld/sweep.sh (the real-time issue's sampler
# sweep; its variables apply) over the run the recipe trained on this machine, training it first
# (stages up to train, truth and judge) where it has not; run it detached as the recipe.
set -uo pipefail
source "$(dirname "$0")/common.sh"
# Under a lock: variants.sh starts several at once, and two pip installs into one target remove
# each other's files (run 23's mw9 failed so).
(
  flock 9
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  if [ ! -d /tmp/site/metaworld ]; then
    rm -rf /tmp/site /tmp/site.part
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site.part .whl/*.whl &&
      mv /tmp/site.part /tmp/site
  fi
) 9> /tmp/metaworld-setup.lock || exit 1
export MUJOCO_GL=egl PYOPENGL_PLATFORM=egl PYTHONUNBUFFERED=1
export PYTHONPATH=/tmp/site
# Unpacked beside and renamed: a second instance started while one runs would otherwise fail
# writing the binary the first is executing ("Text file busy").
mkdir -p dist && xz -dc .carry/bwm.xz > dist/bwm.$$ && chmod +x dist/bwm.$$ && mv -f dist/bwm.$$ dist/bwm || exit 1
export BWM="$PWD/dist/bwm" PYTHON=python3
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
python3 - <<'PY' || exit 1
import importlib
missing = []
for name in ("numpy", "torch", "pyarrow", "PIL", "scipy", "msgpack", "safetensors", "websockets", "metaworld", "mujoco"):
    try:
        m = importlib.import_module(name)
        print(f"{name} {getattr(m, '__version__', '')}")
    except Exception as e:
        missing.append(f"{name} ({e})")
if missing:
    raise SystemExit("missing on this machine: " + ", ".join(missing))
PY
recipe() { bash bench/metaworld/recipe.sh "$@"; }
R=${RUN:-runs/metaworld}
# The stages up to a trained model, the independent ones side by side: truth (MuJoCo, CPU) and
# the judge (a small CNN) beside the VAE, latents and DiT; a judge that learns from the VAE's
# round trips (JUDGE_FRAMES or COMPARE_JUDGE = reconstructed) beside the latents and DiT, once
# the VAE is trained. Stages already done are skipped.
JUDGES="${JUDGE_FRAMES:-real} ${COMPARE_JUDGE:-}"
if [ -n "${COMPARE_JUDGE:-}" ]; then
  case "$COMPARE_JUDGE" in real|reconstructed) ;; *) echo "metaworld: COMPARE_JUDGE must be real or reconstructed" >&2; exit 2 ;; esac
  [ "$COMPARE_JUDGE" != "${JUDGE_FRAMES:-real}" ] || { echo "metaworld: COMPARE_JUDGE=$COMPARE_JUDGE is the study's own judge (JUDGE_FRAMES)" >&2; exit 2; }
fi
judge_log() { if [ "$1" = real ]; then echo "$OUT/judge.log"; else echo "$OUT/judge-$1.log"; fi; }
# The study each judge is for (its judge stage leaves the judge on the simulator's frames there).
study_dir() { if [ "$1" = "${JUDGE_FRAMES:-real}" ]; then echo "${STUDY_DIR:-$R/study}"; else echo "$R/study-judge-$1"; fi; }
train_stages() {
  status=0
  recipe data 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
  if [ $status = 0 ]; then
    recipe truth > "$OUT/truth.log" 2>&1 & truth=$!
    judges=()
    for frames in $JUDGES; do
      [ "$frames" = real ] || continue
      JUDGE_FRAMES=$frames STUDY_DIR=$(study_dir "$frames") recipe judge > "$(judge_log "$frames")" 2>&1 & judges+=($!)
    done
    recipe vae 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
    if [ $status = 0 ]; then
      for frames in $JUDGES; do
        [ "$frames" = real ] && continue
        JUDGE_FRAMES=$frames STUDY_DIR=$(study_dir "$frames") recipe judge > "$(judge_log "$frames")" 2>&1 & judges+=($!)
      done
      recipe latents train 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    wait $truth || { echo "metaworld: truth failed ($OUT/truth.log)"; status=1; }
    for pid in "${judges[@]}"; do wait "$pid" || { echo "metaworld: a judge failed ($OUT/judge*.log)"; status=1; }; done
  fi
}
if [ "${1:-}" = transfer ]; then
  R=${RUN:-runs/transfer}
  bash bench/metaworld/transfer.sh 2>&1 | tee -a "$OUT/transfer.log"
  status=${PIPESTATUS[0]}
elif [ "${1:-}" = sweep ]; then
  # On a bare machine the model is trained first (the datasets and weights do not outlive it).
  train_stages
  if [ $status = 0 ]; then
    bash bench/metaworld/sweep.sh 2>&1 | tee -a "$OUT/sweep.log"
    status=${PIPESTATUS[0]}
  fi
elif [ $# -gt 0 ]; then
  recipe "$@" 2>&1 | tee -a "$OUT/recipe.log"
  status=${PIPESTATUS[0]}
else
  # Every stage: fidelity and the judge's ceiling beside the study.
  train_stages
  if [ $status = 0 ]; then
    fidelity=
    [ "${SKIP_FIDELITY:-0}" = 1 ] || { recipe fidelity > "$OUT/fidelity.log" 2>&1 & fidelity=$!; }
    recipe ceiling > "$OUT/ceiling.log" 2>&1 & ceiling=$!
    recipe study 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
    if [ $status = 0 ] && [ -n "${COMPARE_JUDGE:-}" ]; then
      # The same world model judged by the other judge; its ceiling after the first (both write
      # the held-out round trip).
      wait $ceiling || { echo "metaworld: ceiling failed ($OUT/ceiling.log)"; status=1; }
      JUDGE_FRAMES=$COMPARE_JUDGE recipe ceiling > "$OUT/ceiling-$COMPARE_JUDGE.log" 2>&1 & ceiling=$!
      JUDGE_FRAMES=$COMPARE_JUDGE STUDY_DIR=$(study_dir "$COMPARE_JUDGE") recipe study 2>&1 | tee -a "$OUT/recipe.log"
      [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    if [ $status = 0 ] && [ -n "${COMPARE_SOLVER:-}" ]; then
      SOLVER=$COMPARE_SOLVER STUDY_DIR=$R/study-$COMPARE_SOLVER recipe study 2>&1 | tee -a "$OUT/recipe.log"
      [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    for w in ${COMPARE_GUIDANCE:-}; do
      [ $status = 0 ] || break
      GUIDANCE=$w STUDY_DIR=$R/study-g$w recipe study 2>&1 | tee -a "$OUT/recipe.log"
      [ "${PIPESTATUS[0]}" = 0 ] || status=1
    done
    if [ $status = 0 ] && [ "${SKIP_PROBE:-0}" != 1 ]; then
      recipe probe 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    [ -z "$fidelity" ] || wait $fidelity || { echo "metaworld: fidelity failed ($OUT/fidelity.log)"; status=1; }
    wait $ceiling || { echo "metaworld: ceiling failed ($OUT/ceiling*.log)"; status=1; }
  fi
fi
# What the run measured comes back as one archive (small files only; the datasets, latents,
# weights and videos stay on the machine).
(cd $R && find . -maxdepth 3 -type f \( -name '*.json' -o -name '*.jsonl' -o -name '*.csv' -o -name '*.svg' -o -name '*.log' \
  -o -name '*.toml' -o -name '*.png' -o -name '*.tsv' \) -not -path '*/videos/*' -not -path './data/*' -not -path './latents/*' -size -3M -print0 |
  tar -czf "$OUT/run.tar.gz" --null -T -)
exit "$status"
