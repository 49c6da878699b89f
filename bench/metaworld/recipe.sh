#!/usr/bin/env bash
# A Meta-World world model from scratch on one GPU, through the product's own commands:
#   data     bench/metaworld/generate.py: training and held-out LeRobot datasets (both tasks)
#   vae      bwm train-vae: a small Wan2.2-architecture VAE on the training frames
#   latents  bwm prepare: the latent cache (x0 + 8 history + 24 future frames, stride 4)
#   train    bwm train --config configs/metaworld.toml
#   fidelity bwm fidelity on the held-out episodes (FIDELITY_EPISODES: some): $FIDELITY_DIR, default $RUN/fidelity/ (JSON, curves, videos)
#   truth    bench/metaworld/study.py --truth-only: each policy variant's true success rate in the
#            simulator on the held-out placements (CPU; $RUN/study/truth.json)
#   judge    bench/metaworld/judge.py: per task, a regressor of the object's distance to its goal
#            (Meta-World's obj_to_target; success by the simulator's own rule on it) learned from
#            the simulator's frames and, by
#            default (JUDGE_FRAMES=reconstructed), on training frames after a round trip through
#            this run's VAE (bwm reconstruct; after the vae stage), scored on real held-out frames:
#            $JUDGE; then the judge on the simulator's frames of the study's episodes
#            ($STUDY_DIR/judged.json, for the study)
#   ceiling  bwm reconstruct + judge.py score: the judge on the held-out frames after a round trip
#            through the VAE, i.e. what it concludes from a perfect world model's frames:
#            $RUN/ceiling/judge-reconstructed.json (judge.json for JUDGE_FRAMES=real's)
#   study    bench/metaworld/study.py: every policy variant through `bwm evaluate` against its true
#            success rate in the simulator, and the judge on the simulator's own frames of the same
#            episodes: $RUN/study/ (study.json, study.csv, study.svg, judged.json)
#   teacher  bench/metaworld/teacher.py: each chunk of the study's episodes drawn by the world model
#            from the simulator's own history frames and judged beside the simulator's chunk: does
#            the model draw a command's outcome wrongly from real frames, or only from its own?
#            $RUN/teacher/teacher.json
#   own      the same teacher forcing over the datasets' own episodes (teacher.py --own-episodes): the
#            first OWN_EPISODES per task of behaviours OWN_BEHAVIOURS (default: `near`, steered off the object) of
#            the training set and of the held-out set, drawn from their real history, judged beside
#            their real chunks, and mapped by the hand's closest approach (contact_map.py): did the
#            world model learn the outcomes it was trained on, and do they hold on unseen placements?
#            $RUN/own/{train,val}/ (teacher.json, contact_map.json)
#   probe    the same study over graded `wrong-<d>cm` variants (the expert with its targets moved d
#            cm along the task's `wrong` offset): does the model's contact follow a shifted
#            command as the simulator's does? $RUN/probe/ (same files as study/)
#   light    (only when named) the realtime stage's light decoder alone (bwm train-light-decoder,
#            from the VAE and the training data: it can train beside the world model), kept by the
#            realtime stage when made the same way: $REALTIME_DIR/light-decoder.safetensors
#   realtime (only when named) cheaper sampling measured against the full path: a light decoder
#            (bwm train-light-decoder) and students distilled from the trained model for 1 and 2
#            steps ([distill], REALTIME_STUDENTS), then the teacher at REALTIME_TEACHER_STEPS (the
#            first, default 50, with the VAE's decoder the reference) and each student, each decoded
#            by the VAE's decoder (-full) and by the light one (-light): the open loop of the first
#            REALTIME_EPISODES held-out episodes (agreement.py, PSNR at h = 32 against the reference
#            and the recorded frames) and, for REALTIME_STUDIES (the teacher's with the VAE's
#            decoder while the others train, then the rest beside the others' rollouts, each group
#            in its order), the study on the test families; $REALTIME_DIR (default $RUN/realtime/:
#            light-decoder.safetensors, student-K/, roll/SETTING/, study-SETTING/, agreement.json,
#            realtime.json)
#   engine   (only when named) the data engine measured, bench/metaworld/engine.py: the expert's
#            commands planned from the first frame of new placements, drawn by `bwm rollout`, and
#            behaviour-cloned policies trained on N real demonstrations with and without them
#            (those the judge calls successes, or all), run in the simulator: $ENGINE_DIR
#            (default $RUN/engine/: plan/, generated/, engine.json); ENGINE_SEEDS,
#            ENGINE_GENERATED, ENGINE_DEMOS, ENGINE_EPISODES, ENGINE_NET_STEPS size it
# Usage (repository root): bash bench/metaworld/recipe.sh [STAGE ...]   (default: all)
# A stage whose output exists keeps it only when it was made by the same command from the same
# inputs (the data: generate.py --reuse; the VAE, latent cache, judge, the held-out round trip and
# the teacher and own reports: a record beside each, OUTPUT.recipe) and refuses it otherwise,
# naming what differs; an output from before the records is kept with a warning. `train` resumes
# from its last checkpoint (bwm train checks the settings) when its latent cache and VAE are those
# it started from.
# Environment: RUN (output folder, default runs/metaworld), BWM (the bwm binary, default
# $CARGO_TARGET_DIR/release/bwm or target/release/bwm), PYTHON (with bench/metaworld's
# requirements), DEVICE (default cuda), and the sizes below. Stage times go to TIMINGS (default
# $RUN/timings.tsv).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
RUN="${RUN:-runs/metaworld}"
TIMINGS="${TIMINGS:-$RUN/timings.tsv}"
BWM="${BWM:-${CARGO_TARGET_DIR:-target}/release/bwm}"
PYTHON="${PYTHON:-python3}"
DEVICE="${DEVICE:-cuda}"
# The data's variables (TASKS ... RESOLUTION), shared with scripts/gpu/variants.sh.
source bench/metaworld/data-settings.sh || exit 2
WORKERS="${WORKERS:-$(nproc)}"
VAE_STEPS="${VAE_STEPS:-1200}"
VAE_EPISODES="${VAE_EPISODES:-200}"
VAE_DATA="${VAE_DATA:-$RUN/data/train}"   # the dataset the VAE trains on
VAE_BATCH="${VAE_BATCH:-4}"
VAE_LR="${VAE_LR:-1e-3}"
VAE_DTYPE="${VAE_DTYPE:-f32}"             # bwm train-vae --dtype: f32, or bf16 with fp32 masters (slower here: docs/performance.md)
VAE_LOSS="${VAE_LOSS:-mse}"                # bwm train-vae --recon-loss: mse or l1
# 1: bwm train-vae --cuda-graph (the step replayed from a CUDA graph: 1.8x faster on an H200,
# docs/performance.md); 0: eager; auto (default): the graph on CUDA devices, and should the graph
# fail, the VAE trained again eagerly (a CPU has no CUDA graphs: eager there).
VAE_GRAPH="${VAE_GRAPH:-auto}"
case "$VAE_GRAPH" in 0|1|auto) ;; *) echo "recipe: VAE_GRAPH must be 0, 1 or auto, not '$VAE_GRAPH'" >&2; exit 2 ;; esac
VAE_EVAL_EVERY="${VAE_EVAL_EVERY:-1000}"  # held-out reconstruction PSNR every N VAE steps (and at the end)
# The VAE trains on clips as long as the DiT's (x0 + 8 + 24 = 33 frames): its causal convolutions
# see the video's start in every 9-frame clip, and one trained on those decodes the later latents
# of a 33-frame clip poorly (docs/fidelity.md at abaed68, runs 10 and 11).
VAE_CLIP_FRAMES="${VAE_CLIP_FRAMES:-33}"  # frames per VAE training clip (1+4k)
# Share of each VAE episode held out for its PSNR; default: enough frames for one clip.
VAE_HOLDOUT_TAIL="${VAE_HOLDOUT_TAIL:-$(awk -v c="$VAE_CLIP_FRAMES" -v f="$FRAMES" 'BEGIN { t = int(100 * (c + 2) / f + 0.999) / 100; print (t < 0.1 ? 0.1 : t) }')}"
VAE_STRIDE="${VAE_STRIDE:-16}"           # pixels per latent cell: 16 or 8
VAE_DIM="${VAE_DIM:-32}"                 # bwm train-vae --dim: the encoder's base width
VAE_DEC_DIM="${VAE_DEC_DIM:-32}"         # bwm train-vae --dec-dim: the decoder's base width
VAE_SEED="${VAE_SEED:-0}"                # bwm train-vae --seed: initial weights and clip order
# bwm train-vae --candidates: VAEs trained from seeds VAE_SEED, VAE_SEED + 1, ..., the best held-out
# PSNR kept. One seed in four settled about 1 dB under the others in every run, and the world model
# on its latents reached r 0.64-0.70 where the others reached 0.78-0.91 (docs/fidelity.md at
# abaed68, run 31). 2 on CUDA devices (with VAE_GRAPH's graphed steps two cost less than one eager
# VAE; eager, as after a graph's failure, they cost about 1.3 times one), 1 elsewhere.
VAE_CANDIDATES="${VAE_CANDIDATES:-$([[ $DEVICE == cuda* ]] && echo 2 || echo 1)}"
# bwm train-vae --choose-at: the candidates' steps before the best goes on alone (the poor seed's
# gap showed early in run 27's training losses: 2.3 dB under the others around step 200, 1.1
# around 400, 1.0 around 600; held out 1.1 at 1000); empty: every candidate trains in full.
VAE_CHOOSE_AT="${VAE_CHOOSE_AT-400}"
VAE_Z_DIM="${VAE_Z_DIM:-48}"             # bwm train-vae --z-dim: latent channels (the DiT's in_dim and out_dim follow)
KEEP_FRAMES="${KEEP_FRAMES:-0}"          # 1: the latent cache also keeps pixel frames (training's validation scores against them; 23 GB at 128x128)
TRAIN_STEPS="${TRAIN_STEPS:-}"            # default: configs/metaworld.toml's
TRAIN_SETS="${TRAIN_SETS:-}"              # more `--set KEY=VALUE` for bwm train, space-separated
# The DiT's weights averaged over its training (optim.ema_decay, e.g. 0.999: about the last 1000
# steps); every stage that rolls out then uses the average of the newest checkpoint (bwm export
# --ema into $RUN/ema/STEP), not its last step's weights. Empty (default): no average. At 0.999 the
# average drew the drawer worse than the last step (docs/fidelity.md at abaed68, run 36).
EMA_DECAY="${EMA_DECAY:-}"
SAMPLE_STEPS="${SAMPLE_STEPS:-4}"         # sampler steps per generated chunk (the sweep's pick, docs/fidelity.md, "The sampler: 4 Euler steps")
SOLVER="${SOLVER:-euler}"                 # euler or dpm++2m (bwm --solver)
FP8="${FP8:-}"                            # tensor or row: the DiT blocks' linears in FP8 (bwm --fp8); default off
SAMPLER_GRAPH="${SAMPLER_GRAPH:-0}"       # 1: the sampler's forward pass replayed from CUDA graphs (bwm --cuda-graph)
                                          # in the fidelity, study, teacher and probe stages; CUDA only
