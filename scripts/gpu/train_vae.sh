#!/usr/bin/env bash
# On one GPU of a CUDA host, from the repo root, with dist/bwm (built without FFmpeg) and the
# frames dumped here (this machine has FFmpeg) by
#   bwm train-vae --resolution 256x192 --dump-frames dist/vae/frames-256x192.safetensors
#   gzip dist/vae/frames-256x192.safetensors        # optional: a smaller copy to the host
# (default split: the last 20% of every bundled episode held out). Fits small VAEs on the GPU, side
# by side, and reports each one's held-out reconstruction PSNR.
#   RUNS     space-separated RES:DIM:CROP:BATCH settings, e.g. "256x192:32:128x96:8 192x144:32:96x64:8"
#            (frames read from dist/vae/frames-RES.safetensors[.gz]; CROP "-" trains on whole frames)
#   BUDGET_S seconds each run may train (all runs share the GPU): the step count is set from the step
#            time measured in a short calibration run of all settings together
#   STEPS    fixed step count instead of BUDGET_S
set -uo pipefail
source scripts/gpu/common.sh
RUNS=${RUNS:-"256x192:32:128x96:8"}
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee "$OUT/gpu.txt"
frames_of() { # $1 = resolution; prints the frame file, unpacked to /tmp when gzipped
  local f=dist/vae/frames-$1.safetensors
  if [ -f "$f.gz" ] && [ ! -f "/tmp/frames-$1.safetensors" ]; then gunzip -c "$f.gz" > "/tmp/frames-$1.safetensors"; fi
  [ -f "$f.gz" ] && f=/tmp/frames-$1.safetensors
  echo "$f"
}
fit() { # $1 = setting, $2 = steps, $3 = log name
  IFS=: read -r res dim crop batch <<< "$1"
  local c=(); [ "$crop" != "-" ] && c=(--crop "$crop")
  dist/bwm train-vae --frames "$(frames_of "$res")" --resolution "$res" --dim "$dim" --dec-dim "$dim" "${c[@]}" \
    --steps "$2" --batch "${batch:-8}" --lr "${LR:-2e-3}" --eval-every "${EVAL_EVERY:-1000}" --device "${DEVICE:-cuda}" \
    --out "/tmp/vae-$3.safetensors" > "$OUT/$3.log" 2>&1
}
for r in $RUNS; do frames_of "${r%%:*}" > /dev/null; done
i=0; pids=()
for r in $RUNS; do
  i=$((i + 1))
  steps=${STEPS:-}
  if [ -z "$steps" ]; then
    fit "$r" "${CAL_STEPS:-40}" "calibrate-$i" & pids+=($!)
  fi
done
if [ -z "${STEPS:-}" ]; then wait "${pids[@]}"; fi
i=0; pids=()
for r in $RUNS; do
  i=$((i + 1))
  steps=${STEPS:-}
  if [ -z "$steps" ]; then
    sps=$(grep -o '[0-9.]* s/step' "$OUT/calibrate-$i.log" | tail -1 | cut -d' ' -f1)
    steps=$(python3 -c "print(int(${BUDGET_S:-420} / max($sps, 1e-3) / 100) * 100)")
    echo "run $i ($r): calibration $sps s/step -> $steps steps"
  fi
  fit "$r" "$steps" "run-$i" & pids+=($!)
done
wait "${pids[@]}"
i=0
for r in $RUNS; do
  i=$((i + 1))
  echo "== run $i: $r"; grep -E "held-out|PSNR .* dB on" "$OUT/run-$i.log" | tail -8
done
