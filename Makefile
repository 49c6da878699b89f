# The two commands a new user needs (see README.md): `make demo` and `make test`.
SHELL := /bin/bash
ENV := source scripts/env.sh

.PHONY: demo test build setup
setup:
	@bash scripts/setup.sh

demo:
	@$(ENV) && cargo run --release -q -p bwm-launcher -- demo

test:
	@$(ENV) && cargo test --workspace --release

build:
	@$(ENV) && cargo build --release -p bwm-launcher