case "$SAMPLER_GRAPH" in 0|1) ;; *) echo "recipe: SAMPLER_GRAPH must be 0 or 1, not '$SAMPLER_GRAPH'" >&2; exit 2 ;; esac
HISTORY_SIGMA="${HISTORY_SIGMA:-}"        # bwm --history-sigma when sampling: the history latents' noise level (empty: the
                                          # level the DiT trained with; 0: clean history)
SAMPLE_SEED="${SAMPLE_SEED:-0}"           # bwm --seed when sampling: the sampler's noise (another draw of the same episodes)
GUIDANCE="${GUIDANCE:-1}"                 # bwm --guidance: classifier-free guidance by the actions (1 = off; other
                                          # values need TRAIN_SETS=objective.action_dropout=P with P > 0)
JUDGE_STEPS="${JUDGE_STEPS:-600}"
JUDGE_FRAMES="${JUDGE_FRAMES:-reconstructed}"  # what the judge learns from: reconstructed (the simulator's frames and
                                          # training frames through this run's VAE) or real (the former alone; it misreads
                                          # some VAEs' open drawer as closed: docs/fidelity.md at abaed68, runs 25 and 26)
JUDGE_DATA="${JUDGE_DATA:-$RUN/data/train}"  # the simulator's episodes the judge learns from (and their round trips)
JUDGE_RECONSTRUCT_EPISODES="${JUDGE_RECONSTRUCT_EPISODES:-400}"  # training episodes reconstructed for it (the first: both tasks, seeds interleaved)
case "$JUDGE_FRAMES" in
  real) JUDGE_NAME=judge ;;
  reconstructed) JUDGE_NAME=judge-reconstructed ;;
  *) echo "recipe: JUDGE_FRAMES must be real or reconstructed, not '$JUDGE_FRAMES'" >&2; exit 2 ;;
