#!/usr/bin/env bash
# On the GPU machine, from the repository root, with tests/reference/wheels copied there (run
# fetch_wheels.sh where PyPI is reachable first; the folder is git-ignored, so copy it by name):
# installs the wheels offline into a --target folder put on PYTHONPATH (a venv made from the
# system python would not see its torch where that python is itself a venv, e.g. /opt/torch/.venv:
# --system-site-packages exposes the base interpreter's packages, not the venv's) and runs the reference benchmarks, logs in $OUT/reference-<name>.log.
#
#   bash tests/reference/run_gpu.sh [vae] [rollout] [train] [train-plain] [lora] [lora-plain]
#   (default: the first four)
#
# Environment: PYTHON (default python3), REF_SITE (install folder, default /tmp/bwm-reference-site),
# REF_ARGS (extra arguments for every script, e.g. "--tiny" for a smoke test),
# TRAIN_ARGS / ROLLOUT_ARGS / VAE_ARGS (extra arguments for one script).
# "train" is the Rust recipe (fp32 masters + AdamW): about 100 GB, so an H200; "train-plain" (AdamW
# on the bf16 weights) fits an 80 GB H100. "lora" / "lora-plain" are the same two with LoRA rank
# ${LORA_RANK:-64} on every attention and FFN linear (DiffSynth's LoRA training; peft from the image).
set -uo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
OUT="${OUT:-/tmp/out}"; mkdir -p "$OUT"
PY=${PYTHON:-python3}
SITE=${REF_SITE:-/tmp/bwm-reference-site}

if ! ls "$HERE"/wheels/*.whl >/dev/null 2>&1; then
  echo "no wheels in $HERE/wheels: run tests/reference/fetch_wheels.sh where PyPI is reachable and copy the folder here" >&2
  exit 1
fi
# --no-deps: diffsynth declares transformers, modelscope, accelerate, ... which the scripts never import.
if "$PY" -m pip --version >/dev/null 2>&1; then
  "$PY" -m pip install --quiet --no-index --no-deps --find-links "$HERE/wheels" --target "$SITE" --upgrade \
    -r "$HERE/requirements.txt" || exit 1
else  # no pip: the wheels are pure python (py3-none-any), so unpacking them is an install
  mkdir -p "$SITE"
  for w in "$HERE"/wheels/*.whl; do "$PY" -m zipfile -e "$w" "$SITE" || exit 1; done
fi
export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
"$PY" -c 'import torch, numpy; print("python", __import__("sys").version.split()[0], "torch", torch.__version__, "numpy", numpy.__version__)'

# Samples the GPU's used memory every 50 ms while one script runs (comparable with the nvidia-smi
# peaks of docs/performance.md, which include the CUDA context and the allocator's cache).
run() { # $1 = log name, the rest = command
  local log=$1; shift
  echo "== $log: $*" | tee "$OUT/reference-$log.log"
  local pid=""
  if command -v nvidia-smi >/dev/null 2>&1; then
    local gpu=0; [[ "${CUDA_VISIBLE_DEVICES:-}" =~ ^[0-9]+ ]] && gpu=${BASH_REMATCH[0]}  # the GPU the script sees
    nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -i "$gpu" -lms 50 > "$OUT/reference-$log.mem" &
    pid=$!
  fi
  "$@" 2>&1 | tee -a "$OUT/reference-$log.log"
  local rc=${PIPESTATUS[0]}
  if [ -n "$pid" ]; then
    kill "$pid"; wait "$pid" 2>/dev/null
    echo "reference $log: nvidia-smi peak $(sort -n "$OUT/reference-$log.mem" | tail -1) MiB used (baseline $(head -1 "$OUT/reference-$log.mem") MiB)" \
      | tee -a "$OUT/reference-$log.log"
  fi
  [ "$rc" = 0 ] || echo "reference $log: FAILED (exit $rc)" | tee -a "$OUT/reference-$log.log"
  return 0
}

WHAT=("$@"); [ ${#WHAT[@]} -gt 0 ] || WHAT=(vae rollout train train-plain)
REF_ARGS=${REF_ARGS:-}
for w in "${WHAT[@]}"; do
  case $w in
    vae)         run vae "$PY" "$HERE/vae.py" $REF_ARGS ${VAE_ARGS:-} ;;
    rollout)     run rollout "$PY" "$HERE/rollout.py" $REF_ARGS ${ROLLOUT_ARGS:-} ;;
    train)       run train "$PY" "$HERE/train_step.py" --mode master $REF_ARGS ${TRAIN_ARGS:-} ;;
    train-plain) run train-plain "$PY" "$HERE/train_step.py" --mode plain $REF_ARGS ${TRAIN_ARGS:-} ;;
    lora)        run lora "$PY" "$HERE/train_step.py" --mode master --lora-rank "${LORA_RANK:-64}" $REF_ARGS ${TRAIN_ARGS:-} ;;
    lora-plain)  run lora-plain "$PY" "$HERE/train_step.py" --mode plain --lora-rank "${LORA_RANK:-64}" $REF_ARGS ${TRAIN_ARGS:-} ;;
    *) echo "unknown workload $w (vae, rollout, train, train-plain, lora, lora-plain)" >&2; exit 2 ;;
  esac
done
echo "== summary"
grep -h -e "^reference [a-z -]*: [0-9]" -e "nvidia-smi peak" -e "FAILED" "$OUT"/reference-*.log 2>/dev/null || true
