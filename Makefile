# The two commands a new user needs (see README.md): `make demo` and `make test`. Each installs what
# it needs when missing (scripts/setup.sh): `make demo` the build's libraries and the virtualenv with
# libtorch (through scripts/env.sh), `make test` also what only the tests use (Slurm, munge, the
# ffmpeg command, Mesa's EGL, the Python packages of the tests). `make setup` installs both at once.
SHELL := /bin/bash
ENV := source scripts/env.sh
DEMO_DATA ?= data/bwm-demo
DEMO_VAE_STEPS ?= 300

.PHONY: demo test build setup
setup:
	@bash scripts/setup.sh --tests

# A small DiT post-trained on the bundled episodes (data/bwm-demo, in the repository), on CPU
# (configs/demo.toml): fit a small VAE (real pixels, on clips as long as the DiT's: x0 + 8 history
# + 8 future = 17 frames), encode a clip at every frame offset into a latent cache, train, and
# write runs/demo/{loss.svg,rollout.mp4}; the closing lines score every held-out clip's rollout
# against holding the last given frame. Each stage is skipped when its output exists; the
# training resumes from its last checkpoint.
demo: build
	@$(ENV) && bwm="$${CARGO_TARGET_DIR:-target}/release/bwm" && \
	{ [ -f runs/vae/vae.safetensors ] || "$$bwm" train-vae --data $(DEMO_DATA) --resolution 96x64 --steps $(DEMO_VAE_STEPS) --batch 2 --clip-frames 17 --holdout-tail 0.15 --device cpu --out runs/vae/vae.safetensors; } && \
	{ [ -f runs/demo/latents/index.json ] || "$$bwm" prepare --data $(DEMO_DATA) --vae runs/vae/vae.safetensors --resolution 96x64 --history 8 --future 8 --stride 1 --keep-frames --device cpu --out runs/demo/latents; } && \
	"$$bwm" train --config configs/demo.toml --set run.device='"cpu"' --resume auto

# Every test binary runs even when one fails; one summary line of counts at the end; the tests
# write under one folder of the run, removed afterwards (scripts/test.sh). The end-to-end tests
# run the `bwm` binary, which `cargo test` does not build (it belongs to another package): build
# first, so that `make test` works on a fresh clone without `make build`; then the tests' own
# dependencies and the golden files (scripts/setup.sh --tests).
test: build
	@$(ENV) && bash scripts/setup.sh --tests && bash scripts/test.sh

build:
	@$(ENV) && cargo build --release -p bwm-cli
