#!/usr/bin/env bash
# Run where PyPI is reachable (the development machine): downloads the pure-python wheels the
# reference scripts need into tests/reference/wheels/ (git-ignored), for run_gpu.sh on the GPU
# machine, which has torch and numpy in its system python but no internet.
# PYTHON picks the interpreter whose pip downloads (any python >= 3.10 with pip: the wheels are
# py3-none-any).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
PY=${PYTHON:-python3}
mkdir -p "$HERE/wheels"
"$PY" -m pip download --no-deps --only-binary=:all: --dest "$HERE/wheels" -r "$HERE/requirements.txt"
ls -l "$HERE/wheels"
du -sh "$HERE/wheels"
