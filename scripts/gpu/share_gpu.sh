#!/usr/bin/env bash
# Whether two Meta-World recipes can share one GPU (from the repo root, with .pack, .whl and .gl
# copied to the host): the recipe's DiT step (`bwm bench-train`, configs/metaworld.toml at
# 128x128, 24 future frames) and its graphed VAE step (`bwm train-vae` with the recipe's settings,
# one candidate, on a small dataset made by the recipe's data stage), each alone and then two at
# once on the same GPU. Usage: bash scripts/gpu/share_gpu.sh [DIT_STEPS [VAE_STEPS]] (default 300
# and 200). Logs in $OUT/NAME.log; the summary on stdout: per process the median over the second
# half of its logged steps (the DiT's samples/s, the VAE's s/step) and its wall time.
set -uo pipefail
source "$(dirname "$0")/common.sh"
dit_steps=${1:-300}
vae_steps=${2:-200}
# The data stage's own outputs (recipe.log, run.tar.gz) stay out of $OUT: keeps the results
# to copy back few.
mkdir -p /tmp/share-gpu/times
OUT=/tmp/share-gpu/data-out RUN=/tmp/share-gpu TRAIN_EPISODES=20 VAL_EPISODES=2 WORKERS="$(nproc)" bash "$(dirname "$0")/metaworld.sh" data > "$OUT/data.log" 2>&1 \
  || { tail -20 "$OUT/data.log"; exit 1; }
dit() { # $1 = name
  CUDA_VISIBLE_DEVICES=0 dist/bwm bench-train --config configs/metaworld.toml --set 'run.device="cuda"' \
    --height 128 --width 128 --future 24 --steps "$dit_steps" --out "/tmp/share-gpu/$1" > "$OUT/$1.log" 2>&1
}
vae() { # $1 = name
  CUDA_VISIBLE_DEVICES=0 dist/bwm train-vae --data /tmp/share-gpu/data/train --max-episodes 40 --holdout-tail 0.3 \
    --resolution 128x128 --dim 32 --dec-dim 32 --spatial-stride 16 --clip-frames 33 --batch 4 --steps "$vae_steps" \
    --lr 1e-3 --no-flip --eval-every 100000 --z-dim 48 --cuda-graph --device cuda --out "/tmp/share-gpu/$1.safetensors" \
    > "$OUT/$1.log" 2>&1
}
summary() { # $1 = the logged figure (samples/s or s/step), the rest names
  local unit=$1; shift
  for name in "$@"; do
    read -r med half n < <(second_half_median "$unit" "$OUT/$name.log")
    echo "$name: median $med $unit over the last $half of $n logged steps; $(cat "/tmp/share-gpu/times/$name.wall") s by the clock (status $(cat "/tmp/share-gpu/times/$name.rc"))"
  done
}
timed() { # $1 = function, $2 = name: runs it, its wall time and status beside the other processes'
  local start=$(date +%s%N) t=/tmp/share-gpu/times/$2
  "$1" "$2"; echo $? > "$t.rc"
  echo "$(( ($(date +%s%N) - start) / 1000000 ))" | awk '{ printf "%.1f\n", $1 / 1000 }' > "$t.wall"
}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
timed dit dit-alone
timed dit dit-pair-a & timed dit dit-pair-b & wait
summary samples/s dit-alone dit-pair-a dit-pair-b
timed vae vae-alone
timed vae vae-pair-a & timed vae vae-pair-b & wait
summary s/step vae-alone vae-pair-a vae-pair-b
