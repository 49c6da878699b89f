#!/usr/bin/env bash
# The sampler sweep (bench/metaworld/sweep.sh) over the GPUs of one host, from the repo root,
# run detached: the first chain of settings trains the recipe's model on its GPU
# (`scripts/gpu/metaworld.sh sweep`, stages up to train, truth and judge) and then measures its
# settings; once the model is trained, the simulator's truth and the judge's verdicts are copied
# into every other setting's study folder and the other chains start beside it. Each chain is
# `GPU:SETTING,SETTING,...`; the default spreads the issue's grid over two GPUs, two chains each:
#   bash scripts/gpu/detached.sh start sw bash scripts/gpu/sweep_split.sh
#   bash scripts/gpu/detached.sh wait sw 560 runs/metaworld/sweep   (in each command, back to back)
# .whl, .gl and .pack must stay on the host until the last chain ends: a chain started after
# they were removed finds no bwm binary (run 43, docs/fidelity.md at abaed68, lost five settings
# so). In 30 minutes of GPU time,
# training (about 13 minutes on an H200) and one round of chains (about 5 minutes each) fit; the
# second settings of the chains may not. SWEEP_EPISODES (default here 10 per task) and the
# recipe's variables apply; the table: `python3 bench/metaworld/sweep.py $RUN/sweep` on the
# folders copied back.
set -uo pipefail
R=${RUN:-runs/metaworld}
export RUN=$R SWEEP_EPISODES=${SWEEP_EPISODES:-10}
CHAINS=${CHAINS:-"0:euler-50,euler-8 0:euler-4,euler-30 1:euler-20,euler-16 1:euler-12"}
base=${OUT:-/tmp/out}
read -r -a chains <<< "$CHAINS"
chain() { # $1 = index, $2 = GPU:SETTING,...
  mkdir -p "$base/c$1"
  CUDA_VISIBLE_DEVICES=${2%%:*} OUT=$base/c$1 SETTINGS="$(tr , ' ' <<< "${2#*:}")" bash scripts/gpu/metaworld.sh sweep > "$base/c$1.log" 2>&1
}
started() { # $1 = index, $2 = its pid: waits until chain $1's sweep began (its training stage done)
  until grep -q "^sweep: " "$base/c$1/sweep.log" 2>/dev/null; do
    kill -0 "$2" 2>/dev/null || { echo "sweep_split: chain $1 ended before its sweep began ($base/c$1.log)"; return 1; }
    sleep 2
  done
}
chain 0 "${chains[0]}" &
first=$!
started 0 $first || exit 1
echo "sweep_split: trained at $(date +%H:%M:%S)"
pids=($first)
status=0
for i in $(seq 1 $((${#chains[@]} - 1))); do
  for s in $(tr , ' ' <<< "${chains[$i]#*:}"); do
    mkdir -p "$R/sweep/$s/study"
    cp "$R/study/truth.json" "$R/study/judged.json" "$R/sweep/$s/study/"
  done
  chain "$i" "${chains[$i]}" &
  pids+=($!)
  # One at a time through the training stage: each chain's `bwm train --resume auto` (nothing
  # left to train) takes the run folder's lock, which a second one at the same moment is refused.
  started "$i" $! || status=1
done
for p in "${pids[@]}"; do wait "$p" || status=1; done
echo "sweep_split: done at $(date +%H:%M:%S) (status $status)"
exit $status
