#!/usr/bin/env bash
# On one GPU, from the repo root, with .pack copied to the host: rollout chunks with the sampler's
# forward pass eager and replayed from a CUDA graph (`--cuda-graph`), for the 5B at 640x480 (x0 + 8
# history, 72 frames, as scripts/gpu/rollout.sh) and for a model of the Meta-World recipe's size
# (configs/metaworld.toml's [model] on random weights, 128x128, x0 + 8 history, 24 frames; the
# random VAE is the full-width Wan2.2 one, so only its DiT seconds compare with the recipe's), at
# STEPS sampler steps each (default "4 20"), one rollout at a time and BATCH (default 32) together
# as the evaluator's episodes in flight; MODELS (default "5b mw") picks the models. Logs in
# $OUT/graph-*.log.
set -uo pipefail
source "$(dirname "$0")/common.sh"
unpack .pack/bwm.xz dist/bwm || exit 1
for steps in ${STEPS:-4 20}; do
  for g in 0 1; do
    [[ " ${MODELS:-5b mw} " == *" 5b "* ]] || break
    CHUNKS=3 RESIDUAL=model SAMPLE_STEPS=$steps GRAPH=$g LOG=graph-5b-s$steps-g$g bash scripts/gpu/rollout.sh | grep -E "^chunk|peak|bench-rollout"
  done
  for b in 1 ${BATCH:-32}; do
    [[ " ${MODELS:-5b mw} " == *" mw "* ]] || break
    for g in 0 1; do
      mem graph-mw-s$steps-b$b-g$g dist/bwm bench-rollout --random-weights configs/metaworld.toml --random-vae --device cuda --dtype bf16 \
        --history 8 --future 24 --sample-steps "$steps" --chunks 4 --batch $b --height 128 --width 128 --residual model \
        $([ $g = 1 ] && echo --cuda-graph) | grep -E "^chunk|peak|bench-rollout"
    done
  done
done
