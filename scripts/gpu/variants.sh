#!/usr/bin/env bash
# Variants of the Meta-World recipe side by side on one GPU host, from the repo
# root, with the files scripts/gpu/metaworld.sh needs copied there:
#   bash scripts/gpu/variants.sh NAME "VAR=VALUE ..." [NAME "VAR=VALUE ..." ...]
# The data are made once (runs/metaworld, when a variant uses them); each variant then runs
# scripts/gpu/metaworld.sh in runs/NAME (its data linked to those, unless its variables give other
# data than the recipe's defaults do: bench/metaworld/data-settings.sh's DATA_VARS; then it makes its
# own, or uses an earlier variant's made with the same values of those, starting once they are
# written) with its variables, on GPU i mod the machine's GPU count for the i-th variant, all at
# once; each trains its own judge, as the recipe does (it learns from the variant's VAE, so it
# trains after it, beside the latents and the DiT). With STAGES (default: every
# stage) picking stages, e.g. STAGES="vae ceiling" to compare VAEs alone, one judge of real frames
# (JUDGE_FRAMES=real: the recipe's own learns from each variant's VAE) is made first for all and
# linked into each variant's folder, and the variants use it unless they set JUDGE_FRAMES. In "VAR=VALUE ...", a word that is not NAME=...
# continues the value before it ("TRAIN_SETS=a=1 b=2" is one variable). Each variant's log and
# outputs go to $OUT/NAME (its run.tar.gz holds the run's small files). The host's cores are shared:
# each variant's WORKERS (the data's and the study's processes) defaults to nproc / variants.
# Longer than one remote command may run:
#   bash scripts/gpu/detached.sh start v bash scripts/gpu/variants.sh s8 "VAE_STRIDE=8" ...
#   bash scripts/gpu/detached.sh wait v 570 runs/s8/study ...   (back to back)
# Exits 1 when any variant failed.
set -uo pipefail -f  # -f: a variant's TRAIN_SETS holds brackets, not globs
[ $# -ge 2 ] && [ $(($# % 2)) = 0 ] || { echo 'usage: variants.sh NAME "VAR=VALUE ..." [NAME "VAR=VALUE ..." ...]' >&2; exit 2; }
cd "$(dirname "$0")/../.."
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
# Every variant's words first: a word not of the form NAME=... continues the variable before it.
# A variant's assignments are kept as one newline-separated string (bash has no arrays of arrays).
names=() assigns=() keys=() lead=()
data_settings() { # VAR=VALUE ...: every data variable's value under these assignments, one per line
  (
    for a in "$@"; do export "${a?}"; done
    source bench/metaworld/data-settings.sh || exit 2
    for v in $DATA_VARS; do echo "$v=${!v}"; done
  )
}
default_data=$(data_settings) || exit 2
while [ $# -gt 0 ]; do
  name=$1 vars=$2; shift 2
  case "$name" in metaworld|*/*|"") echo "variants: '$name' cannot name a run folder" >&2; exit 2 ;; esac
  assign=()
  for w in $vars; do
    if [[ $w =~ ^[A-Z_][A-Z0-9_]*= ]]; then assign+=("$w")
    elif [ ${#assign[@]} -gt 0 ]; then assign[-1]+=" $w"
    else echo "variants: '$vars' must start with NAME=VALUE" >&2; exit 2
    fi
  done
  names+=("$name") assigns+=("$(printf '%s\n' "${assign[@]}")")
  # The data this variant's variables give (bench/metaworld/data-settings.sh's defaults for the
  # rest): none of its own when they are the defaults'.
  key=$(data_settings "${assign[@]}") || { echo "variants: $name's data variables (above)" >&2; exit 2; }
  [ "$key" != "$default_data" ] || key=
  # A variant whose data variables are an earlier one's uses that one's data (its lead).
  l=${#keys[@]}
  for j in "${!keys[@]}"; do [ -n "$key" ] && [ "${keys[$j]}" = "$key" ] && { l=$j; break; }; done
  keys+=("$key") lead+=("$l")
done
# The shared data only when a variant links them (or the shared judge trains on them).
shared=()
own=0  # variants that make (or share) their own data
for k in "${keys[@]}"; do [ -n "$k" ] && own=$((own + 1)); done
[ "$own" -lt ${#names[@]} ] || [ -n "${STAGES:-}" ] && shared+=(data)
[ -n "${STAGES:-}" ] && shared+=(judge)
if [ ${#shared[@]} -gt 0 ]; then
  JUDGE_FRAMES=real bash scripts/gpu/metaworld.sh "${shared[@]}" > "$OUT/shared.log" 2>&1 || { echo "variants: ${shared[*]} failed ($OUT/shared.log)"; exit 1; }
fi
gpus=$(nvidia-smi -L | wc -l)
workers=$(( $(nproc) / ${#names[@]} )); [ "$workers" -ge 1 ] || workers=1
pids=()
for i in "${!names[@]}"; do
  name=${names[$i]}
  assign=()
  [ -n "${assigns[$i]}" ] && mapfile -t assign <<< "${assigns[$i]}"
  mkdir -p "runs/$name" "$OUT/$name"
  stages=${STAGES:-}
  after=  # the lead's data, when this variant waits for them
  [ -n "${keys[$i]}" ] && [ -n "$stages" ] && stages="data $stages"
  if [ -n "${keys[$i]}" ] && [ "${lead[$i]}" != "$i" ] && { [ -L "runs/$name/data" ] || [ ! -e "runs/$name/data" ]; }; then
    lead_name=${names[${lead[$i]}]}
    ln -sfn "$PWD/runs/$lead_name/data" "runs/$name/data"
    after=runs/$lead_name/data/val/meta/info.json  # generate.py renames a finished dataset into place
    echo "variants: $name uses $lead_name's data (the same data variables)"
  elif [ -n "${keys[$i]}" ]; then
    [ -L "runs/$name/data" ] && rm "runs/$name/data"
    echo "variants: $name makes its own data"
  else
    ln -sfn "$PWD/runs/metaworld/data" "runs/$name/data"
  fi
  [ -n "${STAGES:-}" ] && ln -sfn "$PWD/runs/metaworld/judge.pt" "runs/$name/judge.pt"
  echo "variants: $name on GPU $((i % gpus)):$(printf ' [%s]' "${assign[@]}")"
  # shellcheck disable=SC2086  # stages are words by design
  (
    if [ -n "$after" ]; then
      until [ -f "$after" ]; do
        kill -0 "${pids[${lead[$i]}]}" 2>/dev/null || [ -f "$after" ] || { echo "variants: ${names[${lead[$i]}]} ended without its data"; exit 1; }
        sleep 5
      done
    fi
    exec env CUDA_VISIBLE_DEVICES=$((i % gpus)) RUN="runs/$name" OUT="$OUT/$name" WORKERS="${WORKERS:-$workers}" \
      ${STAGES:+JUDGE_FRAMES=real} "${assign[@]}" \
      bash scripts/gpu/metaworld.sh $stages
  ) > "$OUT/$name/log" 2>&1 &
  pids+=($!)
done
status=0
for k in "${!pids[@]}"; do
  if wait "${pids[$k]}"; then echo "variants: ${names[$k]} done"; else echo "variants: ${names[$k]} failed ($OUT/${names[$k]}/log)"; status=1; fi
done
exit $status
