#!/usr/bin/env bash
# The paper's per-GPU recipe shape on all GPUs of one CUDA host (measured on four and eight
# H200s), from the repo root, with dist/bwm built without FFmpeg/HDF5: 5B, 640x480, 1+8+72 frames,
# micro-batch 1 per GPU, accumulation 4, sharded optimizer state, recomputation on, random init.
# First the same on GPU 0 alone (the scaling baseline), then `bwm launch` over every GPU.
# OVERLAP=false reduces the gradients after the backward walk instead of during it.
set -uo pipefail
source "$(dirname "$0")/common.sh"
NP=$(nvidia-smi -L | wc -l)
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
COMMON=(--config configs/bwm-wan22-ti2v-5b.toml --set 'run.device="cuda"' --set train.grad_accum=4 --set train.shard_optimizer=true --set train.overlap_grad_reduce=${OVERLAP:-true})
# BASE_STEPS=0 skips the one-GPU baseline (e.g. when it was measured on the same GPU model already).
if [ "${BASE_STEPS:-4}" -gt 0 ]; then
  CUDA_VISIBLE_DEVICES=0 mem recipe-1gpu dist/bwm bench-train "${COMMON[@]}" --steps ${BASE_STEPS:-4} --out /tmp/recipe-1
fi
nvidia-smi --query-gpu=index,memory.used --format=csv,noheader,nounits -lms 100 > "$OUT/recipe.mem" &
pid=$!
dist/bwm launch --nproc-per-node $NP -- bench-train "${COMMON[@]}" --steps ${STEPS:-20} --out /tmp/recipe-n 2>&1 | tee "$OUT/recipe-${NP}gpu-overlap-${OVERLAP:-true}.log"
kill $pid
for g in $(seq 0 $((NP - 1))); do echo "GPU $g peak $(grep "^$g," "$OUT/recipe.mem" | cut -d, -f2 | sort -n | tail -1) MiB"; done | tee -a "$OUT/recipe-${NP}gpu-overlap-${OVERLAP:-true}.log"
