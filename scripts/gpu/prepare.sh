#!/usr/bin/env bash
# On one GPU, from the repo root, with dist/bwm and runs/gpu-images copied to the host (made by
# `python3 scripts/gpu/make_image_dataset.py runs/gpu-images`: the 3 bundled episodes, 120 frames
# each, 640x480 JPEG frames inside LeRobot v2.1 parquet files, since the GPU machines have no FFmpeg).
# Times `bwm prepare` of 81-frame clips (x0 + 8 history + 72 future, stride 8: 18 clips) at
# 640x480 with the full-width Wan2.2 VAE (random weights) in bf16, at batch 1 and batch 4.
set -uo pipefail
source "$(dirname "$0")/common.sh"
for b in 1 4; do
  mem prepare-b$b dist/bwm prepare --data runs/gpu-images --random-vae --device cuda --resolution 640x480 \
    --history 8 --future 72 --stride 8 --batch $b --out /tmp/prepare-b$b
done
