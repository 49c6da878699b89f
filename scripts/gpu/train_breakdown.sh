#!/usr/bin/env bash
# On one H200 (dist/ copied to the host), from the repo root: the 5B training
# step (640x480, 1+8+72 frames, batch 1, accumulation 1, random weights) with its breakdown, for
# each setting of RUNS, logged to $OUT/NAME.log.
#   RUNS  space-separated NAME:BINARY:RESIDUAL:KEEP, e.g. "before:bwm-old:f32:0 after:bwm:model:30"
#         (dist/BINARY; RESIDUAL f32 or model = model.residual; KEEP = train.recompute_keep_last)
#   STEPS optimizer steps per setting (default 5)
set -uo pipefail
source scripts/gpu/common.sh
RUNS=${RUNS:-"f32-0:bwm:f32:0 model-0:bwm:model:0 model-30:bwm:model:30"}
for r in $RUNS; do
  IFS=: read -r name bin residual keep <<< "$r"
  dist/$bin bench-train --config configs/bwm-wan22-ti2v-5b.toml --set 'run.device="cuda"' --set train.grad_accum=1 \
    --set train.recompute_keep_last=$keep --set "model.residual=\"$residual\"" --steps ${STEPS:-5} --breakdown > "$OUT/$name.log" 2>&1
  echo "== $name (dist/$bin, residual $residual, keep $keep)"
  grep -E "^step|breakdown|^  |rror" "$OUT/$name.log" | grep -v "step      1/"
done
