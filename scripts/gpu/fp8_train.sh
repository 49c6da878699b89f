#!/usr/bin/env bash
# On one GPU of a CUDA host, from the repo root, with the bwm binary copied there as
# scripts/gpu/pack.sh packs it (.pack/bwm.xz). Times the 5B training step (random init, 640x480,
# 1+8+72 frames, batch 1, AdamW with fp32 masters; recomputation as RECOMPUTE, default on) with the
# DiT blocks' linear layers in bf16 and then in FP8 (`train.fp8`), one after the other on the same
# GPU, each with its breakdown (attention, linear layers, the rest) and its peak memory.
# REFERENCE=1 (tests/reference/wheels copied too) then times the reference's best configuration
# in the same run (tests/reference/run_gpu.sh train, checkpointing off) and prints each step
# against it (the issue's targets: bf16 1.35x, FP8 1.7x). Each step is bench-train's median of
# its timed steps (its breakdown's first line).
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
unpack .pack/bwm.xz dist/bwm || exit 1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
for mode in bf16 fp8; do
  sets=(--set 'run.device="cuda"' --set train.grad_accum=1 --set "train.recompute=${RECOMPUTE:-true}")
  [ $mode = fp8 ] && sets+=(--set train.fp8=true)
  mem "train5b_$mode" dist/bwm bench-train --config configs/bwm-wan22-ti2v-5b.toml "${sets[@]}" --steps "${STEPS:-6}" --breakdown --out "/tmp/bench-train-$mode"
done
step() { sed -n 's/^breakdown of a \([0-9.]*\) s step.*/\1/p' "$OUT/train5b_$1.log" | head -1; }
if [ "${REFERENCE:-0}" = 1 ]; then
  TRAIN_ARGS="--no-checkpointing" bash tests/reference/run_gpu.sh train
  ref=$(sed -n 's/^reference train: \([0-9.]*\) s\/step.*/\1/p' "$OUT/reference-train.log" | head -1)
  for mode in bf16 fp8; do
    s=$(step $mode)
    if [ -n "$s" ] && [ -n "$ref" ]; then
      echo "fp8_train: $mode $s s per step, the reference $ref s: $(awk -v a="$ref" -v b="$s" 'BEGIN { printf "%.3f", a / b }')x"
    else
      echo "fp8_train: $mode ${s:-no} step, the reference ${ref:-no} step: no ratio"
    fi
  done | tee "$OUT/fp8_vs_reference.txt"
fi
