#!/usr/bin/env bash
# On the GPU machine (device tool), from the repo root, with the binaries copied into dist/:
#   dist/bwm and dist/cuda_parity (the test binary of tests/cuda_parity.rs).
# Runs the CUDA-vs-CPU parity test, then the 5B forward benchmark while sampling GPU memory.
set -uo pipefail
OUT="${OUT:-/tmp/out}"; mkdir -p "$OUT"
TL=$(python3 -c 'import torch,os;print(os.path.dirname(torch.__file__))')/lib
export LD_LIBRARY_PATH=$TL:${LD_LIBRARY_PATH:-} NCCL_NVLS_ENABLE=0
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
dist/cuda_parity --ignored --nocapture 2>&1 | tee "$OUT/cuda_parity.log"
mem() { # $1 = log name; samples used memory every 50 ms while the rest of the arguments run
  local log=$1; shift
  nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 50 > "$OUT/$log.mem" &
  local pid=$!
  "$@" 2>&1 | tee "$OUT/$log.log"
  kill $pid
  local base; base=$(head -1 "$OUT/$log.mem")
  local peak; peak=$(sort -n "$OUT/$log.mem" | tail -1)
  echo "$log: peak GPU memory used ${peak} MiB (baseline ${base} MiB before the process)" | tee -a "$OUT/$log.log"
}
mem forward5b dist/bwm bench-forward --preset wan22_ti2v_5b --device cuda --dtype bf16 --frames 81 --height 480 --width 640 --warmup 2 --iters 10