esac
JUDGE="$RUN/$JUDGE_NAME.pt"
STUDY_EPISODES="${STUDY_EPISODES:-50}"    # per task and variant, the first held-out episodes
STUDY_JOBS="${STUDY_JOBS:-8}"             # bwm evaluate processes at once
STUDY_IN_FLIGHT="${STUDY_IN_FLIGHT:-16}"  # episodes each of them runs at once (one batch per chunk)
STUDY_STREAMS="${STUDY_STREAMS:-1}"       # lanes each splits them into, on CUDA streams of their own (bwm evaluate --streams)
STUDY_HORIZON="${STUDY_HORIZON:-$FRAMES}" # frames after x0, in the simulator and the world model
STUDY_VARIANTS="${STUDY_VARIANTS:-}"      # comma-separated (default: all)
STUDY_DIR="${STUDY_DIR:-$RUN/study}"      # where the study writes (another, to compare sampler settings)
# A study folder of the same episodes and variants whose truth and judged episodes the study starts
# from (copied where STUDY_DIR has none): another setting of the same model, or another model on
# the same task, costs no second truth or judging (study.py measures a copy again if its key differs).
STUDY_FROM="${STUDY_FROM:-}"
FIDELITY_DIR="${FIDELITY_DIR:-$RUN/fidelity}"  # where the fidelity report goes
FIDELITY_EPISODES="${FIDELITY_EPISODES:-}" # comma-separated positions in data/val (default: all)
FIDELITY_IN_FLIGHT="${FIDELITY_IN_FLIGHT:-8}" # episodes rolled out at once (one batch per chunk)
FIDELITY_STREAMS="${FIDELITY_STREAMS:-1}"     # lanes they are split into, on CUDA streams of their own (bwm fidelity --streams)
PROBE_VARIANTS="${PROBE_VARIANTS:-wrong-0cm,wrong-1cm,wrong-2cm,wrong-3cm,wrong-4cm,wrong-5cm,wrong-6cm}"
TEACHER_VARIANTS="${TEACHER_VARIANTS:-$STUDY_VARIANTS}"  # the teacher stage's variants (default: the study's)
OWN_BEHAVIOURS="${OWN_BEHAVIOURS-near}"   # the own stage's generator behaviours, comma-separated (empty: all)
OWN_EPISODES="${OWN_EPISODES:-400}"       # the own stage's episodes per task and dataset (the first of those behaviours)
REALTIME_DIR="${REALTIME_DIR:-$RUN/realtime}"  # where the realtime stage writes
REALTIME_TEACHER_STEPS="${REALTIME_TEACHER_STEPS:-50 4 2 1}"  # the teacher's sampler steps measured; the first is the reference's
REALTIME_STUDENTS="${REALTIME_STUDENTS-1 2}"  # students distilled, by their sampler steps (each from the teacher's SAMPLE_STEPS-step path)
REALTIME_STUDENT_STEPS="${REALTIME_STUDENT_STEPS:-1000}"  # each student's training steps (of the recipe's batch)
REALTIME_STUDENT_LR="${REALTIME_STUDENT_LR:-1e-4}"
LIGHT_STEPS="${LIGHT_STEPS:-2000}"         # the light decoder's training steps (clips of VAE_CLIP_FRAMES frames)
LIGHT_BATCH="${LIGHT_BATCH:-4}"
LIGHT_LR="${LIGHT_LR:-2e-3}"
REALTIME_EPISODES="${REALTIME_EPISODES:-20}"  # open loop: the first N held-out episodes (the tasks interleaved)
REALTIME_IN_FLIGHT="${REALTIME_IN_FLIGHT:-$REALTIME_EPISODES}"  # open loop: episodes rolled out at once (default: all, one batch per chunk)
REALTIME_VARIANTS="${REALTIME_VARIANTS:-}"   # the closed loop's variants, comma-separated (default: the test families')
# Settings studied in closed loop on the test families (t<steps>-<full|light>, s<steps>-<full|light>), the
# reference among them; the teacher's with the VAE's decoder first (while the others train), each group
# in this order; all: every setting; empty: none.
REALTIME_STUDIES="${REALTIME_STUDIES-all}"
ENGINE_DIR="${ENGINE_DIR:-$RUN/engine}"   # where the engine stage writes
ENGINE_SEEDS="${ENGINE_SEEDS:-3}"         # data seeds: each its own real and generated placements and network seed
ENGINE_GENERATED="${ENGINE_GENERATED:-16}"  # generated episodes per task and data seed (M)
ENGINE_DEMOS="${ENGINE_DEMOS:-2,4,8}"     # real demonstration counts N
ENGINE_EPISODES="${ENGINE_EPISODES:-100}" # simulator episodes per cloned policy
ENGINE_NET_STEPS="${ENGINE_NET_STEPS:-}"  # the cloned network's training steps (default: families.py's NET_STEPS)
ENGINE_IN_FLIGHT="${ENGINE_IN_FLIGHT:-16}"  # generated episodes rolled out at once
STAGES=()
for arg in "$@"; do
  case "$arg" in
    data|vae|latents|train|fidelity|truth|judge|ceiling|study|teacher|own|probe|light|realtime|engine) STAGES+=("$arg") ;;
    *) echo "recipe: unknown stage '$arg' (stages: data vae latents train fidelity truth judge ceiling study teacher own probe light realtime engine)" >&2; exit 2 ;;
  esac
