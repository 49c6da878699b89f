#!/usr/bin/env bash
# On the GPU machine, from the repo root, with dist/bwm: Wan2.2 VAE encode/decode of 81 frames at
# 640x480 in bf16 (random weights), then a 30 s streaming decode, sampling GPU memory with time stamps.
set -uo pipefail
OUT="${OUT:-/tmp/out}"; mkdir -p "$OUT"
TL=$(python3 -c 'import torch,os;print(os.path.dirname(torch.__file__))')/lib
export LD_LIBRARY_PATH=$TL:${LD_LIBRARY_PATH:-} NCCL_NVLS_ENABLE=0
nvidia-smi --query-gpu=timestamp,memory.used --format=csv,noheader,nounits -lms 100 > "$OUT/vae.mem" &
pid=$!
dist/bwm bench-vae --device cuda --dtype bf16 --frames 81 --height 480 --width 640 --iters 3 --stream-seconds 30 2>&1 \
  | while IFS= read -r line; do echo "$(date '+%H:%M:%S.%3N') $line"; done | tee "$OUT/vae.log"
kill $pid
echo "peak GPU memory used: $(cut -d, -f2 "$OUT/vae.mem" | sort -n | tail -1) MiB" | tee -a "$OUT/vae.log"
