#!/usr/bin/env bash
# On one GPU of a CUDA host (the LoRA issue asks for one H100), from the repo
# root, with the bwm binary copied there as scripts/gpu/pack.sh packs it (.pack/bwm.xz). Times the
# 5B training step with LoRA rank 64 on every attention and FFN linear (the override of the README's
# LoRA guide: adapters and the action encoder trained, the base frozen in bf16), and with FULL=1 full
# fine-tuning beside it, at 640x480, 1+8+72 frames, batch 1, random weights, while sampling GPU memory.
#   bash scripts/gpu/lora.sh
# RECOMPUTE=false times LoRA without recomputation too; STEPS (default 5) steps each. With the
# reference wheels copied too (tests/reference/fetch_wheels.sh), DiffSynth's LoRA training of the same
# model and shapes runs after it in the same run (tests/reference/run_gpu.sh lora-plain lora):
#   bash scripts/gpu/lora.sh            (.pack and tests/reference/wheels copied; one H100)
#   FULL=1 bash scripts/gpu/lora.sh     (full fine-tuning needs an H200's memory)
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
unpack .pack/bwm.xz dist/bwm || exit 1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
common=(--config configs/bwm-wan22-ti2v-5b.toml --set run.device=\"cuda\" --set train.grad_accum=1 --steps "${STEPS:-5}")
mem lora64_recompute dist/bwm bench-train "${common[@]}" "${LORA64[@]}" --out /tmp/bench-lora
if [ "${RECOMPUTE:-true}" = false ]; then
  mem lora64 dist/bwm bench-train "${common[@]}" "${LORA64[@]}" --set train.recompute=false --out /tmp/bench-lora2
fi
# Full fine-tuning needs about 95.5 GiB (97,777 MiB) with every block recomputed (docs/performance.md, "LoRA
# post-training of the 5B on one H100 80 GB"): FULL=1 on an
# H200 call.
if [ "${FULL:-0}" = 1 ]; then
  mem full_recompute dist/bwm bench-train "${common[@]}" --out /tmp/bench-full
fi
if ls tests/reference/wheels/*.whl >/dev/null 2>&1; then
  LORA_RANK=64 bash tests/reference/run_gpu.sh lora-plain lora
fi
echo "== summary"
grep -h -e "peak GPU memory" -e "^reference [a-z -]*: [0-9]" -e "nvidia-smi peak" "$OUT"/*.log 2>/dev/null
