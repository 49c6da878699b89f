#!/usr/bin/env bash
# On one H200, from the repo root, with .pack and tests/reference/wheels copied to the
# host: where the 5B training step's GPU time goes, ours and the reference's
# in one run, both with every block's activations kept (accumulation 1, bf16 weights, fp32
# masters and moments, clip 1.0, random weights, 640x480, 1+8+72 frames):
#   dist/bwm bench-train --config configs/bwm-wan22-ti2v-5b.toml --set train.recompute=false --profile T
#   tests/reference/train_step.py --mode master --no-checkpointing --profile T  (torch.profiler)
# Each prints its GPU's busy and idle time and its kernels with the most GPU time; the Chrome traces
# go xz-compressed into $OUT.
# SET: more `--set` overrides for ours (e.g. "train.recompute=true"); STEPS (default 4: three profiled);
# REFERENCE=0 profiles ours alone.
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
unpack .pack/bwm.xz dist/bwm || exit 1
sets=(--set 'run.device="cuda"' --set train.grad_accum=1 --set train.recompute=false)
for s in ${SET:-}; do sets+=(--set "$s"); done
mem bwm-profile dist/bwm bench-train --config configs/bwm-wan22-ti2v-5b.toml "${sets[@]}" --steps "${STEPS:-4}" \
  --profile /tmp/bwm-trace.json --out /tmp/bench-train-profile
xz -T0 -c /tmp/bwm-trace.json > "$OUT/bwm-trace.json.xz"
if [ "${REFERENCE:-1}" != 0 ]; then
  TRAIN_ARGS="--no-checkpointing --steps $(( ${STEPS:-4} - 1 )) --profile /tmp/reference-trace.json" bash tests/reference/run_gpu.sh train
  xz -T0 -c /tmp/reference-trace.json > "$OUT/reference-trace.json.xz"
fi
ls -la "$OUT"
