#!/usr/bin/env bash
# On the GPU machine, from the repo root, with the binaries copied into dist/:
#   dist/bwm and dist/cuda_parity (the test binary of tests/cuda_parity.rs).
# Runs the CUDA-vs-CPU parity test, then the 5B forward benchmark while sampling GPU memory.
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
dist/cuda_parity --ignored --nocapture 2>&1 | tee "$OUT/cuda_parity.log"
mem forward5b dist/bwm bench-forward --preset wan22_ti2v_5b --device cuda --dtype bf16 --frames 81 --height 480 --width 640 --warmup 2 --iters 10
