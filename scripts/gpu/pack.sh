#!/usr/bin/env bash
# Packs what the GPU scripts need on a CUDA host without the Rust toolchain, FFmpeg or network
# access, built on this machine from the repo root: .pack/bwm.xz (the bwm binary built with
# --no-default-features, stripped and xz-compressed to keep the copy small), .pack-tests/test-*.xz
# (the tests of native/cuda-graph/, trainer/ (its NCCL tests too), inference/, native/fused-ops/
# and native/fp8-autograd/ that need a GPU to check anything, which scripts/gpu/unit.sh runs
# there), .whl (bench/metaworld's wheels for the host's Python 3.12) and .gl (the GL loader debs
# MuJoCo's EGL rendering needs there). Each part is skipped when present; --rebuild rebuilds and
# repacks the binaries. Copy the folders into the host's checkout of the same commit, then run
# from its repo root, for example:
#   bash scripts/gpu/metaworld.sh data   (needs .whl, .gl and .pack)
#   bash scripts/gpu/unit.sh             (needs .pack-tests)
# The unit tests are packed apart, so that a copy holds only what its scripts read. The four
# folders are git-ignored (.gitignore), so that they stay out of commits. The binaries are rebuilt
# when the source changed since they were packed (.pack/source). Respects BWM_VENV and CARGO_TARGET_DIR (default ~/.cache/bwm-gpu-target, kept apart
# from the CPU build's target: the feature sets differ).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
rebuild=0
case "${1:-}" in
  "") ;;
  --rebuild) rebuild=1 ;;
  *) echo "usage: scripts/gpu/pack.sh [--rebuild]" >&2; exit 2 ;;
esac
for d in .pack .pack-tests .whl .gl; do
  git check-ignore -q "$d/x" || { echo "pack: $d is not git-ignored; add /$d/ to .gitignore" >&2; exit 1; }
done
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/bwm-gpu-target}"
source scripts/env.sh
# The wheels' versions below are the virtualenv's own: that of the tests' part of the set-up.
"$BWM_VENV/bin/python" -c 'import websockets, safetensors' 2>/dev/null || bash scripts/setup.sh --tests

pack() { # $1 = executable, $2 = path without .xz (under .pack or .pack-tests): stripped and xz-compressed
  strip -o "$2.tmp" "$1"
  xz -T0 -6 -c "$2.tmp" > "$2.xz.tmp" && rm "$2.tmp" && mv "$2.xz.tmp" "$2.xz"
}
# The binaries' source: the commit and a hash of the uncommitted changes to tracked files and of the
# untracked files' names, kept beside them (.pack/source): binaries of other source are rebuilt.
source_now="$(git rev-parse HEAD) $( (git diff HEAD; git ls-files --others --exclude-standard) | sha256sum | cut -c1-16)"
if [ -f .pack/bwm.xz ] && [ "$(cat .pack/source 2>/dev/null)" != "$source_now" ]; then
  echo "pack: .pack was built from other source ($(cat .pack/source 2>/dev/null || echo unrecorded)); rebuilding"
  rebuild=1
fi
if [ $rebuild = 1 ] || [ ! -f .pack/bwm.xz ] || [ "$(ls .pack-tests/test-*.xz 2>/dev/null | wc -l)" -lt 7 ]; then
  echo "pack: building bwm without FFmpeg/HDF5 into $CARGO_TARGET_DIR (several minutes cold)"
  cargo build --release -p bwm-cli --no-default-features
  mkdir -p .pack .pack-tests
  pack "$CARGO_TARGET_DIR/release/bwm" .pack/bwm
  # The unit tests that need a GPU to check anything (scripts/gpu/unit.sh runs them there).
  for test in cuda-graph:--lib trainer:--lib training:--test=training inference:--lib fused-ops:--lib fp8-autograd:--lib dist_nccl:--test=dist_nccl; do
    crate=${test%%:*}; case $crate in training | dist_nccl) crate=bwm-trainer ;; *) crate=bwm-$crate ;; esac
    exe=$(cargo test --release --no-default-features -p "$crate" "${test#*:}" --no-run --message-format=json 2>/dev/null |
      "$BWM_VENV/bin/python" -c 'import json,sys; print([m["executable"] for m in map(json.loads, sys.stdin) if m.get("executable")][-1])')
    pack "$exe" ".pack-tests/test-${test%%:*}"
  done
  echo "$source_now" > .pack/source
fi

# Pinned as bench/metaworld/requirements.txt and the virtualenv's safetensors; websockets as the
# venv's. For a host with Python 3.12 on x86_64.
WHEELS=(metaworld==3.1.1 mujoco==3.3.0 gymnasium==1.4.0 farama-notifications==0.0.4 PyOpenGL==3.1.10 glfw==2.11.0
        "websockets==$("$BWM_VENV/bin/python" -c 'import websockets; print(websockets.__version__)')"
        "safetensors==$("$BWM_VENV/bin/python" -c 'import safetensors; print(safetensors.__version__)')")
if [ ! -d .whl ] || [ "$(ls .whl/*.whl 2>/dev/null | wc -l)" -lt ${#WHEELS[@]} ]; then
  mkdir -p .whl
  "$BWM_VENV/bin/pip" download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl "${WHEELS[@]}"
fi

if [ "$(ls .gl/*.deb 2>/dev/null | wc -l)" -lt 7 ]; then
  mkdir -p .gl
  lists=$(mktemp -d)
  trap 'rm -rf "$lists"' EXIT
  mkdir -p "$lists/partial"
  apt=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 "-oDir::State::Lists=$lists")
  apt-get "${apt[@]}" update > /dev/null
  (cd .gl && apt-get "${apt[@]}" download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
fi
echo "pack: $(du -sh .pack | cut -f1) binary, $(ls .whl | wc -l) wheels, $(ls .gl | wc -l) GL debs; copy .whl, .gl and .pack to the host"
echo "pack: $(du -sh .pack-tests | cut -f1) of GPU unit tests; copy .pack-tests to the host for scripts/gpu/unit.sh"
