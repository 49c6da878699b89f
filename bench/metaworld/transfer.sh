#!/usr/bin/env bash
# The value of a base model: a world model trained on one Meta-World task (the base), then
# post-trained onto a task it never saw from a few episodes, in full and with LoRA adapters,
# against a model trained from scratch on the same episodes for the same steps; `bwm fidelity`
# of each on the new task's held-out episodes (copy-last-frame beside).
#   base      recipe.sh data vae latents train with TASKS=$BASE_TASK (the VAE on $RUN/data/vae:
#             both tasks, seeds 50000.., so that it can draw the new task; no DiT sees them)
#   target    recipe.sh data latents with TASKS=$TARGET_TASK, TRAIN_EPISODES=$TARGET_EPISODES,
#             encoded with the base's VAE
#   full / lora / scratch   bwm train on the target cache for $POST_STEPS steps from the base's
#             last checkpoint (all weights, or LoRA rank $LORA_RANK on every attention and FFN
#             linear with the action encoder trained in full) or from random weights
#   fidelity  recipe.sh fidelity of each arm
#   study     (CLOSED_LOOP=1, the default) each arm through the evaluator on the new task: one
#             truth and one judge for all (recipe.sh truth judge in $RUN/target, the judge learning
#             from $RUN/data/vae, the episodes no DiT sees, and their round trips through the VAE),
#             then recipe.sh study of each arm on TRANSFER_VARIANTS (default: the test families'
#             variants) from that truth and the judge's verdicts: Pearson r, MAE, invented / missed
#   report    $RUN/transfer.json (each arm's open loop and closed loop) and a table on stdout
# Usage (repository root): bash bench/metaworld/transfer.sh; the recipe's variables apply
# (RESOLUTION, WORKERS, DEVICE, PYTHON, BWM, VAL_EPISODES, TRAIN_SETS of the base, STUDY_EPISODES,
# JUDGE_STEPS, ...). Every step is skipped when its output exists.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
T="${RUN:-runs/transfer}"
BASE_TASK="${BASE_TASK:-button-press-topdown-v3}"
TARGET_TASK="${TARGET_TASK:-drawer-open-v3}"
TARGET_EPISODES="${TARGET_EPISODES:-20}"
VAE_TASK_EPISODES="${VAE_TASK_EPISODES:-100}"
POST_STEPS="${POST_STEPS:-1500}"
LORA_RANK="${LORA_RANK:-32}"
ARMS="${ARMS:-full lora scratch}"
CLOSED_LOOP="${CLOSED_LOOP:-1}"
case "$CLOSED_LOOP" in 0|1) ;; *) echo "transfer: CLOSED_LOOP must be 0 or 1, not '$CLOSED_LOOP'" >&2; exit 2 ;; esac
export PYTHON="${PYTHON:-python3}" BWM="${BWM:-${CARGO_TARGET_DIR:-target}/release/bwm}" DEVICE="${DEVICE:-cuda}"
RESOLUTION="${RESOLUTION:-128}"
WORKERS="${WORKERS:-$(nproc)}"
export RESOLUTION WORKERS
recipe() { bash bench/metaworld/recipe.sh "$@"; }
mkdir -p "$T/data"

if [ ! -f "$T/data/vae/meta/info.json" ]; then
  "$PYTHON" bench/metaworld/generate.py --tasks "$BASE_TASK,$TARGET_TASK" --episodes "$VAE_TASK_EPISODES" --seed-start 50000 \
    --frames "${FRAMES:-120}" --resolution "$RESOLUTION" --workers "$WORKERS" --out "$T/data/vae"
fi
RUN="$T/base" TASKS="$BASE_TASK" VAE_DATA="$T/data/vae" VAE_EPISODES=$((2 * VAE_TASK_EPISODES)) recipe data vae latents train
mkdir -p "$T/target"
ln -sfn ../base/vae.safetensors "$T/target/vae.safetensors"
RUN="$T/target" TASKS="$TARGET_TASK" TRAIN_EPISODES="$TARGET_EPISODES" recipe data latents

if [ "$CLOSED_LOOP" = 1 ]; then
  variants=${TRANSFER_VARIANTS:-$("$PYTHON" bench/metaworld/families.py --list test)}
  # The truth of the new task's policies and a judge of its outcomes, made once for every arm.
  RUN="$T/target" TASKS="$TARGET_TASK" JUDGE_DATA="$T/data/vae" STUDY_VARIANTS="$variants" recipe truth judge
fi

