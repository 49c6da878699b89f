#!/usr/bin/env bash
# How Meta-World-sized trainings on one host slow each other through libtorch's CPU thread pool
# (from the repo root, with .pack copied to the host): the recipe's DiT step (`bwm bench-train`,
# configs/metaworld.toml at 128x128, 24 future frames) alone on GPU 0 and then one per GPU at
# once, each with `--cpu-threads N` for every N given (default: nproc, i.e. libtorch's own one per
# core, 16 and 1). Usage: bash scripts/gpu/host_contention.sh [STEPS [N ...]] (default 150 steps).
# Logs in $OUT/NAME-gGPU.log; the summary (median s/step over each process's second half of
# steps) on stdout.
set -uo pipefail
source "$(dirname "$0")/common.sh"
steps=${1:-150}; shift || true
threads=("$@"); [ ${#threads[@]} -gt 0 ] || threads=("$(nproc)" 16 1)
unpack .pack/bwm.xz dist/bwm || exit 1
gpus=$(nvidia-smi -L | wc -l)
bench() { # $1 = name, $2 = GPU, $3 = CPU threads
  CUDA_VISIBLE_DEVICES=$2 dist/bwm --cpu-threads "$3" bench-train --config configs/metaworld.toml \
    --height 128 --width 128 --future 24 --steps "$steps" --out "/tmp/bt/$1-g$2" > "$OUT/$1-g$2.log" 2>&1
}
summary() { # median s/step over the second half of each log's steps
  for f in "$OUT/$1"-g*.log; do
    read -r med half n < <(second_half_median s/step "$f")
    echo "$(basename "$f" .log): median $med s/step over the last $half of $n steps"
  done
}
for t in "${threads[@]}"; do bench "alone-t$t" 0 "$t"; summary "alone-t$t"; done
for t in "${threads[@]}"; do
  for ((g = 0; g < gpus; g++)); do bench "all-t$t" $g "$t" & done; wait
  summary "all-t$t"
done
