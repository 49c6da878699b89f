#!/usr/bin/env bash
# On one GPU of a CUDA host, from the repo root, with the bwm binary copied there as
# scripts/gpu/pack.sh packs it (.pack/bwm.xz) and, for the reference, tests/reference/wheels: the
# real-time issue's 5B chunk, every setting and the reference in one run. One rollout chunk of the
# 5B world model at random weights (640x480, x0 + 8 history frames, 72 generated frames, bf16, the
# residual stream in bf16; CHUNKS chunks, default 3, the first with start-up costs) per word of
# SETTINGS, DECODER:STEPS (default "light:1 light:2 light:4 full:4 full:50"; empty: none; the light decoder of
# random weights, `--random-light-decoder`, or the VAE's decoder; Euler steps), through
# scripts/gpu/rollout.sh; then the DiffSynth reference's 50-step chunk (tests/reference/run_gpu.sh
# rollout; REFERENCE=0 leaves it out) and each setting's last chunk against it, with its generated
# frames per second: $OUT/realtime_5b.txt. Then the step of step distillation for each student
# step count of DISTILL (default "1 2"; empty leaves it out) from the TEACHER_STEPS-step path
# (default 4): `bwm bench-train --distill K` (a frozen teacher of random weights, 1+8+72 frames at
# 640x480, batch 1, every block recomputed, STEPS steps, default 5, the median of those after the
# first) for each word of WEIGHTS (default "lora full"): with the LoRA guide's rank-64 adapters, and
# with full weights where the GPU holds 120 GB or more (full fine-tuning alone needs 97,777 MiB):
# its time and peak memory, also in
# realtime_5b.txt. Logs: $OUT/roll-DECODER-sSTEPS.log, reference-rollout.log,
# distill-{lora,full}-sK.log.
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
settings=${SETTINGS-light:1 light:2 light:4 full:4 full:50}
for s in $settings; do
  case "${s%%:*}" in light | full) ;; *) echo "realtime_5b: '$s': the decoder is light or full" >&2; exit 2 ;; esac
  [[ ${s#*:} =~ ^[1-9][0-9]*$ ]] || { echo "realtime_5b: '$s': the steps are a positive whole number" >&2; exit 2; }
done
students=${DISTILL-1 2} teacher_steps=${TEACHER_STEPS:-4}
for k in $students; do
  [[ $k =~ ^[1-9][0-9]*$ ]] && [ $((teacher_steps % k)) = 0 ] ||
    { echo "realtime_5b: DISTILL '$k': a student's steps divide the teacher's $teacher_steps (TEACHER_STEPS)" >&2; exit 2; }
done
for w in ${WEIGHTS:-lora full}; do
  case "$w" in lora | full) ;; *) echo "realtime_5b: WEIGHTS '$w': lora or full" >&2; exit 2 ;; esac
done
unpack .pack/bwm.xz dist/bwm || exit 1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
status=0
for s in $settings; do
  decoder=${s%%:*} steps=${s#*:}
  CHUNKS=${CHUNKS:-3} RESIDUAL=model SAMPLE_STEPS=$steps LIGHT=$([ "$decoder" = light ] && echo 1 || echo 0) \
    LOG="roll-$decoder-s$steps" bash "$(dirname "${BASH_SOURCE[0]}")/rollout.sh" || status=1
done
ref=
if [ "${REFERENCE:-1}" = 1 ]; then
  bash tests/reference/run_gpu.sh rollout || status=1
  ref=$(sed -n 's/^reference rollout: \([0-9.]*\) s per chunk.*/\1/p' "$OUT/reference-rollout.log" 2>/dev/null | head -1)
  [ -n "$ref" ] || { echo "realtime_5b: no reference chunk timed ($OUT/reference-rollout.log)"; status=1; }
fi
for s in $settings; do
  decoder=${s%%:*} steps=${s#*:}
  # The last timed chunk: "chunk N: T s = encode E s + DiT D s (X s/step) + decode C s; F frames; G generated frames/s; ..."
  line=$(grep '^chunk [0-9]*: [0-9.]* s = ' "$OUT/roll-$decoder-s$steps.log" 2>/dev/null | tail -1)
  chunk=$(sed -n 's/^chunk [0-9]*: \([0-9.]*\) s = .*/\1/p' <<< "$line")
  if [ -z "$chunk" ]; then
    echo "realtime_5b: $decoder decoder, $steps steps: no chunk timed ($OUT/roll-$decoder-s$steps.log)"
    status=1
    continue
  fi
  parts=$(sed -n 's/^chunk [0-9]*: [0-9.]* s = \(encode [0-9.]* s + DiT [0-9.]* s\) ([0-9.]* s\/step) + \(decode [0-9.]* s\); [0-9]* frames; \([0-9.]*\) generated frames\/s.*/\1 + \2; \3 generated frames\/s/p' <<< "$line")
  against=
  [ -z "$ref" ] || against=", the reference's 50-step chunk $ref s: $(awk -v a="$ref" -v b="$chunk" 'BEGIN { printf "%.2f", a / b }')x"
  echo "realtime_5b: $decoder decoder, $steps steps: $chunk s per chunk ($parts)$against"
done | tee "$OUT/realtime_5b.txt"
grep -q "no chunk timed" "$OUT/realtime_5b.txt" && status=1
gpu_mib=$(nvidia-smi --query-gpu=memory.total --format=csv,noheader,nounits | head -1)
for k in $students; do
  for weights in ${WEIGHTS:-lora full}; do
    if [ $weights = full ] && [ "${gpu_mib:-0}" -lt 120000 ]; then
      echo "realtime_5b: distillation, full weights, a student of $k step(s): not run, the GPU holds ${gpu_mib:-no} MiB (full fine-tuning alone needs 97,777 MiB)"
      continue
    fi
    log=distill-$weights-s$k
    sets=(--set 'run.device="cuda"' --set train.grad_accum=1 --set train.recompute=true)
    [ $weights = lora ] && sets+=("${LORA64[@]}")
    mem "$log" dist/bwm bench-train --config configs/bwm-wan22-ti2v-5b.toml "${sets[@]}" --steps "${STEPS:-5}" \
      --distill "$k" --teacher-substeps $((teacher_steps / k)) --out "/tmp/bench-$log" > /dev/null
    read -r median half n <<< "$(second_half_median s/step "$OUT/$log.log")"
    peak=$(sed -n 's/^.*: peak GPU memory used \([0-9]*\) MiB.*/\1/p' "$OUT/$log.log" | tail -1)
    if [ "$median" = none ] || [ "$n" -lt 2 ]; then
      echo "realtime_5b: distillation, $weights weights, a student of $k step(s): no step timed ($OUT/$log.log)"
      continue
    fi
    echo "realtime_5b: distillation, $([ $weights = lora ] && echo "LoRA rank 64" || echo "full weights"), a student of $k step(s) from the teacher's $teacher_steps: $median s per step (median of the last $half of $n), peak GPU memory ${peak:-unknown} MiB"
  done
done | tee -a "$OUT/realtime_5b.txt"
grep -q "no step timed" "$OUT/realtime_5b.txt" && status=1
exit $status