base_ckpt="$T/base/checkpoints/$(cat "$T/base/checkpoints/latest")"
holdout=$("$PYTHON" -c 'import json, sys; print(int((json.load(open(sys.argv[1])).get("plan") or {}).get("holdout_episodes", 0)))' "$T/target/latents/index.json")
for arm in $ARMS; do
  dir="$T/$arm"
  mkdir -p "$dir"
  for link in data latents; do ln -sfn "../target/$link" "$dir/$link"; done
  ln -sfn ../base/vae.safetensors "$dir/vae.safetensors"
  sets=(--set "run.out_dir=\"$dir\"" --set "run.device=\"$DEVICE\"" --set "data.latent_cache=\"$dir/latents\""
        --set "data.holdout_episodes=$holdout" --set "validation.vae=\"$dir/vae.safetensors\"" --set "train.steps=$POST_STEPS"
        --set "optim.warmup_steps=100" --set "checkpoint.every=$POST_STEPS"
        --set "model.dit.in_dim=${VAE_Z_DIM:-48}" --set "model.dit.out_dim=${VAE_Z_DIM:-48}")
  case "$arm" in
    full) sets+=(--set "model.init={from=\"bwm-checkpoint\", path=\"$base_ckpt\"}") ;;
    lora) sets+=(--set "model.init={from=\"bwm-checkpoint\", path=\"$base_ckpt\"}"
                 --set "model.lora={rank=$LORA_RANK, targets=[\"blocks.*.self_attn.*\", \"blocks.*.cross_attn.*\", \"blocks.*.ffn.*\"]}"
                 --set 'train.trainable=["*.lora_A.weight", "*.lora_B.weight", "action_encoder.*"]') ;;
    scratch) ;;
    *) echo "transfer: unknown arm '$arm' (full, lora, scratch)" >&2; exit 2 ;;
  esac
  set -f  # the settings may hold glob characters
  for kv in ${TRAIN_SETS:-}; do sets+=(--set "$kv"); done
  set +f
  trained=0; [ "$(cat "$dir/checkpoints/latest" 2>/dev/null)" = "$(printf 'step-%08d' "$POST_STEPS")" ] && trained=1
  # Run also where the arm is trained: `--resume auto` refuses a run of another model section or
  # trainable set (another base, rank or arm), and does nothing where the run is complete.
  t0=$(date +%s.%N)
  "$BWM" train --config configs/metaworld.toml "${sets[@]}" --resume auto
  [ "$trained" = 1 ] || awk -v n="train-$arm" -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%s\t%.1f\n", n, b - a }' | tee -a "$T/timings.tsv"
  RUN="$dir" recipe fidelity
  if [ "$CLOSED_LOOP" = 1 ]; then
    judge_file=$([ "${JUDGE_FRAMES:-reconstructed}" = real ] && echo judge.pt || echo judge-reconstructed.pt)
    ln -sfn "../target/$judge_file" "$dir/$judge_file"
    RUN="$dir" TASKS="$TARGET_TASK" STUDY_VARIANTS="$variants" STUDY_FROM="$T/target/study" recipe study
  fi
done

"$PYTHON" - "$T" $ARMS <<'PY'
import json, os, sys
sys.path.insert(0, "bench/metaworld")
from files import write_json
from realtime import closed_loop, number
root, arms = sys.argv[1], sys.argv[2:]
out, closed = {}, {}
for arm in arms:
    f = json.load(open(os.path.join(root, arm, "fidelity", "fidelity.json")))
    out[arm] = f["all"]["horizons"]
    p = os.path.join(root, arm, "study", "study.json")
    if os.path.isfile(p):
        closed[arm] = closed_loop(json.load(open(p)))
write_json(os.path.join(root, "transfer.json"), {**out, **({"closed_loop": closed} if closed else {})})
print("| arm | h | model PSNR (SSIM) | copy last frame | other actions |")
print("|---|---|---|---|---|")
for arm, hs in out.items():
    for h, v in sorted(hs.items(), key=lambda kv: int(kv[0]) if kv[0].isdigit() else 1 << 30):
        print(f"| {arm} | {h} | {v['model']['psnr']:.2f} ({v['model']['ssim']:.3f}) | {v['copy_last_frame']['psnr']:.2f} | {v['other_actions']['psnr']:.2f} |")
if closed:
    print("| arm | closed loop: Pearson r | Spearman | MAE | best first | invented / missed | per family r |")
    print("|---|---|---|---|---|---|---|")
    for arm, c in closed.items():
        fams = ", ".join(f"{k} {number(v).strip()}" for k, v in c["families"].items())
        print(f"| {arm} | {number(c['pearson_r']).strip()} | {number(c['spearman_rho']).strip()} | {c['mae']:.3f} | {c['best_ranked_first']} | {c['invented']} / {c['missed']} of {c['episodes']} | {fams} |")
print(f"transfer: {os.path.join(root, 'transfer.json')}")
PY
