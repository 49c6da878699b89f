#!/usr/bin/env bash
# On one GPU machine (device tool), from the repo root, with the bwm binary carried as
# scripts/gpu/carry.sh packs it (.carry/bwm.xz). Times the 5B training step (random init, 640x480,
# 1+8+72 frames, batch 1, AdamW with fp32 masters; recomputation as RECOMPUTE, default on) with the
# DiT blocks' linear layers in bf16 and then in FP8 (`train.fp8`), one after the other on the same
# GPU, each with its breakdown (attention, linear layers, the rest) and its peak memory.
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
unpack .carry/bwm.xz dist/bwm || exit 1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
for mode in bf16 fp8; do
  sets=(--set 'run.device="cuda"' --set train.grad_accum=1 --set "train.recompute=${RECOMPUTE:-true}")
  [ $mode = fp8 ] && sets+=(--set train.fp8=true)
  mem "train5b_$mode" dist/bwm bench-train --config configs/bwm-wan22-ti2v-5b.toml "${sets[@]}" --steps "${STEPS:-6}" --breakdown --out "/tmp/bench-train-$mode"
done
