#!/usr/bin/env bash
# On one GPU of a CUDA host, from the repo root, with the bwm binary copied there as
# scripts/gpu/pack.sh packs it (.pack/bwm.xz): the attention kernels of libtorch 2.11 on the 5B's
# shapes (scripts/gpu/sdpa_backends.py), then `bwm bench-rollout` (5B, random weights, 640x480,
# x0 + 8 history, 72 frames, STEPS sampler steps, 2 chunks) under each --sdp-backend in BACKENDS.
#   bash scripts/gpu/attention.sh   (measured on one H100)
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
unpack .pack/bwm.xz dist/bwm || exit 1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
python3 scripts/gpu/sdpa_backends.py 2>&1 | tee "$OUT/sdpa_backends.log"
for b in ${BACKENDS:-auto cudnn efficient}; do
  dist/bwm --sdp-backend "$b" bench-rollout --random-weights wan22_ti2v_5b --random-vae --device cuda --dtype bf16 --residual model \
    --history 8 --future 72 --sample-steps "${STEPS:-20}" --chunks 2 2>&1 | tee "$OUT/rollout-$b.log" | grep -v "^\s*$"
done
