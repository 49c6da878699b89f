# Sourced by the GPU scripts: $OUT, libtorch on LD_LIBRARY_PATH, NVLink multicast off, every
# optional dependency of a test required, `mem`, and the 5B's LoRA of the LoRA guide (LORA64).
OUT="${OUT:-/tmp/out}"; mkdir -p "$OUT"
# A test run here that asks bwm_testdir for CUDA, NCCL or anything else fails where it is missing
# instead of being skipped (testdir/src/optional.rs): a GPU machine is where those are checked.
export BWM_REQUIRE=all
TL=$(python3 -c 'import torch,os;print(os.path.dirname(torch.__file__))')/lib
export LD_LIBRARY_PATH=$TL:${LD_LIBRARY_PATH:-} NCCL_NVLS_ENABLE=0
mem() { # $1 = log name; samples used memory every 50 ms while the rest of the arguments run, and
  # returns their exit status. A command that fails is named on its memory line and in $mem_failed,
  # and the script that sourced this file then exits 1 (the trap below) even where it measures on.
  local log=$1; shift
  # nvidia-smi sees every GPU of the host whatever CUDA_VISIBLE_DEVICES says: sample the first visible one.
  local gpu=(); [[ "${CUDA_VISIBLE_DEVICES:-}" =~ ^[0-9]+ ]] && gpu=(-i "${BASH_REMATCH[0]}")
  nvidia-smi "${gpu[@]}" --query-gpu=memory.used --format=csv,noheader,nounits -lms 50 > "$OUT/$log.mem" &
  local pid=$!
  "$@" 2>&1 | tee "$OUT/$log.log"
  local rc=${PIPESTATUS[0]}
  kill $pid 2>/dev/null
  local base; base=$(head -1 "$OUT/$log.mem")
  local peak; peak=$(sort -n "$OUT/$log.mem" | tail -1)
  local failed=
  if [ "$rc" != 0 ]; then failed="FAILED (exit status $rc); "; mem_failed="${mem_failed:-}${mem_failed:+ }$log"; fi
  echo "$log: ${failed}peak GPU memory used ${peak} MiB (baseline ${base} MiB before the process)" | tee -a "$OUT/$log.log"
  return "$rc"
}
mem_failed=
trap 'rc=$?; if [ "$rc" = 0 ] && [ -n "$mem_failed" ]; then echo "failed: $mem_failed (their logs in $OUT)" >&2; exit 1; fi' EXIT
second_half_median() { # $1 = a figure's unit in a log (s/step, samples/s), $2 = the log: "MEDIAN HALF N", the
  # median of the figure over the last HALF of its N values (the steps after warm-up; "none" without any)
  local n half
  n=$(awk -v u="$1" '{ for (i = 1; i < NF; i++) if ($(i+1) == u) n++ } END { print n + 0 }' "$2")
  half=$(( (n + 1) / 2 ))
  awk -v u="$1" '{ for (i = 1; i < NF; i++) if ($(i+1) == u) print $i }' "$2" | tail -n "$half" | sort -g \
    | awk -v half="$half" -v n="$n" '{ v[NR] = $1 } END { print (NR ? v[int((NR + 1) / 2)] : "none"), half, n }'
}
unpack() { # $1 = an xz-packed executable (.pack/bwm.xz), $2 = where it goes (dist/bwm). Unpacked beside
  # and renamed into place: writing over a binary that another script on the host is running fails
  # ("Text file busy"), a rename does not.
  mkdir -p "$(dirname "$2")" && xz -dc "$1" > "$2.$$" && chmod +x "$2.$$" && mv -f "$2.$$" "$2" ||
    { rm -f "$2.$$"; echo "cannot unpack $1 into $2" >&2; return 1; }
}
# bench-train's overrides for the 5B with LoRA rank 64 on every attention and FFN linear (the README's
# LoRA guide: adapters and the action encoder trained, the base frozen in bf16).
LORA64=(--set 'model.lora={rank=64, targets=["blocks.*.self_attn.*", "blocks.*.cross_attn.*", "blocks.*.ffn.*"]}'
        --set 'train.trainable=["*.lora_A.weight", "*.lora_B.weight", "action_encoder.*"]')
