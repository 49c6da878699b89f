#!/usr/bin/env bash
# The Meta-World recipe's stages in the order scripts/gpu/metaworld.sh runs them, once that has set
# the GPU host up (its header says which stages and variables; it execs this). Apart so that the
# CPU tests run the orchestration over a stub recipe (tests/gpu_scripts.rs). Needs $BWM and $PYTHON
# as recipe.sh does; logs go to $OUT.
set -uo pipefail
OUT="${OUT:-/tmp/out}"; mkdir -p "$OUT"
recipe() { bash bench/metaworld/recipe.sh "$@"; }
R=${RUN:-runs/metaworld}
# The stages up to a trained model, the independent ones side by side: truth (MuJoCo, CPU) and
# a judge of real frames alone (JUDGE_FRAMES or COMPARE_JUDGE = real) beside the VAE, latents and
# DiT; the judge that also learns from the VAE's round trips (recipe.sh's default) beside the
# latents and DiT, once the VAE is trained. Stages already done are skipped.
# Taken once here (recipe.sh's default): a command's own `JUDGE_FRAMES=... STUDY_DIR=$(study_dir
# ...)` prefix is in effect while its later assignments expand (run 26's second judge and study
# went to the first's folder).
OWN_JUDGE=${JUDGE_FRAMES:-reconstructed}
OWN_STUDY=${STUDY_DIR:-$R/study}
JUDGES="$OWN_JUDGE ${COMPARE_JUDGE:-}"
if [ -n "${COMPARE_JUDGE:-}" ]; then
  case "$COMPARE_JUDGE" in real|reconstructed) ;; *) echo "metaworld: COMPARE_JUDGE must be real or reconstructed" >&2; exit 2 ;; esac
  [ "$COMPARE_JUDGE" != "$OWN_JUDGE" ] || { echo "metaworld: COMPARE_JUDGE=$COMPARE_JUDGE is the study's own judge (JUDGE_FRAMES)" >&2; exit 2; }
fi
if [ "${COMPARE_EMA:-0}" = 1 ] && [ -z "${EMA_DECAY:-}" ]; then
  echo "metaworld: COMPARE_EMA=1 compares the average of weights with the last step's; set EMA_DECAY" >&2; exit 2
fi
if [ -n "${OTHER_SEEDS:-}" ]; then
  (VAL_SEED_START=$OTHER_SEEDS; source bench/metaworld/data-settings.sh) || { echo "metaworld: OTHER_SEEDS=$OTHER_SEEDS (above)" >&2; exit 2; }
