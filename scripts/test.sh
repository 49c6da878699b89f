#!/usr/bin/env bash
# `make test`: the whole workspace suite in release. Every test binary runs even when one fails
# (--no-fail-fast), one line of passed/failed counts closes the output, and everything the tests
# write goes under one folder of this run (TMPDIR), removed at the end.
set -uo pipefail
run=$(mktemp -d "${TMPDIR:-/tmp}/bwm-test-run-XXXXXX") || exit 1
log="$run/cargo-test.log"
mkdir -p "$run/tmp"
TMPDIR="$run/tmp" cargo test --workspace --release --no-fail-fast "$@" 2>&1 | tee "$log"
status=${PIPESTATUS[0]}
left=$(find "$run/tmp" -mindepth 1 -maxdepth 1 -printf '%f ' 2>/dev/null)
[ -n "$left" ] && echo "test: left behind in the temporary folder (removed now): $left"
awk '/^test result:/ { p += $4; f += $6; i += $8; b += 1 }
     END { printf "test: %d passed, %d failed, %d ignored in %d test binaries\n", p, f, i, b }' "$log"
rm -rf "$run"
[ "$status" -eq 0 ] || echo "test: FAILED (cargo test exit $status); search the output above for 'FAILED' or 'panicked'"
exit "$status"
