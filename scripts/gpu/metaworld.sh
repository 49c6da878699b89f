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
python3 - <<'PY' || exit 1
import importlib
missing = []
for name in ("numpy", "torch", "pyarrow", "PIL", "scipy", "msgpack", "websockets", "metaworld", "mujoco"):
    try:
        m = importlib.import_module(name)
        print(f"{name} {getattr(m, '__version__', '')}")
    except Exception as e:
        missing.append(f"{name} ({e})")
if missing:
    raise SystemExit("missing on this machine: " + ", ".join(missing))
PY
bash bench/metaworld/recipe.sh "$@" 2>&1 | tee -a "$OUT/recipe.log"
status=${PIPESTATUS[0]}
# What the run measured comes back (small files only; the datasets and latents stay there).
R=runs/metaworld
mkdir -p "$OUT/run"
cp $R/timings.tsv $R/*.svg $R/judge.json $R/metrics.jsonl "$OUT/run/" 2>/dev/null
(cd $R && find fidelity study -type f \( -name '*.json' -o -name '*.jsonl' -o -name '*.csv' -o -name '*.svg' -o -name '*.log' \
  -o -name '*.toml' -o -name '*.png' \) -not -path '*/videos/*' -size -3M -exec cp --parents {} "$OUT/run/" \; 2>/dev/null)
exit "$status"