fi
judge_log() { if [ "$1" = real ]; then echo "$OUT/judge.log"; else echo "$OUT/judge-$1.log"; fi; }
# The study each judge is for (its judge stage leaves the judge on the simulator's frames there).
study_dir() { if [ "$1" = "$OWN_JUDGE" ]; then echo "$OWN_STUDY"; else echo "$R/study-judge-$1"; fi; }
# A study of the same model and episodes under other sampler settings starts from the study's
# truth and its judge's verdicts on the simulator's frames (recipe.sh's STUDY_FROM).
# The study once more per value of a recipe variable ($1; the rest: its values), each in
# $R/study-$2VALUE, while the stages before it succeeded.
compare_per_value() {
  local var=$1 tag=$2 value; shift 2
  for value in "$@"; do
    [ $status = 0 ] || break
    (export "$var=$value" STUDY_DIR="$R/study-$tag$value" STUDY_FROM="$OWN_STUDY"; recipe study) 2>&1 | tee -a "$OUT/recipe.log"
    [ "${PIPESTATUS[0]}" = 0 ] || status=1
  done
}
train_stages() { # $1 = light: the realtime stage's light decoder trains beside the world model (it needs the VAE alone)
  status=0
  recipe data 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
  if [ $status = 0 ]; then
    recipe truth > "$OUT/truth.log" 2>&1 & truth=$!
    beside=()  # the judges (and the light decoder) training beside the world model
    for frames in $JUDGES; do
      [ "$frames" = real ] || continue
      JUDGE_FRAMES=$frames STUDY_DIR=$(study_dir "$frames") recipe judge > "$(judge_log "$frames")" 2>&1 & beside+=($!)
    done
    recipe vae 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
    if [ $status = 0 ]; then
      for frames in $JUDGES; do
        [ "$frames" = real ] && continue
        JUDGE_FRAMES=$frames STUDY_DIR=$(study_dir "$frames") recipe judge > "$(judge_log "$frames")" 2>&1 & beside+=($!)
      done
      [ "${1:-}" = light ] && { recipe light > "$OUT/light.log" 2>&1 & beside+=($!); }
      recipe latents train 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    wait $truth || { echo "metaworld: truth failed ($OUT/truth.log)"; status=1; }
    for pid in "${beside[@]}"; do wait "$pid" || { echo "metaworld: a judge or the light decoder failed ($OUT/judge*.log, $OUT/light.log)"; status=1; }; done
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
elif [ "${1:-}" = engine ] || [ "${1:-}" = realtime ]; then
  # The data engine or cheaper sampling measured (recipe.sh's engine or realtime stage) on a model
  # trained here first; for the realtime stage its light decoder trains beside the world model.
  if [ "$1" = realtime ]; then train_stages light; else train_stages; fi
  if [ $status = 0 ]; then
    recipe "$1" 2>&1 | tee -a "$OUT/recipe.log"
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
      # The same world model judged by the other judge; its ceiling after the first (whose
      # round trip of the held-out frames it reuses).
      wait $ceiling || { echo "metaworld: ceiling failed ($OUT/ceiling.log)"; status=1; }
      JUDGE_FRAMES=$COMPARE_JUDGE recipe ceiling > "$OUT/ceiling-$COMPARE_JUDGE.log" 2>&1 & ceiling=$!
      JUDGE_FRAMES=$COMPARE_JUDGE STUDY_DIR=$(study_dir "$COMPARE_JUDGE") recipe study 2>&1 | tee -a "$OUT/recipe.log"
      [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    if [ $status = 0 ] && [ -n "${COMPARE_STREAMS:-}" ]; then
      # The same study with the episodes in flight in lanes on CUDA streams of their own (the same
      # estimates; what changes is the time).
      STUDY_STREAMS=$COMPARE_STREAMS STUDY_DIR=$R/study-streams$COMPARE_STREAMS STUDY_FROM=$OWN_STUDY recipe study 2>&1 | tee -a "$OUT/recipe.log"
      [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    if [ $status = 0 ] && [ -n "${COMPARE_SOLVER:-}" ]; then
      SOLVER=$COMPARE_SOLVER STUDY_DIR=$R/study-$COMPARE_SOLVER STUDY_FROM=$OWN_STUDY recipe study 2>&1 | tee -a "$OUT/recipe.log"
      [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    if [ $status = 0 ] && [ "${COMPARE_EMA:-0}" = 1 ]; then
      # The same training's last step's weights, beside the average the study rolled out.
      EMA_DECAY= STUDY_DIR=$R/study-last STUDY_FROM=$OWN_STUDY recipe study 2>&1 | tee -a "$OUT/recipe.log"
      [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    compare_per_value GUIDANCE g ${COMPARE_GUIDANCE:-}
    compare_per_value HISTORY_SIGMA h ${COMPARE_HISTORY_SIGMA:-}
    compare_per_value SAMPLE_SEED seed ${COMPARE_SAMPLE_SEED:-}
    if [ $status = 0 ] && [ "${TEACHER:-0}" = 1 ]; then
      recipe teacher 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    if [ $status = 0 ] && [ "${OWN:-0}" = 1 ]; then
      recipe own 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    if [ $status = 0 ] && [ "${SKIP_PROBE:-0}" != 1 ]; then
      recipe probe 2>&1 | tee -a "$OUT/recipe.log"; [ "${PIPESTATUS[0]}" = 0 ] || status=1
    fi
    if [ $status = 0 ] && [ -n "${OTHER_SEEDS:-}" ]; then
      # The same world model on held-out seeds from OTHER_SEEDS, in a folder inside the run's (so
      # that its study comes back in run.tar.gz).
      STUDY_DIR= FIDELITY_DIR= VAL_SEED_START=$OTHER_SEEDS RUN=$R/seeds-$OTHER_SEEDS \
        bash bench/metaworld/other-seeds.sh "$R" data truth study 2>&1 | tee -a "$OUT/recipe.log"
      [ "${PIPESTATUS[0]}" = 0 ] || status=1
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
