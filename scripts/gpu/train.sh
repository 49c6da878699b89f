#!/usr/bin/env bash
# On one GPU of a CUDA host (an H200), from the repo root, with dist/bwm built
# without FFmpeg/HDF5 (`cargo build --release -p bwm-cli --no-default-features`, stripped).
# Times the real 5B training step (random init, 640x480, 1+8+72 frames, batch 1, recomputation on,
# AdamW with fp32 masters) while sampling GPU memory.
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
mem train5b dist/bwm bench-train --config configs/bwm-wan22-ti2v-5b.toml --set run.device=\"cuda\" --set train.grad_accum=1 --steps ${STEPS:-4} --out /tmp/bench-train
mem train5b_accum2 dist/bwm bench-train --config configs/bwm-wan22-ti2v-5b.toml --set run.device=\"cuda\" --set train.grad_accum=2 --steps 2 --out /tmp/bench-train2
