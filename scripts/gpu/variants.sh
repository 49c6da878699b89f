#!/usr/bin/env bash
# Variants of the Meta-World recipe side by side on one lent machine (device tool), from the repo
# root, with the carry of scripts/gpu/metaworld.sh:
#   bash scripts/gpu/variants.sh NAME "VAR=VALUE ..." [NAME "VAR=VALUE ..." ...]
# The data and the judge are made once (runs/metaworld); each variant then runs
# scripts/gpu/metaworld.sh in runs/NAME (its data and judge.pt linked to those) with its variables,
# on GPU i mod the machine's GPU count for the i-th variant, all at once. STAGES (default: every
# stage) picks stages, e.g. STAGES="vae ceiling" compares VAEs alone. Each variant's log and
# outputs go to $OUT/NAME (its run.tar.gz holds the run's small files). Longer than one call:
#   bash scripts/gpu/detached.sh start v bash scripts/gpu/variants.sh s8 "VAE_STRIDE=8" ...
#   bash scripts/gpu/detached.sh wait v 570 runs/s8/study ...   (back to back)
# Exits 1 when any variant failed.
set -uo pipefail -f  # -f: a variant's TRAIN_SETS holds brackets, not globs
[ $# -ge 2 ] && [ $(($# % 2)) = 0 ] || { echo 'usage: variants.sh NAME "VAR=VALUE ..." [NAME "VAR=VALUE ..." ...]' >&2; exit 2; }
cd "$(dirname "$0")/../.."
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
bash scripts/gpu/metaworld.sh data judge > "$OUT/shared.log" 2>&1 || { echo "variants: data or judge failed ($OUT/shared.log)"; exit 1; }
gpus=$(nvidia-smi -L | wc -l)
i=0 pids=() names=()
while [ $# -gt 0 ]; do
  name=$1 vars=$2; shift 2
  case "$name" in metaworld|*/*|"") echo "variants: '$name' cannot name a run folder" >&2; exit 2 ;; esac
  mkdir -p "runs/$name" "$OUT/$name"
  ln -sfn "$PWD/runs/metaworld/data" "runs/$name/data"
  ln -sfn "$PWD/runs/metaworld/judge.pt" "runs/$name/judge.pt"
  echo "variants: $name on GPU $((i % gpus)): $vars"
  # shellcheck disable=SC2086  # the variables are words by design
  env CUDA_VISIBLE_DEVICES=$((i % gpus)) RUN="runs/$name" OUT="$OUT/$name" $vars \
    bash scripts/gpu/metaworld.sh ${STAGES:-} > "$OUT/$name/log" 2>&1 &
  pids+=($!) names+=("$name") i=$((i + 1))
done
status=0
for k in "${!pids[@]}"; do
  if wait "${pids[$k]}"; then echo "variants: ${names[$k]} done"; else echo "variants: ${names[$k]} failed ($OUT/${names[$k]}/log)"; status=1; fi
done
exit $status
