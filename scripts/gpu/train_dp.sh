#!/usr/bin/env bash
# On a CUDA host of 2 GPUs (measured on two H200s), from the repo root, with dist/bwm built
# without FFmpeg/HDF5. The 5B training step on one GPU, then data-parallel over NCCL: `bwm launch`
# starts one rank per GPU (torchrun's variables, NCCL_NVLS_ENABLE=0, a libnccl.so link to the torch
# wheel's NCCL), each running the real training step on random weights (identical on both ranks,
# checked by checksum). SHARD=false keeps the optimizer state replicated; OVERLAP=false reduces the
# gradients after the backward walk instead of during it; SINGLE=0 skips the one-GPU baseline.
set -uo pipefail
source "$(dirname "$0")/common.sh"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
STEPS=${STEPS:-5}
COMMON=(--config configs/bwm-wan22-ti2v-5b.toml --set run.device=\"cuda\" --set train.grad_accum=${ACCUM:-1} --set train.shard_optimizer=${SHARD:-true} --set train.overlap_grad_reduce=${OVERLAP:-true} --steps $STEPS)
if [ "${SINGLE:-1}" = 1 ]; then
  CUDA_VISIBLE_DEVICES=0 mem single dist/bwm bench-train "${COMMON[@]}" --out /tmp/bench-single
fi
TAG=dp-overlap-${OVERLAP:-true}
nvidia-smi --query-gpu=index,memory.used --format=csv,noheader,nounits -lms 100 > "$OUT/$TAG.mem" &
pid=$!
dist/bwm launch --nproc-per-node 2 -- bench-train "${COMMON[@]}" --out /tmp/bench-dp 2>&1 | tee "$OUT/$TAG.log"
kill $pid
for g in 0 1; do echo "GPU $g peak $(grep "^$g," "$OUT/$TAG.mem" | cut -d, -f2 | sort -n | tail -1) MiB"; done | tee -a "$OUT/$TAG.log"
