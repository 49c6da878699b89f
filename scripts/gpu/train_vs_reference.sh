#!/usr/bin/env bash
# On one H200, from the repo root, with .pack and tests/reference/wheels copied to the host
# (scripts/gpu/pack.sh packs .pack/bwm.xz; tests/reference/fetch_wheels.sh
# fetches the wheels): the 5B training step at identical numerics (bf16 weights, fp32 masters and
# moments, clip 1.0, accumulation 1, random weights, 640x480, 1+8+72 frames, batch 1), ours and the
# reference's in one run, each with every block's activations kept and with every block
# recomputed (checkpointed):
#   dist/bwm bench-train --config configs/bwm-wan22-ti2v-5b.toml --set train.grad_accum=1 --set train.recompute=R --breakdown
#   tests/reference/run_gpu.sh train  (TRAIN_ARGS="--no-checkpointing" for the kept activations)
# BINARIES: space-separated NAME:XZ pairs of binaries to time (default "bwm:.pack/bwm.xz"; e.g.
# "before:.pack/bwm-before.xz bwm:.pack/bwm.xz" times a change against the build before it).
# STEPS optimizer steps of ours (default 6; the first is warm-up). Logs in $OUT.
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
mkdir -p dist
for pair in ${BINARIES:-bwm:.pack/bwm.xz}; do
  name=${pair%%:*} xz=${pair#*:}
  unpack "$xz" "dist/$name" || exit 1
  for recompute in false true; do
    mem "train5b-$name-recompute-$recompute" "dist/$name" bench-train --config configs/bwm-wan22-ti2v-5b.toml \
      --set 'run.device="cuda"' --set train.grad_accum=1 --set "train.recompute=$recompute" \
      --steps "${STEPS:-6}" --breakdown --out "/tmp/bench-train-$name"
  done
done
TRAIN_ARGS="--no-checkpointing" bash tests/reference/run_gpu.sh train
mv "$OUT/reference-train.log" "$OUT/reference-train-no-checkpointing.log"
mv "$OUT/reference-train.mem" "$OUT/reference-train-no-checkpointing.mem"
bash tests/reference/run_gpu.sh train
grep -h "^reference train:\|s/step" "$OUT"/reference-train*.log | grep -v "warm-up" | tail -4
