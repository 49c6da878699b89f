#!/usr/bin/env bash
# Installs what a command needs, when missing (Debian packages with apt-get, as root or through
# sudo; Python packages into the project virtualenv, never system-wide). Two parts:
#   scripts/setup.sh          the build's: the Debian libraries `bwm` links (FFmpeg's and HDF5's
#                             development packages, libclang, pkg-config) and the virtualenv with
#                             libtorch (the PyPI torch wheel). What `make demo` and `make build`
#                             run (through scripts/env.sh).
#   scripts/setup.sh --tests  the build's, then what only the tests use: the ffmpeg command, Slurm,
#                             munge and iproute2 (the test cluster), Mesa's EGL/OSMesa (MuJoCo's
#                             rendering for bench/metaworld), the Python packages the tests and the
#                             reference use and the Meta-World benchmark's pinned packages, and the
#                             golden files of the parity tests (scripts/golden.py, cached in the
#                             virtualenv). What `make test` and `make setup` run.
# Idempotent: present packages and a venv that already has them are left alone.
# BWM_VENV picks the location (default: .venv in the repository).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${BWM_VENV:-$ROOT/.venv}"
tests=0
case "${1:-}" in
  "") ;;
  --tests) tests=1 ;;
  *) echo "usage: scripts/setup.sh [--tests]" >&2; exit 2 ;;
esac
TORCH_VERSION="2.11.0"
# The build's Python packages: libtorch comes from the torch wheel (LIBTORCH_USE_PYTORCH).
BASE_PY_PACKAGES=("torch==$TORCH_VERSION" numpy)
# The tests' (the reference implementation, the golden files, the Python helpers of the tests).
TEST_PY_PACKAGES=(safetensors tensorboard "torchaudio==2.11.0" "diffsynth==2.0.11" "diffusers==0.42.1" "peft==0.21.2" pyarrow h5py opencv-python-headless
  websockets msgpack "scikit-image==0.26.0")
# Debian packages the build needs: FFmpeg's libraries for bwm-data's `video` feature (found with
# pkg-config, bindings generated with libclang) and libhdf5 for its `hdf5` feature.
BASE_APT_PACKAGES=(libavcodec-dev libavformat-dev libavutil-dev libswscale-dev libclang-dev pkg-config libhdf5-dev)
# Debian packages only the tests need: the ffmpeg CLI that scripts/make_fixtures.py encodes the
# test datasets with; Slurm (controller, node daemon, client commands), munge and iproute2 (network
# namespaces, one per node) for the test cluster of tests/slurm.rs (scripts/slurm/); MuJoCo's
# offscreen rendering for bench/metaworld: EGL through Mesa, or OSMesa.
TEST_APT_PACKAGES=(ffmpeg slurm-wlm munge iproute2 libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6)
# The Meta-World benchmark's pinned packages (bench/metaworld/requirements.txt).
BENCH_REQUIREMENTS="$ROOT/bench/metaworld/requirements.txt"

APT_PACKAGES=("${BASE_APT_PACKAGES[@]}")
if [ $tests = 1 ]; then APT_PACKAGES+=("${TEST_APT_PACKAGES[@]}"); fi
missing=()
if command -v dpkg >/dev/null 2>&1; then
  for pkg in "${APT_PACKAGES[@]}"; do
    dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
  done
elif ! pkg-config --exists libavcodec libavformat libavutil libswscale 2>/dev/null; then
  echo "setup: no dpkg here; install FFmpeg's development libraries, libclang and pkg-config (${BASE_APT_PACKAGES[*]} on Debian)" >&2
elif [ $tests = 1 ]; then
  echo "setup: no dpkg here; the tests also use ${TEST_APT_PACKAGES[*]} (Debian names): a test whose tool is missing is skipped" >&2
fi
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=()
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null 2>&1 || { echo "setup: missing ${missing[*]}; run as root or install them" >&2; exit 1; }
    SUDO=(sudo)
  fi
  echo "setup: installing ${missing[*]}" >&2
  apt_install() { "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${missing[@]}" >&2; }
  apt_install || { "${SUDO[@]}" apt-get update -q >&2 && apt_install; }
fi

# Importing diffusers makes torch create its compile cache; keep it in the virtualenv, not as
# torchinductor_$USER in the temporary folder of everyone who sources scripts/env.sh.
export TORCHINDUCTOR_CACHE_DIR="${TORCHINDUCTOR_CACHE_DIR:-$VENV/.torchinductor}"
if ! { [ -x "$VENV/bin/python" ] && "$VENV/bin/python" - "$TORCH_VERSION" <<'PY' 2>/dev/null
import sys, torch, numpy
sys.exit(0 if torch.__version__.split("+")[0] == sys.argv[1] else 1)
PY
}; then
  echo "setup: creating virtualenv at $VENV with torch==$TORCH_VERSION (about 4.6 GB, a few minutes)" >&2
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install --quiet --disable-pip-version-check "${BASE_PY_PACKAGES[@]}"
fi
if [ $tests = 1 ]; then
  if ! "$VENV/bin/python" -c "import safetensors, tensorboard, pyarrow, h5py, cv2, torchaudio, diffsynth, diffusers, peft, websockets, msgpack, skimage" 2>/dev/null; then
    echo "setup: installing the tests' Python packages into $VENV" >&2
    # torch pinned again, so that no package of the list moves it.
    "$VENV/bin/pip" install --quiet --disable-pip-version-check "${BASE_PY_PACKAGES[@]}" "${TEST_PY_PACKAGES[@]}"
  fi
  if ! "$VENV/bin/python" -c "import metaworld, mujoco, gymnasium, PIL, scipy" 2>/dev/null; then
    echo "setup: installing the Meta-World benchmark's packages ($BENCH_REQUIREMENTS)" >&2
    "$VENV/bin/pip" install --quiet --disable-pip-version-check -r "$BENCH_REQUIREMENTS"
  fi
fi
if [ $tests = 1 ]; then
  # The golden files of the parity tests, computed by the reference implementation the packages
  # above pin (scripts/golden.py: DiffSynth-Studio on torch, on the CPU, about a minute) into the
  # virtualenv, under the start of the generator's SHA-256: a changed generator or a new virtualenv
  # computes them again, an unchanged one finds them. The tests read them there unless BWM_SHARED
  # names a folder with golden/ (bwm-testdir's files.rs).
  GOLDEN="$VENV/bwm-golden/$(sha256sum "$ROOT/scripts/golden.py" | cut -c1-16)"
  if [ ! -f "$GOLDEN/complete" ]; then
    echo "setup: computing the golden files with the reference (scripts/golden.py) into $GOLDEN" >&2
    rm -rf "$GOLDEN.partial" && mkdir -p "$GOLDEN.partial"
    "$VENV/bin/python" "$ROOT/scripts/golden.py" "$GOLDEN.partial" >&2
    touch "$GOLDEN.partial/complete"
    rm -rf "$GOLDEN" && mv "$GOLDEN.partial" "$GOLDEN"
  fi
fi
echo "setup: done" >&2
