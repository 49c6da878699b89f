#!/usr/bin/env bash
# bench/metaworld/recipe.sh on a lent GPU machine (device tool), from the repo root. Carry:
#   .whl          bench/metaworld's wheels for that machine's Python 3.12 (metaworld, mujoco,
#                 gymnasium, farama-notifications, pyopengl, websockets; README of the device tool)
#   .gl           the GL loader debs (libegl1, libglvnd0, libopengl0, ...), for MuJoCo through EGL
#   .carry/bwm.xz the bwm binary built with --no-default-features (xz: the carry limit is 64 MiB)
# Usage: bash scripts/gpu/metaworld.sh [STAGE ...]; logs and timings go to $OUT.
set -uo pipefail
source "$(dirname "$0")/common.sh"
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
export MUJOCO_GL=egl PYOPENGL_PLATFORM=egl PYTHONUNBUFFERED=1
if [ ! -d /tmp/site/metaworld ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
fi
export PYTHONPATH=/tmp/site
mkdir -p dist && xz -dc .carry/bwm.xz > dist/bwm && chmod +x dist/bwm || exit 1
export BWM="$PWD/dist/bwm" PYTHON=python3
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
bash bench/metaworld/recipe.sh "$@" 2>&1 | tee -a "$OUT/recipe.log"
status=${PIPESTATUS[0]}
cp runs/metaworld/timings.tsv "$OUT/" 2>/dev/null
exit "$status"
