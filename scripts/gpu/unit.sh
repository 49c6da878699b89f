#!/usr/bin/env bash
# The unit tests that only check something where there is a GPU (on CPU they say so and pass):
# CUDA graphs (cuda-graph/: a replayed forward and backward pass against the eager one, a capture
# that fails, and work queued on two CUDA streams in turn, as `--streams` does), and the VAE's
# and the DiT's training with the step replayed from a graph against
# the eager training (trainer/: `vae_train` and tests/training.rs), and rollouts whose sampler
# replays a recorded forward pass against eager ones (inference/: `graphed`), and the fused AdamW kernels
# against the tensor path and the accumulator (trainer/: `optim`), and the rotary embedding's kernels
# and the DiT's fused element-wise kernels (rotary embedding, per-frame multiply-add) against the
# CPU arithmetic and libtorch's, and the FP8 quantization kernel against libtorch's cast
# (fused-ops/: `fused`), and the FP8 linear's training products on CUDA (fp8-autograd/: `fp8`).
# From the repo root of a lent
# machine, carry [".carry-tests"] as scripts/gpu/carry.sh prepares it (all six beside the wheels
# pass the device tool's 64 MiB; the groups asked for need only their own test-*.xz):
#   bash scripts/gpu/unit.sh [GROUP ...]
# GROUP: `vae` (cuda-graph's tests and the VAE's graphed training: what the recipe's VAE_GRAPH
# relies on; the streams of `--streams` too), `dit` (the DiT's graphed training,
# `train.cuda_graph`), `rollout` (the graphed
# sampler, `--cuda-graph`), `optim` (the fused AdamW kernels, `optim.fused`) or `fused` (the DiT's
# fused element-wise kernels and the FP8 quantization, used on CUDA) or `fp8` (`train.fp8`'s
# linear); default all six. (The recipe
# needs no fallback of its own: with VAE_GRAPH=auto it trains the VAE eagerly should the graph fail.)
# Exits non-zero when a test failed; the output is also in $OUT/unit.log.
set -uo pipefail
source "$(dirname "$0")/common.sh"
groups=("$@"); [ ${#groups[@]} -gt 0 ] || groups=(vae dit rollout optim fused fp8)
crates=()  # the groups' own test binaries: only those need to travel (beside the wheels the six pass the 64 MiB)
for g in "${groups[@]}"; do
  case "$g" in
    vae) crates+=(cuda-graph trainer) ;; dit) crates+=(training) ;; rollout) crates+=(inference) ;;
    optim) crates+=(trainer) ;; fused) crates+=(fused-ops) ;; fp8) crates+=(fp8-autograd) ;;
    *) echo "unit: unknown group '$g' (groups: vae dit rollout optim fused fp8)" >&2; exit 2 ;;
  esac
done
mkdir -p dist
status=0
{
  for crate in $(printf '%s\n' "${crates[@]}" | sort -u); do
    [ -f ".carry-tests/test-$crate.xz" ] || { echo "unit: .carry-tests/test-$crate.xz is missing (scripts/gpu/carry.sh --rebuild; carry [\".carry-tests\"])"; exit 2; }
    unpack ".carry-tests/test-$crate.xz" "dist/test-$crate" || exit 2
  done
  for g in "${groups[@]}"; do
    if [ "$g" = vae ]; then
      # One test at a time: a capture fails when another thread's CUDA work waits on the device
      # meanwhile (the trainer's own tests also take turns on the GPU).
      dist/test-cuda-graph --test-threads 1 || status=1
      dist/test-trainer the_cuda_graph --test-threads 1 || status=1
    elif [ "$g" = dit ]; then
      dist/test-training cuda_graph --test-threads 1 || status=1
    elif [ "$g" = fused ]; then
      dist/test-fused-ops --ignored --test-threads 1 || status=1
    elif [ "$g" = fp8 ]; then
      dist/test-fp8-autograd --ignored --test-threads 1 || status=1
    elif [ "$g" = optim ]; then
      dist/test-trainer --ignored optim::tests::fused_update optim::tests::the_update_reads --test-threads 1 || status=1
    else
      dist/test-inference graphed --test-threads 1 || status=1
    fi
  done
  exit $status
} 2>&1 | tee "$OUT/unit.log"
exit "${PIPESTATUS[0]}"