done
[ ${#STAGES[@]} -gt 0 ] || STAGES=(data vae latents train fidelity truth judge ceiling study teacher own probe)
[ -x "$BWM" ] || { echo "recipe: no bwm binary at $BWM (make build, or set BWM)" >&2; exit 1; }
mkdir -p "$RUN"
wants() { [[ " ${STAGES[*]} " == *" $1 "* ]]; }
stop_tree() { # $@ = pids: each stopped with every process it started (a stage's background
  local p       # subshells run `bwm` and python as children, which outlive a subshell killed alone)
  for p in "$@"; do
    stop_tree $(pgrep -P "$p" 2>/dev/null)
    kill "$p" 2>/dev/null
  done
  return 0
}

# A stage's commands run in a `||` context, where `set -e` does not stop them: a stage function
# must return its first failure itself (`|| return 1`).
timed() { # $1 = stage name; the rest runs, its wall time appended to $TIMINGS (as NAME-failed when it fails)
  local name=$1 t0 status=0; shift
  t0=$(date +%s.%N)
  echo "recipe: $name ($(date +%T))"
  "$@" || status=$?
  [ "$status" = 0 ] || name="$name-failed"
  awk -v n="$name" -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%s\t%.1f\n", n, b - a }' | tee -a "$TIMINGS"
  return "$status"
}

# How an output was made, as its record holds it: the command's words (the program, devices,
# batch and worker counts and where it writes left out: none changes what it makes), each input
# it names followed by that input's sha256 (an input made by an earlier stage: of its record,
# whose last line says when it was made, so an input made again, even alike, is a new input; any
# other file: of its bytes; a dataset: of its meta/ files; a checkpoint: of its weights). Code
# (*.py, the bwm binary) is not an input.
not_in_record() { # $1 = a flag whose value changes nothing the command makes (or names the program)
  case "$1" in --device|--judge-device|--workers|--jobs|--episodes-in-flight|--streams|--batch|--out|--bwm) return 0 ;; esac
  return 1
}
record_of() { # the command's words, its program first; one line per flag with its values
  local prev=$1 w id line=
  shift
  for w in "$@"; do
    if not_in_record "$w" || not_in_record "$prev"; then prev=$w; continue; fi
    id=
    if [ "$prev" != --reconstructed ] && [[ $w != *.py ]]; then
      if [ -f "$w.recipe" ]; then id=$(sha256sum < "$w.recipe")
      elif [ -f "$w" ]; then id=$(sha256sum < "$w")
      elif [ -d "$w/meta" ]; then id=$(find "$w/meta" -maxdepth 1 -type f -print0 | sort -z | xargs -0 cat | sha256sum)
      elif [ -f "$w/model.safetensors" ]; then id=$(sha256sum < "$w/model.safetensors")
      fi
    fi
    prev=$w
    [ -z "$id" ] || w="$w (sha256 ${id%% *})"
    if [[ $w =~ ^--?[A-Za-z] || $w == -- ]]; then [ -z "$line" ] || echo "$line"; line=$w; else line="${line:+$line }$w"; fi
  done
  [ -z "$line" ] || echo "$line"
}
# 0 when OUTPUT exists and its record is RECORD (kept); 1 when OUTPUT is to be made; exits 2 when
# OUTPUT was made otherwise.
kept() { # $1 = output, $2 = the record it must have
  local out=$1 want=$2 there
  [ -e "$out" ] || return 1
  if [ ! -f "$out.recipe" ]; then
    echo "recipe: $out exists and has no record of how it was made (made before the recipe kept records); kept" >&2
    return 0
  fi
  there=$(grep -v '^made ' "$out.recipe")
  if [ "$there" = "$want" ]; then
    echo "recipe: $out exists, made with these settings from these inputs; kept" >&2
    return 0
  fi
  echo "recipe: $out exists but was made otherwise (its record $out.recipe); remove it, and what was made from it, or pick another RUN:" >&2
  diff <(printf '%s\n' "$there") <(printf '%s\n' "$want") | sed -n 's/^< /  there: /p; s/^> /  now:   /p' >&2
  exit 2
}
recorded() { # $1 = output, $2 = its record
  printf '%s\nmade %s %s\n' "$2" "$(date -u +%FT%T.%NZ)" "$RANDOM$RANDOM" > "$1.recipe.tmp" && mv -f "$1.recipe.tmp" "$1.recipe"
}

# The EMA weights of a checkpoint (EMA_DECAY), exported once per checkpoint (its weights' sha256 in
# the export's record: a checkpoint trained again at the same step is exported again): under a
# lock, since stages that roll out may start side by side (scripts/gpu/metaworld-stages.sh).
ema_export() { # $1 = the checkpoint's folder name (step-NNNNNNNN)
  local export=("$BWM" export --checkpoint "$RUN/checkpoints/$1" --ema --dtype fp32 --out "$RUN/ema/$1") made_with
  made_with=$(record_of "${export[@]}")
  mkdir -p "$RUN/ema"
  (
    flock 9
    if [ -f "$RUN/ema/$1/config.json" ] && [ "$(grep -v '^made ' "$RUN/ema/$1.recipe" 2>/dev/null)" = "$made_with" ]; then exit 0; fi
    rm -rf "$RUN/ema/$1"
    timed ema "${export[@]}" && recorded "$RUN/ema/$1" "$made_with"
  ) 9> "$RUN/ema/.lock"
}

if wants data; then
  for split in train val; do
    if [ $split = train ]; then n=$TRAIN_EPISODES; s=0; else n=$VAL_EPISODES; s=$VAL_SEED_START; fi
    generate=("$PYTHON" bench/metaworld/generate.py --tasks "$TASKS" --episodes "$n" --seed-start "$s" \
      --frames "$FRAMES" --resolution "$RESOLUTION" ${MIX:+--mix "$MIX"} --observe-every "$OBSERVE_EVERY" --workers "$WORKERS" --out "$RUN/data/$split")
    # Existing data are kept only when made with these settings (the generator checks them).
    if [ -f "$RUN/data/$split/meta/info.json" ]; then "${generate[@]}" --reuse; continue; fi
    timed "data-$split" "${generate[@]}"
  done
fi

if wants vae; then
  vae=("$BWM" train-vae --data "$VAE_DATA" --max-episodes "$VAE_EPISODES" --holdout-tail "$VAE_HOLDOUT_TAIL"
      --resolution "${RESOLUTION}x$RESOLUTION" --dim "$VAE_DIM" --dec-dim "$VAE_DEC_DIM" --spatial-stride "$VAE_STRIDE" --clip-frames "$VAE_CLIP_FRAMES" --batch "$VAE_BATCH" --steps "$VAE_STEPS" --lr "$VAE_LR"
      --no-flip --eval-every "$VAE_EVAL_EVERY" --dtype "$VAE_DTYPE" --recon-loss "$VAE_LOSS" --seed "$VAE_SEED" --candidates "$VAE_CANDIDATES" ${VAE_CHOOSE_AT:+--choose-at "$VAE_CHOOSE_AT"} --z-dim "$VAE_Z_DIM" --device "$DEVICE" --out "$RUN/vae.safetensors")
  made_with=$(record_of "${vae[@]}")
  if ! kept "$RUN/vae.safetensors" "$made_with"; then
    if [ "$VAE_GRAPH" = 1 ]; then
      timed vae "${vae[@]}" --cuda-graph
    elif [ "$VAE_GRAPH" = auto ] && [[ $DEVICE == cuda* ]]; then
      # Only a failure of the graph is retried eagerly; any other error stops the recipe. The
      # attempt's error output is shown once it ends.
      status=0
      timed vae "${vae[@]}" --cuda-graph 2> "$RUN/vae-graph.err" || status=$?
      cat "$RUN/vae-graph.err" >&2
      if [ "$status" != 0 ]; then
        grep -q "CUDA graph" "$RUN/vae-graph.err" || exit "$status"
        echo "recipe: the VAE's step could not be replayed from a CUDA graph (above); training it eagerly (VAE_GRAPH=0 skips the graph)" >&2
        timed vae-eager "${vae[@]}"
      fi
      rm -f "$RUN/vae-graph.err"
    else
      timed vae "${vae[@]}"
    fi
    recorded "$RUN/vae.safetensors" "$made_with"
  fi
fi

if wants latents; then
  keep=(); [ "$KEEP_FRAMES" = 1 ] && keep=(--keep-frames)
  prepare=("$BWM" prepare --data "$RUN/data/train" --vae "$RUN/vae.safetensors" --resolution "${RESOLUTION}x$RESOLUTION"
    --history 8 --future 24 --stride 4 --actions observation.state:0-3 --validation-fraction 0.02
    "${keep[@]}" --batch 64 --device "$DEVICE" --out "$RUN/latents")
  made_with=$(record_of "${prepare[@]}")
  if ! kept "$RUN/latents/index.json" "$made_with"; then
    timed latents "${prepare[@]}"
    recorded "$RUN/latents/index.json" "$made_with"
  fi
fi

# bwm train's settings on this run's latents and VAE into `sets` (TRAIN_SETS last), writing to $1.
train_sets() { # $1 = the run's output folder
  local holdout kv
  # The validation episodes `bwm prepare` put last (the plan recorded in the cache's index names them).
  holdout=$("$PYTHON" - "$RUN/latents/index.json" <<'PY'
import json, sys
plan = json.load(open(sys.argv[1])).get("plan") or {}
print(int(plan.get("holdout_episodes", 0)))
PY
) || return 1
  sets=(--set "run.out_dir=\"$1\"" --set "run.device=\"$DEVICE\"" --set "data.latent_cache=\"$RUN/latents\""
        --set "data.holdout_episodes=$holdout" --set "validation.vae=\"$RUN/vae.safetensors\""
        --set "model.dit.in_dim=$VAE_Z_DIM" --set "model.dit.out_dim=$VAE_Z_DIM")
  [ -z "$TRAIN_STEPS" ] || sets+=(--set "train.steps=$TRAIN_STEPS")
  [ -z "$EMA_DECAY" ] || sets+=(--set "optim.ema_decay=$EMA_DECAY")
  set -f  # the settings may hold glob characters (patch_size=[1,2,2])
  for kv in $TRAIN_SETS; do sets+=(--set "$kv"); done
  set +f
}

if wants train; then
  train_sets "$RUN" || exit 1
  # Continued only on the latent cache and VAE it started from (settings are bwm train's to check).
  made_with=$(record_of train --latents "$RUN/latents/index.json" --vae "$RUN/vae.safetensors")
  if ! kept "$RUN/checkpoints/latest" "$made_with"; then
    mkdir -p "$RUN/checkpoints"
    recorded "$RUN/checkpoints/latest" "$made_with"
  fi
  timed train "$BWM" train --config configs/metaworld.toml "${sets[@]}" --resume auto
  [ -z "$EMA_DECAY" ] || ema_export "$(cat "$RUN/checkpoints/latest")"
fi
# The world-model flags every later command shares: the newest checkpoint (its EMA weights with
# EMA_DECAY, exported once; MODEL), its VAE and statistics.
world_model() {
  local step
  step=$(cat "$RUN/checkpoints/latest")
  MODEL="$RUN/checkpoints/$step"
  if [ -n "$EMA_DECAY" ]; then
    ema_export "$step" || exit 1
    MODEL="$RUN/ema/$step"
  fi
  wm_flags "$MODEL" "$SAMPLE_STEPS"
}
wm_flags() { # $1 = weights, $2 = sampler steps: the world-model flags into WM
  WM=(--checkpoint "$1" --vae "$RUN/vae.safetensors" --stats "$RUN/latents/stat.json" --stats-group observation.state
      --history 8 --future 24 --sample-steps "$2" --solver "$SOLVER" --guidance "$GUIDANCE" ${HISTORY_SIGMA:+--history-sigma "$HISTORY_SIGMA"} ${FP8:+--fp8 "$FP8"} --device "$DEVICE")
  if [ "$SAMPLER_GRAPH" = 1 ]; then WM+=(--cuda-graph); fi
  if [ "$SAMPLE_SEED" != 0 ]; then WM+=(--seed "$SAMPLE_SEED"); fi
}

if wants fidelity; then
  world_model
  timed fidelity "$BWM" fidelity "${WM[@]}" --data "$RUN/data/val" --actions observation.state:0-3 --resolution "${RESOLUTION}x$RESOLUTION" \
    --horizons 8,16,32,64 --videos 4 ${FIDELITY_EPISODES:+--episodes "$FIDELITY_EPISODES"} --episodes-in-flight "$FIDELITY_IN_FLIGHT" \
    --streams "$FIDELITY_STREAMS" --out "$FIDELITY_DIR"
fi

# The study's tasks: the data's, named where they are not the default (study.py's default is both).
STUDY_TASKS=; [ "$TASKS" = "$DEFAULT_TASKS" ] || STUDY_TASKS=$TASKS
seed_study() { # $1 = a study folder, $2 = another: $2 starts from $1's truth and judged episodes
  local f
  mkdir -p "$2" || return 1
  for f in truth.json judged.json; do
    [ -e "$2/$f" ] || [ ! -f "$1/$f" ] || cp "$1/$f" "$2/$f" || return 1
  done
}
COMMON_STUDY_ARGS=(--data "$RUN/data/val" ${STUDY_TASKS:+--tasks "$STUDY_TASKS"} --episodes "$STUDY_EPISODES" --horizon "$STUDY_HORIZON" --resolution "$RESOLUTION" --workers "$WORKERS")
STUDY_ARGS=("${COMMON_STUDY_ARGS[@]}" ${STUDY_VARIANTS:+--variants "$STUDY_VARIANTS"} --out "$STUDY_DIR")
if wants truth; then
  timed truth "$PYTHON" bench/metaworld/study.py "${STUDY_ARGS[@]}" --truth-only
fi

if wants judge; then
  reconstruct=() reconstructed=()
  if [ "$JUDGE_FRAMES" = reconstructed ]; then
    reconstruct=("$BWM" reconstruct --data "$JUDGE_DATA" --vae "$RUN/vae.safetensors" --resolution "${RESOLUTION}x$RESOLUTION"
      --max-episodes "$JUDGE_RECONSTRUCT_EPISODES" --device "$DEVICE" --out "$RUN/judge-reconstructed/train.safetensors")
    reconstructed=(--reconstructed "$RUN/judge-reconstructed/train.safetensors")
  fi
  train_judge=("$PYTHON" bench/metaworld/judge.py train --data "$JUDGE_DATA" "${reconstructed[@]}" --val "$RUN/data/val"
    --steps "$JUDGE_STEPS" --device "$DEVICE" --out "$JUDGE")
  judge() {
    if [ ${#reconstruct[@]} -gt 0 ]; then
      [ -f "$RUN/vae.safetensors" ] || { echo "recipe: JUDGE_FRAMES=reconstructed needs the vae stage's $RUN/vae.safetensors" >&2; return 1; }
      "${reconstruct[@]}" || return 1
    fi
    "${train_judge[@]}"
  }
  made_with=$(if [ ${#reconstruct[@]} -gt 0 ]; then record_of "${reconstruct[@]}"; fi; record_of "${train_judge[@]}")
  if ! kept "$JUDGE" "$made_with"; then
    timed "$JUDGE_NAME" judge
    recorded "$JUDGE" "$made_with"
  fi
  # The judge on the simulator's frames of the study's episodes (the study's first step, cached
  # for it) here, beside training.
  timed "${JUDGE_NAME/judge/judged}" "$PYTHON" bench/metaworld/study.py "${STUDY_ARGS[@]}" --judge "$JUDGE" --judged-only
fi

if wants ceiling; then
  ceiling() {
    # The VAE's round trip of the held-out frames is the same for every judge: made once.
    local round_trip=("$BWM" reconstruct --data "$RUN/data/val" --vae "$RUN/vae.safetensors" --resolution "${RESOLUTION}x$RESOLUTION"
      --device "$DEVICE" --out "$RUN/ceiling/val.safetensors")
    local made_with
    made_with=$(record_of "${round_trip[@]}")
    if ! kept "$RUN/ceiling/val.safetensors" "$made_with"; then
      "${round_trip[@]}" || return 1
      recorded "$RUN/ceiling/val.safetensors" "$made_with"
    fi
    "$PYTHON" bench/metaworld/judge.py score --model "$JUDGE" --val "$RUN/data/val" \
      --reconstructed "$RUN/ceiling/val.safetensors" --device "$DEVICE" --out "$RUN/ceiling/$JUDGE_NAME.json"
  }
  timed ceiling ceiling
fi

if wants study; then
  world_model
  [ -z "$STUDY_FROM" ] || seed_study "$STUDY_FROM" "$STUDY_DIR"
  timed study "$PYTHON" bench/metaworld/study.py "${STUDY_ARGS[@]}" --judge "$JUDGE" --bwm "$BWM" \
    --jobs "$STUDY_JOBS" --episodes-in-flight "$STUDY_IN_FLIGHT" --streams "$STUDY_STREAMS" -- "${WM[@]}"
fi

if wants teacher; then
  world_model
  teacher=("$PYTHON" bench/metaworld/teacher.py "${COMMON_STUDY_ARGS[@]}" ${TEACHER_VARIANTS:+--variants "$TEACHER_VARIANTS"}
    --out "$RUN/teacher" --judge "$JUDGE" --judge-device "$DEVICE" --bwm "$BWM" -- "${WM[@]}")
  made_with=$(record_of "${teacher[@]}")
  if ! kept "$RUN/teacher/teacher.json" "$made_with"; then
    timed teacher "${teacher[@]}"
    recorded "$RUN/teacher/teacher.json" "$made_with"
  fi
fi

if wants own; then
  world_model
  for split in train val; do
    own=("$PYTHON" bench/metaworld/teacher.py --data "$RUN/data/$split" --own-episodes ${OWN_BEHAVIOURS:+--behaviours "$OWN_BEHAVIOURS"}
      --episodes "$OWN_EPISODES" --horizon "$STUDY_HORIZON" --resolution "$RESOLUTION" --workers "$WORKERS"
      --out "$RUN/own/$split" --judge "$JUDGE" --judge-device "$DEVICE" --bwm "$BWM" -- "${WM[@]}")
    made_with=$(record_of "${own[@]}")
    kept "$RUN/own/$split/teacher.json" "$made_with" && continue
    timed "own-$split" "${own[@]}"
    recorded "$RUN/own/$split/teacher.json" "$made_with"
    "$PYTHON" bench/metaworld/contact_map.py "$RUN/own/$split/teacher.json" --band-cm 1 --json "$RUN/own/$split/contact_map.json"
  done
fi

if wants probe; then
  world_model
  timed probe "$PYTHON" bench/metaworld/study.py "${COMMON_STUDY_ARGS[@]}" --variants "$PROBE_VARIANTS" --out "$RUN/probe" \
    --judge "$JUDGE" --bwm "$BWM" --jobs "$STUDY_JOBS" --episodes-in-flight "$STUDY_IN_FLIGHT" --streams "$STUDY_STREAMS" -- "${WM[@]}"
fi
# The light decoder of the realtime stage: its command into `light_decoder`, its output `light`
# and its record `light_made_with`. It needs the VAE and the data alone.
light_decoder_command() {
  light="$REALTIME_DIR/light-decoder.safetensors"
  light_decoder=("$BWM" train-light-decoder --vae "$RUN/vae.safetensors" --data "$RUN/data/train" --max-episodes "$VAE_EPISODES"
    --holdout-tail "$VAE_HOLDOUT_TAIL" --resolution "${RESOLUTION}x$RESOLUTION" --clip-frames "$VAE_CLIP_FRAMES" --steps "$LIGHT_STEPS"
    --batch "$LIGHT_BATCH" --lr "$LIGHT_LR" --seed "$VAE_SEED" --device "$DEVICE" --out "$light")
  light_made_with=$(record_of "${light_decoder[@]}")
}
train_light_decoder() { timed light-decoder "${light_decoder[@]}" && recorded "$light" "$light_made_with"; }
if wants light; then
  light_decoder_command
  if ! kept "$light" "$light_made_with"; then
    mkdir -p "$REALTIME_DIR"
    train_light_decoder || exit 1
  fi
fi
if wants realtime; then
  world_model
  teacher=$MODEL
  RT=$REALTIME_DIR
  read -r -a teacher_steps <<< "$REALTIME_TEACHER_STEPS"
  read -r -a students <<< "$REALTIME_STUDENTS"
  [ ${#teacher_steps[@]} -gt 0 ] || { echo "recipe: REALTIME_TEACHER_STEPS names no step count" >&2; exit 2; }
  for k in "${teacher_steps[@]}" "${students[@]}"; do
    [[ $k =~ ^[1-9][0-9]*$ ]] || { echo "recipe: the realtime stage's step counts are positive integers, not '$k'" >&2; exit 2; }
  done
  for k in "${students[@]}"; do
    [ $((SAMPLE_STEPS % k)) = 0 ] || { echo "recipe: a student of $k steps learns the teacher's $SAMPLE_STEPS-step path (SAMPLE_STEPS) in $k equal parts; make SAMPLE_STEPS a multiple of $k" >&2; exit 2; }
  done
  [[ $REALTIME_EPISODES =~ ^[1-9][0-9]*$ ]] || { echo "recipe: REALTIME_EPISODES is a positive number of episodes, not '$REALTIME_EPISODES'" >&2; exit 2; }
  settings=()
  for k in "${teacher_steps[@]}"; do settings+=("t$k-full" "t$k-light"); done
  for k in "${students[@]}"; do settings+=("s$k-full" "s$k-light"); done
  reference=${settings[0]}
  if [ "$REALTIME_STUDIES" = all ]; then
    studies=("${settings[@]}")
  else
    read -r -a studies <<< "${REALTIME_STUDIES//,/ }"
    for name in "${studies[@]}"; do
      [[ " ${settings[*]} " == *" $name "* ]] || { echo "recipe: REALTIME_STUDIES names '$name', not one of this stage's settings (${settings[*]})" >&2; exit 2; }
    done
    # A setting's closed loop is measured against the reference's, so the reference is studied too.
    [ ${#studies[@]} = 0 ] || [[ " ${studies[*]} " == *" $reference "* ]] ||
      { echo "recipe: REALTIME_STUDIES must include the reference, $reference (the others' r is set against its r)" >&2; exit 2; }
  fi
  mkdir -p "$RT"
  # The rollouts, their scores and the settings' studies are made afresh each time (a study left
  # from other settings must not enter this table); the light decoder, the students and the
  # truth and verdicts of study-base are kept when made the same way.
  rm -rf "$RT/roll" "$RT"/study-[ts]* "$RT/agreement.json" "$RT/realtime.json"
  weights_id() { # $1 = a checkpoint or export folder, or a weights file: the sha256 of its weights
    if [ -f "$1/model.safetensors" ]; then sha256sum < "$1/model.safetensors"
    elif [ -f "$1" ]; then sha256sum < "$1"
    else find "$1" -name '*.safetensors' -print0 | sort -z | xargs -0 cat | sha256sum
    fi | cut -d' ' -f1
  }
  # The light decoder and the students train side by side (background), while the teacher's
  # settings with the VAE's decoder are rolled out and studied; then the others.
  # Whether each is to be made is settled before any starts: a refused output stops the stage
  # with nothing left running. (The light stage may have made the light decoder already.)
  light_decoder_command
  train_light=0
  kept "$light" "$light_made_with" || train_light=1
  student_of() { # $1 = the student's steps: its training command into `student` (the device apart: not recorded)
    # The teacher's own run config (its objective: shift, history noise), action dropout off (a
    # student learns the conditional path alone), started from the teacher's weights.
    student=("$BWM" train --config "$RUN/config.toml" --set "run.out_dir=\"$RT/student-$1\""
      --set "train.steps=$REALTIME_STUDENT_STEPS" --set "optim.lr=$REALTIME_STUDENT_LR"
      --set "optim.warmup_steps=$(( (REALTIME_STUDENT_STEPS + 19) / 20 ))" --set "objective.action_dropout=0.0"
      --set "model.init={ from = \"bwm-checkpoint\", path = \"$teacher\" }" --set "distill.teacher=\"$teacher\""
      --set "distill.student_steps=$1" --set "distill.teacher_substeps=$((SAMPLE_STEPS / $1))")
  }
  teacher_id=$(weights_id "$teacher")
  for k in "${students[@]}"; do
    student_of "$k"
    made_with=$(record_of "${student[@]}"; echo "teacher (sha256 $teacher_id)")
    if ! kept "$RT/student-$k/checkpoints/latest" "$made_with"; then
      mkdir -p "$RT/student-$k/checkpoints"
      recorded "$RT/student-$k/checkpoints/latest" "$made_with"
    fi
  done
  # Side by side on the device: their stage times (and those of the rollouts and studies beside
  # them) are not the settings' speed.
  training=()
  if [ $train_light = 1 ]; then
    train_light_decoder & training+=($!)
  fi
  for k in "${students[@]}"; do
    student_of "$k"
    timed "student-$k" "${student[@]}" --set "run.device=\"$DEVICE\"" --resume auto > "$RT/student-$k.log" 2>&1 & training+=($!)
  done
  # Should the stage stop before it waits for them, they stop with it.
  trap 'stop_tree "${training[@]}"' EXIT
  realtime_wm() { # $1 = a setting: its world-model flags into WM
    local kind=${1%%-*} steps weights
    steps=${kind:1}
    if [ "${kind:0:1}" = t ]; then
      weights=$teacher
    else
      weights="$RT/student-$steps/checkpoints/$(cat "$RT/student-$steps/checkpoints/latest")" || return 1
    fi
    wm_flags "$weights" "$steps"
    [ "${1#*-}" = full ] || WM+=(--light-decoder "$light")
  }
  roll() { # $@ = settings, each rolled out over the first REALTIME_EPISODES held-out episodes (the same noise)
    local name
    for name in "$@"; do
      realtime_wm "$name" || return 1
      rm -rf "$RT/roll/$name"
      timed "roll-$name" "$BWM" rollout "${WM[@]}" --data "$RUN/data/val" --episodes "$(seq -s, 0 $((REALTIME_EPISODES - 1)))" \
        --actions observation.state:0-3 --resolution "${RESOLUTION}x$RESOLUTION" --frame-storage image \
        --episodes-in-flight "$REALTIME_IN_FLIGHT" --out "$RT/roll/$name" || return 1
    done
  }
  variants=$REALTIME_VARIANTS
  [ -n "$variants" ] || variants=$("$PYTHON" bench/metaworld/families.py --list test)
  base=("$PYTHON" bench/metaworld/study.py "${COMMON_STUDY_ARGS[@]}" --variants "$variants" --out "$RT/study-base")
  study_of() { # $@ = settings, each studied on the variants (from the truth and verdicts of study-base)
    local name
    for name in "$@"; do
      realtime_wm "$name" && seed_study "$RT/study-base" "$RT/study-$name" || return 1
      timed "study-$name" "$PYTHON" bench/metaworld/study.py "${COMMON_STUDY_ARGS[@]}" --variants "$variants" --out "$RT/study-$name" \
        --judge "$JUDGE" --bwm "$BWM" --jobs "$STUDY_JOBS" --episodes-in-flight "$STUDY_IN_FLIGHT" --streams "$STUDY_STREAMS" -- "${WM[@]}" || return 1
    done
  }
  first=() later=() first_studies=() later_studies=()
  for name in "${settings[@]}"; do [[ $name == t*-full ]] && first+=("$name") || later+=("$name"); done
  for name in "${studies[@]}"; do [[ $name == t*-full ]] && first_studies+=("$name") || later_studies+=("$name"); done
  status=0
  roll "${first[@]}" || status=1
  if [ $status = 0 ] && [ ${#studies[@]} -gt 0 ]; then
    # From the recipe's study's truth and verdicts where the truth and judge stages made them (over
    # every variant: study.py takes these variants' rates from them when made the same way).
    { seed_study "$STUDY_DIR" "$RT/study-base" && timed realtime-truth "${base[@]}" --truth-only &&
      timed realtime-judged "${base[@]}" --judge "$JUDGE" --judged-only; } || status=1
  fi
  [ $status != 0 ] || study_of "${first_studies[@]}" || status=1
  for pid in "${training[@]}"; do wait "$pid" || { echo "recipe: the light decoder or a student failed (above; $RT/student-*.log)" >&2; status=1; }; done
  training=()
  trap - EXIT
  # The other settings' rollouts and the open-loop scores (on the CPU) beside their studies.
  if [ $status = 0 ]; then
    { roll "${later[@]}" &&
        timed agreement "$PYTHON" bench/metaworld/agreement.py --reference "$RT/roll/$reference" --recorded "$RUN/data/val" --horizon 32 \
          --json "$RT/agreement.json" "${settings[@]/#/$RT/roll/}"; } & open_loop=$!
    trap 'stop_tree "$open_loop"' EXIT
    study_of "${later_studies[@]}" || status=1
    wait "$open_loop" || { echo "recipe: a rollout or agreement.py failed (above)" >&2; status=1; }
    trap - EXIT
  fi
  [ $status != 0 ] || "$PYTHON" bench/metaworld/realtime.py "$RT" --reference "$reference" --json "$RT/realtime.json" || status=1
  [ $status = 0 ] || exit 1
fi
if wants engine; then
  world_model
  # Made afresh each time: the plan, the rollout and the policies take minutes, and a half-made
  # set from other settings must not be mixed into the next.
  rm -rf "$ENGINE_DIR/plan" "$ENGINE_DIR/generated"
  fps=$(PYTHONPATH="bench/metaworld${PYTHONPATH:+:$PYTHONPATH}" "$PYTHON" -c 'from mw import FPS; print(FPS)')
  timed engine-plan "$PYTHON" bench/metaworld/engine.py plan --out "$ENGINE_DIR/plan" --tasks "$TASKS" --seeds "$ENGINE_SEEDS" \
    --generated "$ENGINE_GENERATED" --frames "$FRAMES" --resolution "$RESOLUTION" --workers "$WORKERS" || exit 1
  timed engine-rollout "$BWM" rollout "${WM[@]}" --inputs "$ENGINE_DIR/plan/inputs.jsonl" --drive file --fps "$fps" \
    --resolution "${RESOLUTION}x$RESOLUTION" --frame-storage image --episodes-in-flight "$ENGINE_IN_FLIGHT" --out "$ENGINE_DIR/generated" || exit 1
  timed engine-measure "$PYTHON" bench/metaworld/engine.py measure --plan "$ENGINE_DIR/plan" --generated "$ENGINE_DIR/generated" \
    --judge "$JUDGE" --demos "$ENGINE_DEMOS" --episodes "$ENGINE_EPISODES" ${ENGINE_NET_STEPS:+--net-steps "$ENGINE_NET_STEPS"} \
    --workers "$WORKERS" --device "$DEVICE" --out "$ENGINE_DIR/engine.json" || exit 1
fi
echo "recipe: done; stage times in $TIMINGS"
