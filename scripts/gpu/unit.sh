#!/usr/bin/env bash
# The unit tests that only check something where there is a GPU (on CPU they say so and pass):
# CUDA graphs (cuda-graph/: a replayed forward and backward pass against the eager one, a capture
# that fails), and the VAE's and the DiT's training with the step replayed from a graph against
# the eager training (trainer/: `vae_train` and tests/training.rs). From the repo root of a lent
# machine, carry [".carry"] as scripts/gpu/carry.sh prepares it:
#   bash scripts/gpu/unit.sh
# Exits non-zero when a test failed; the output is also in $OUT/unit.log.
set -uo pipefail
source "$(dirname "$0")/common.sh"
mkdir -p dist
status=0
{
  for crate in cuda-graph trainer training; do
    [ -f ".carry/test-$crate.xz" ] || { echo "unit: .carry/test-$crate.xz is missing (scripts/gpu/carry.sh --rebuild)"; exit 2; }
    xz -dc ".carry/test-$crate.xz" > "dist/test-$crate" && chmod +x "dist/test-$crate"
  done
  # One at a time: a failed capture is one of the tests, and the others share the process.
  dist/test-cuda-graph --test-threads 1 || status=1
  dist/test-trainer the_cuda_graph || status=1
  dist/test-training cuda_graph || status=1
  exit $status
} 2>&1 | tee "$OUT/unit.log"
exit "${PIPESTATUS[0]}"
