#!/usr/bin/env bash
# On one GPU machine (device tool), from the repo root, with dist/bwm (built without FFmpeg) and
# dist/vae/frames-96x64.safetensors written here by
#   bwm train-vae --resolution 96x64 --dump-frames dist/vae/frames-96x64.safetensors
# (the bundled episodes 0-1 for training, episode 2 held out). Fits the small VAE on the GPU and
# reports the held-out reconstruction PSNR. FRAMES, RES, DIM and CROP (e.g. FRAMES=dist/vae/frames-128x96.safetensors
# RES=128x96 DIM=32 CROP=64x48, the frames dumped the same way at that resolution) pick another setting.
set -uo pipefail
OUT="${OUT:-/tmp/out}"; mkdir -p "$OUT"
TL=$(python3 -c 'import torch,os;print(os.path.dirname(torch.__file__))')/lib
export LD_LIBRARY_PATH=$TL:${LD_LIBRARY_PATH:-}
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee "$OUT/gpu.txt"
/usr/bin/time -v dist/bwm train-vae --frames ${FRAMES:-dist/vae/frames-96x64.safetensors} --resolution ${RES:-96x64} \
  --dim ${DIM:-16} --dec-dim ${DIM:-16} ${CROP:+--crop $CROP} \
  --steps ${STEPS:-3000} --batch ${BATCH:-8} --lr ${LR:-2e-3} --eval-every 500 --device cuda \
  --out "$OUT/vae-96x64-d16.safetensors" 2>&1 | tee "$OUT/train_vae.log" | grep -v "^\s*\(Page\|Volunt\|Invol\|Swaps\|File\|Socket\|Signals\|Average\|Exit\|Minor\|Major\|Percent\|System\|User\)"
