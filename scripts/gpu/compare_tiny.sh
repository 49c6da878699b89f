#!/usr/bin/env bash
# On the development machine, after scripts/gpu/dist_tiny.sh: trains the same tiny run on the CPU
# (2 ranks over the TCP collective, `bwm launch`) and compares its final weights with the NCCL
# run's. Usage: BWM=path/to/bwm bash scripts/gpu/compare_tiny.sh NCCL_MODEL.safetensors
set -euo pipefail
NCCL=${1:?usage: compare_tiny.sh NCCL_MODEL.safetensors}
BWM=${BWM:-bwm}
RUN=${RUN:-/tmp/tcp-tiny}
sed '/^\[validation\]/,$d' configs/tiny.toml > /tmp/tiny-cpu.toml
rm -rf "$RUN"
"$BWM" launch --nproc-per-node 2 -- train --config /tmp/tiny-cpu.toml --set 'run.device="cpu"' --set 'model.dtype="f32"' \
  --set log.tensorboard=false --set train.steps=3 --set "run.out_dir=\"$RUN\"" | tail -2
python3 - "$NCCL" "$RUN/checkpoints/$(cat "$RUN/checkpoints/latest")/model.safetensors" <<'PY'
import sys
from safetensors.torch import load_file
a, b = load_file(sys.argv[1]), load_file(sys.argv[2])
assert a.keys() == b.keys(), "different tensors"
worst = max(((a[k] - b[k]).norm() / b[k].norm().clamp_min(1e-12)).item() for k in a)
num = sum(((a[k] - b[k]).double() ** 2).sum().item() for k in a) ** 0.5
den = sum((b[k].double() ** 2).sum().item() for k in a) ** 0.5
mad = max((a[k] - b[k]).abs().max().item() for k in a)
print(f"{len(a)} tensors: worst per-tensor relative error {worst:.2e}, whole model {num / den:.2e}, max abs difference {mad:.2e}")
sys.exit(0 if worst <= 1e-4 else 1)
PY
