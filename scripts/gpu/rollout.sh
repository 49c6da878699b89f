#!/usr/bin/env bash
# On one GPU, from the repo root, with dist/bwm built without FFmpeg/HDF5: one rollout
# chunk of the 5B world model at 640x480 (x0 + 8 history frames, 72 generated frames, 50 Euler
# steps, bf16) on random weights and a random full-width Wan2.2 VAE (RESIDUAL=model: the DiT's
# residual stream in bf16; SAMPLE_STEPS and SOLVER the sampler; FP8=tensor|row the DiT blocks'
# linears in FP8; GRAPH=1 the sampler's forward pass replayed from a CUDA graph, `--cuda-graph`;
# LIGHT=1 decodes with a light decoder of random weights, `--random-light-decoder`;
# LOG names the log; BATCH rollouts at once, split into STREAMS lanes on CUDA streams of their own,
# `--batch`, `--streams`); the first chunk includes start-up costs, so two are timed.
set -uo pipefail
source "$(dirname "$0")/common.sh"
mem ${LOG:-rollout} dist/bwm bench-rollout --random-weights wan22_ti2v_5b --random-vae --device cuda --dtype bf16 \
  --history 8 --future 72 --sample-steps ${SAMPLE_STEPS:-50} --solver ${SOLVER:-euler} ${FP8:+--fp8 $FP8} \
  $([ "${GRAPH:-0}" = 1 ] && echo --cuda-graph) $([ "${LIGHT:-0}" = 1 ] && echo --random-light-decoder) \
  --chunks ${CHUNKS:-2} --residual ${RESIDUAL:-f32} --batch ${BATCH:-1} --streams ${STREAMS:-1}
