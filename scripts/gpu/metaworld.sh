#!/usr/bin/env bash
# bench/metaworld/recipe.sh on a CUDA host without the toolchain, from the repo root, with these
# copied there (scripts/gpu/pack.sh packs them):
#   .whl          bench/metaworld's wheels for that machine's Python 3.12 (metaworld, mujoco,
#                 gymnasium, farama-notifications, pyopengl, websockets, safetensors)
#   .gl           the GL loader debs (libegl1, libglvnd0, libopengl0, ...), for MuJoCo through EGL
#   .pack/bwm.xz  the bwm binary built with --no-default-features (xz-compressed)
# Usage: bash scripts/gpu/metaworld.sh [STAGE ...]; logs and timings go to $OUT, the run's small
# outputs to $OUT/run.tar.gz. With no stage, every stage (independent ones side by side); where
# a remote command is limited in time (10 minutes), run it detached:
#   bash scripts/gpu/detached.sh start mw bash scripts/gpu/metaworld.sh; bash scripts/gpu/detached.sh wait mw 570 runs/metaworld/study runs/metaworld/probe
# and the same `wait` in the commands that follow, back to back (on a host released when idle
# between commands or after 30 minutes, the run ends with it). With the recipe's defaults
# (128x128, a DiT of width 768) data to trained model takes about 17 minutes on an H200, the study
# 5-6 more, the fidelity stage about 20 (beside the studies) and the probe about 4: four
# 10-minute waits, the last started before minute 30 (docs/fidelity.md at abaed68, run 12).
# SKIP_FIDELITY=1 leaves out the fidelity stage (which otherwise runs beside the study and slows
# it); SKIP_PROBE=1 the probe (graded `wrong` variants, after the study); TEACHER=1 adds the
# teacher stage after the study
# (each chunk drawn from the simulator's real history: $RUN/teacher/teacher.json; TEACHER_VARIANTS
# picks variants); OWN=1 the own stage after that (the same over the training and held-out
# datasets' own near misses: $RUN/own/{train,val}/; OWN_BEHAVIOURS, OWN_EPISODES). COMPARE_STREAMS=2
# studies the same model a second time with each evaluate process's episodes in flight in 2 lanes
# on CUDA streams of their own ($RUN/study-streams2: the same estimates, its own time in the
# timings). COMPARE_SOLVER=dpm++2m studies the same model a
# second time with that sampler ($RUN/study-dpm++2m); COMPARE_GUIDANCE="2 3" once more per
# action-guidance value ($RUN/study-g2, ...; the model trained with objective.action_dropout > 0);
# COMPARE_HISTORY_SIGMA="0" once more per history-noise level when sampling ($RUN/study-h0, ...;
# recipe.sh's HISTORY_SIGMA); COMPARE_SAMPLE_SEED="1 2" once more per sampler seed (the same
# episodes drawn again: $RUN/study-seed1, ...; recipe.sh's SAMPLE_SEED); each such study starts
# from the study's truth and judged episodes;
# COMPARE_EMA=1 (with EMA_DECAY) once more with the newest checkpoint's last step's weights instead
# of their average ($RUN/study-last);
# OTHER_SEEDS=S once more on held-out seeds from S (bench/metaworld/other-seeds.sh, without
# training again: $RUN/seeds-S/);
# COMPARE_JUDGE=real once more with the judge that learned from the simulator's frames alone
# ($RUN/study-judge-real, its ceiling in $RUN/ceiling/judge.json; JUDGE_FRAMES=real makes it the
# study's own, and COMPARE_JUDGE=reconstructed then adds the recipe's default judge).
# `bash scripts/gpu/metaworld.sh transfer` runs bench/metaworld/transfer.sh (the base-versus-scratch
# study of the LoRA issue; its variables apply) instead, its small outputs in $OUT/run.tar.gz;
# `bash scripts/gpu/metaworld.sh engine` trains the model (stages up to train, truth and judge)
# where it has not, then runs the recipe's engine stage (the data engine measured; its ENGINE_*
# variables apply): $RUN/engine/engine.json comes back in run.tar.gz. Run it detached as the recipe.
# `bash scripts/gpu/metaworld.sh realtime` likewise trains the model where it has not (the recipe's
# light stage, the light decoder, beside it once the VAE is trained), then runs the
# recipe's realtime stage (a light decoder and distilled students against the teacher's steps, open
# and closed loop; its REALTIME_*, LIGHT_* variables apply): $RUN/realtime/realtime.json,
# agreement.json and each setting's study-SETTING/study.json come back in run.tar.gz.
# `bash scripts/gpu/metaworld.sh sweep` runs bench/metaworld/sweep.sh (the real-time issue's sampler
# sweep; its variables apply) over the run the recipe trained on this machine, training it first
# (stages up to train, truth and judge) where it has not; run it detached as the recipe.
set -uo pipefail
source "$(dirname "$0")/common.sh"
# Under a lock: variants.sh starts several at once, and two pip installs into one target remove
# each other's files (run 23's mw9 failed so).
(
  flock 9
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  if [ ! -d /tmp/site/metaworld ]; then
    rm -rf /tmp/site /tmp/site.part
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site.part .whl/*.whl &&
      mv /tmp/site.part /tmp/site
  fi
) 9> /tmp/metaworld-setup.lock || exit 1
export MUJOCO_GL=egl PYOPENGL_PLATFORM=egl PYTHONUNBUFFERED=1
export PYTHONPATH=/tmp/site
unpack .pack/bwm.xz dist/bwm || exit 1
export BWM="$PWD/dist/bwm" PYTHON=python3
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
python3 - <<'PY' || exit 1
import importlib
missing = []
for name in ("numpy", "torch", "pyarrow", "PIL", "scipy", "msgpack", "safetensors", "websockets", "metaworld", "mujoco"):
    try:
        m = importlib.import_module(name)
        print(f"{name} {getattr(m, '__version__', '')}")
    except Exception as e:
        missing.append(f"{name} ({e})")
if missing:
    raise SystemExit("missing on this machine: " + ", ".join(missing))
PY
export OUT
exec bash "$(dirname "$0")/metaworld-stages.sh" "$@"
