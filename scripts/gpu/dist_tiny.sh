#!/usr/bin/env bash
# On a CUDA host of 2 GPUs (measured on two H200s), from the repo root, with dist/bwm and a
# latent cache of the tiny config in runs/tiny/latents (both copied to the host).
# 1. NCCL parity: the tiny config in f32 trained 3 steps by 2 ranks over NCCL (`bwm launch`); the
#    final weights land in $OUT/nccl-model.safetensors to compare with the same run over TCP on the
#    CPU (scripts/gpu/compare_tiny.sh does that on the development machine).
# 2. A killed peer: 2 ranks started by hand (torchrun's variables, BWM_DIST_TIMEOUT=20); rank 1 is
#    killed with SIGKILL mid-run; rank 0 must exit non-zero with an error naming the failure within
#    the timeout (KILL=0 skips this part).
set -uo pipefail
source "$(dirname "$0")/common.sh"
# The tiny config without its [validation] section (no VAE here, and no FFmpeg for rollout.mp4).
sed '/^\[validation\]/,$d' configs/tiny.toml > /tmp/tiny-gpu.toml
TINY=(--config /tmp/tiny-gpu.toml --set 'run.device="cuda"' --set 'model.dtype="f32"' --set log.tensorboard=false)
# A run folder of an earlier call would hold its checkpoint: this run starts from none.
rm -rf /tmp/nccl-tiny /tmp/kill-tiny
dist/bwm launch --nproc-per-node 2 --master-port 29611 -- train "${TINY[@]}" --set train.steps=3 --set 'run.out_dir="/tmp/nccl-tiny"' 2>&1 | tee "$OUT/nccl-tiny.log"
rc=${PIPESTATUS[0]}
[ "$rc" = 0 ] || { echo "dist_tiny: the NCCL run failed (exit status $rc), no weights to compare" >&2; exit 1; }
cp "/tmp/nccl-tiny/checkpoints/$(cat /tmp/nccl-tiny/checkpoints/latest)/model.safetensors" "$OUT/nccl-model.safetensors" || exit 1

[ "${KILL:-1}" = 0 ] && exit 0
# Started by hand, the ranks need what `bwm launch` sets up: a libnccl.so link to the torch wheel's
# NCCL first on LD_LIBRARY_PATH (docs/architecture.md).
NL=$(python3 -c 'import nvidia.nccl,os;print(os.path.join(list(nvidia.nccl.__path__)[0],"lib"))')
mkdir -p /tmp/nccl-link && ln -sf "$NL/libnccl.so.2" /tmp/nccl-link/libnccl.so
export LD_LIBRARY_PATH=/tmp/nccl-link:$NL:$LD_LIBRARY_PATH
export BWM_DIST_TIMEOUT=20 MASTER_ADDR=127.0.0.1 MASTER_PORT=29621 WORLD_SIZE=2
for r in 0 1; do
  RANK=$r LOCAL_RANK=$r dist/bwm train "${TINY[@]}" --set train.steps=100000 --set 'run.out_dir="/tmp/kill-tiny"' > "$OUT/kill-rank$r.log" 2>&1 &
  eval "pid$r=$!"
done
sleep 25
echo "killing rank 1 (pid $pid1)" | tee "$OUT/kill.log"
kill -9 "$pid1"
start=$(date +%s%N)
wait "$pid0"; rc=$?
echo "rank 0 exited with $rc after $(( ($(date +%s%N) - start) / 1000000 )) ms (BWM_DIST_TIMEOUT=20)" | tee -a "$OUT/kill.log"
tail -3 "$OUT/kill-rank0.log" | tee -a "$OUT/kill.log"
