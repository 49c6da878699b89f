#!/usr/bin/env bash
# `make test`: the whole workspace suite in release. Every test binary runs even when one fails
# (--no-fail-fast), one line of passed/failed counts closes the output, and everything the tests
# write goes under one folder of this run (TMPDIR), removed at the end. The inference crate's
# example runs after the tests and counts as one more binary.
set -uo pipefail
run=$(mktemp -d "${TMPDIR:-/tmp}/bwm-test-run-XXXXXX") || exit 1
log="$run/cargo-test.log"
mkdir -p "$run/tmp"
skips="$run/skipped.log"
export BWM_SKIP_LOG="$skips"
# Importing the reference packages (diffusers, DiffSynth) makes torch create its compile cache in the
# temporary folder; it belongs to this run, not to any test.
export TORCHINDUCTOR_CACHE_DIR="$run/torchinductor"
TMPDIR="$run/tmp" cargo test --workspace --release --no-fail-fast "$@" 2>&1 | tee "$log"
status=${PIPESTATUS[0]}
# The library's example (inference/examples/step.rs: a tiny random world model stepped twice).
if cargo run --release -q -p bwm-inference --example step -- "$run/step-frames" 2>&1 | tee -a "$log" &&
   [ "$(find "$run/step-frames" -name 'frame_*.png' | wc -l)" -eq 8 ]; then
  echo "test result: ok. 1 passed; 0 failed; 0 ignored (inference/examples/step.rs)" | tee -a "$log"
else
  echo "test result: FAILED. 0 passed; 1 failed; 0 ignored (inference/examples/step.rs)" | tee -a "$log"
  status=1
fi
left=$(find "$run/tmp" -mindepth 1 -maxdepth 1 -printf '%f ' 2>/dev/null)
[ -n "$left" ] && echo "test: left behind in the temporary folder (removed now): $left"
# A test whose optional dependency is missing and not required (BWM_REQUIRE, bwm-testdir's
# `optional` module) writes a line to BWM_SKIP_LOG and returns: counted as skipped here, taken out
# of the passed count.
skipped=$(grep -c '^bwm-test: SKIPPED' "$skips" 2>/dev/null || true)
skipped=${skipped:-0}
awk -v s="$skipped" '/^test result:/ { p += $4; f += $6; i += $8; b += 1 }
     END { printf "test: %d passed, %d failed, %d ignored, %d skipped (optional dependency missing) in %d test binaries\n", p - s, f, i, s, b }' "$log"
[ "$skipped" -gt 0 ] && cat "$skips"
rm -rf "$run"
[ "$status" -eq 0 ] || echo "test: FAILED (cargo test exit $status); search the output above for 'FAILED' or 'panicked'"
exit "$status"
