#!/usr/bin/env bash
# The unit tests that need a GPU to check anything (`#[ignore]`d in a plain `cargo test`, run here
# with --ignored): CUDA graphs (native/cuda-graph/: a replayed forward and backward pass against the eager
# one, a capture that fails, and work queued on two CUDA streams in turn, as `--streams` does), and
# the VAE's and the DiT's training with the step replayed from a graph against the eager training
# (trainer/: `vae_train` and tests/training.rs), and rollouts whose sampler replays a recorded
# forward pass against eager ones, with and without the hand map (inference/: `graphed`), and the fused AdamW kernels against the
# tensor path and the accumulator (trainer/: `optim`), and the rotary embedding's kernels and the
# DiT's fused element-wise kernels (rotary embedding, per-frame multiply-add) against the CPU
# arithmetic and libtorch's, and the FP8 quantization kernel against libtorch's cast (native/fused-ops/:
# `fused`), and the FP8 linear's training products on CUDA (native/fp8-autograd/: `fp8`), and NCCL
# (trainer/tests/dist_nccl.rs: the collectives, a peer that dies or stops, and 2 ranks training as
# 1 rank with the same global batch, the gradients reduced during the backward walk or after it).
# Nothing is optional here: BWM_REQUIRE=all (common.sh), so a test whose CUDA device, NCCL or
# second GPU is missing fails instead of skipping, and a test binary that runs no test (a filter
# that matches nothing) fails too: a binary that failed to link libtorch_cuda cannot pass.
# From the repo root of a CUDA host, with .pack-tests copied there as scripts/gpu/pack.sh prepares
# it (the groups asked for need only their own test-*.xz):
#   bash scripts/gpu/unit.sh [GROUP ...]
# GROUP: `vae` (cuda-graph's tests and the VAE's graphed training: what the recipe's VAE_GRAPH
# relies on; the streams of `--streams` too), `dit` (the DiT's graphed training,
# `train.cuda_graph`), `rollout` (the graphed sampler, `--cuda-graph`), `optim` (the fused AdamW
# kernels, `optim.fused`) or `fused` (the DiT's fused element-wise kernels and the FP8
# quantization, used on CUDA) or `fp8` (`train.fp8`'s linear) or `nccl` (needs 2 GPUs); default
# all seven: on a machine of one GPU name the other six. (The recipe needs no fallback of its
# own: with VAE_GRAPH=auto it trains the VAE eagerly should the graph fail.)
# Exits non-zero when a test failed or a binary ran none; the output is also in $OUT/unit.log.
set -uo pipefail
source "$(dirname "$0")/common.sh"
all=(vae dit rollout optim fused fp8 nccl)
groups=("$@"); [ ${#groups[@]} -gt 0 ] || groups=("${all[@]}")
crates=()  # the groups' own test binaries: only those need to be on the host
for g in "${groups[@]}"; do
  case "$g" in
    vae) crates+=(cuda-graph trainer) ;; dit) crates+=(training) ;; rollout) crates+=(inference) ;;
    optim) crates+=(trainer) ;; fused) crates+=(fused-ops) ;; fp8) crates+=(fp8-autograd) ;; nccl) crates+=(dist_nccl) ;;
    *) echo "unit: unknown group '$g' (groups: ${all[*]})" >&2; exit 2 ;;
  esac
done

# Runs a test binary with its arguments: fails when a test failed or none ran.
tests() {
  local log rc ran
  log=$(mktemp)
  "$@" 2>&1 | tee "$log"
  rc=${PIPESTATUS[0]}
  ran=$(awk '/^test result:/ { n += $4 } END { print n + 0 }' "$log")
  rm -f "$log"
  [ "$rc" -eq 0 ] || { echo "unit: FAILED: $*"; return 1; }
  [ "$ran" -gt 0 ] || { echo "unit: FAILED: $* ran no test"; return 1; }
}

# NCCL for the dist_nccl tests: libtorch's own libnccl.so.2 reachable as libnccl.so, first on the
# library path (trainer/src/dist/nccl.rs says why).
nccl_setup() {
  local nl
  nl=$(python3 -c 'import nvidia, os; print(os.path.join(nvidia.__path__[0], "nccl/lib"))') && [ -f "$nl/libnccl.so.2" ] ||
    { echo "unit: libtorch's NCCL (nvidia/nccl/lib/libnccl.so.2 beside python3's torch) is not there"; return 1; }
  mkdir -p /tmp/nccl-link && ln -sf "$nl/libnccl.so.2" /tmp/nccl-link/libnccl.so &&
    export LD_LIBRARY_PATH=/tmp/nccl-link:$nl:$LD_LIBRARY_PATH
}

mkdir -p dist
status=0
{
  for crate in $(printf '%s\n' "${crates[@]}" | sort -u); do
    [ -f ".pack-tests/test-$crate.xz" ] || { echo "unit: .pack-tests/test-$crate.xz is missing (scripts/gpu/pack.sh --rebuild, then copy .pack-tests here)"; exit 2; }
    unpack ".pack-tests/test-$crate.xz" "dist/test-$crate" || exit 2
  done
  for g in "${groups[@]}"; do
    # One test at a time: a capture fails when another thread's CUDA work waits on the device
    # meanwhile (the trainer's own tests also take turns on the GPU).
    case "$g" in
      vae) tests dist/test-cuda-graph --ignored --test-threads 1 || status=1
           tests dist/test-trainer --ignored the_cuda_graph --test-threads 1 || status=1 ;;
      dit) tests dist/test-training --ignored cuda_graph --test-threads 1 || status=1 ;;
      rollout) tests dist/test-inference --ignored graphed --test-threads 1 || status=1 ;;
      optim) tests dist/test-trainer --ignored optim::tests::fused_update optim::tests::the_update_reads --test-threads 1 || status=1 ;;
      fused) tests dist/test-fused-ops --ignored --test-threads 1 || status=1 ;;
      fp8) tests dist/test-fp8-autograd --ignored --test-threads 1 || status=1 ;;
      nccl) ( nccl_setup && tests dist/test-dist_nccl --ignored nccl_ --test-threads 1 ) || status=1 ;;
    esac
  done
  exit $status
} 2>&1 | tee "$OUT/unit.log"
exit "${PIPESTATUS[0]}"
