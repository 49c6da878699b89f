#!/usr/bin/env bash
# A trained recipe run's world model measured on other held-out seeds, without training again:
#   VAL_SEED_START=S bash bench/metaworld/other-seeds.sh FROM_RUN [STAGE ...]
# RUN (default FROM_RUN-seeds-S) gets links to FROM_RUN's training data, VAE, latent cache,
# checkpoints and judge (with the records beside them), then bench/metaworld/recipe.sh runs the
# stages that use the held-out episodes (default: data fidelity truth study; ceiling too if you
# like) over VAL_EPISODES episodes per task from seed S: new placements, and the policies' noise
# drawn from the same seeds. Every other variable is the recipe's: give the data variables
# FROM_RUN's data were made with (the data stage refuses its training data otherwise, naming what
# differs) and the SAMPLE_STEPS, SOLVER, GUIDANCE, EMA_DECAY and JUDGE_FRAMES its study used.
set -euo pipefail
[ $# -ge 1 ] || { echo "usage: VAL_SEED_START=S bash bench/metaworld/other-seeds.sh FROM_RUN [STAGE ...]" >&2; exit 2; }
from=${1%/}; shift
[ -n "${VAL_SEED_START:-}" ] || { echo "other-seeds: set VAL_SEED_START, the first held-out seed" >&2; exit 2; }
[ -f "$from/checkpoints/latest" ] || { echo "other-seeds: $from holds no trained world model ($from/checkpoints/latest)" >&2; exit 2; }
RUN=${RUN:-$from-seeds-$VAL_SEED_START}
[ "$(realpath -m "$RUN")" != "$(realpath "$from")" ] || { echo "other-seeds: RUN must not be FROM_RUN ($from): its held-out data would be replaced" >&2; exit 2; }
shopt -s nullglob
parts=(data/train vae.safetensors vae.safetensors.recipe latents checkpoints "$from"/judge*.pt "$from"/judge*.pt.recipe)
parts=("${parts[@]#"$from"/}")
for part in "${parts[@]}"; do
  [ -e "$from/$part" ] || { echo "other-seeds: $from/$part is missing" >&2; exit 2; }
done
mkdir -p "$RUN/data"
for part in "${parts[@]}"; do
  [ -e "$RUN/$part" ] || ln -s "$(realpath "$from/$part")" "$RUN/$part"
done
[ $# -gt 0 ] || set -- data fidelity truth study
echo "other-seeds: $RUN: $from's world model on held-out seeds from $VAL_SEED_START (stages: $*)"
RUN=$RUN exec bash "$(dirname "$0")/recipe.sh" "$@"
