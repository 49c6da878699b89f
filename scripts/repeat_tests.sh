#!/usr/bin/env bash
# `make test` N times in a row on a fresh clone of this checkout's HEAD, optionally next to a
# CPU-bound process (`yes > /dev/null` per --load), as issue 18's acceptance asks. Each run's
# output goes to DIR/test-K.log (default runs/repeat-tests); one line per run (exit status, seconds, the suite's summary line,
# anything new in the temporary folder), then the clone and its target folder are removed.
# Usage: bash scripts/repeat_tests.sh [--load N] [--runs N] [--keep-logs DIR]
# The virtualenv comes from BWM_VENV (default: the CI cache's); the clone builds into its own
# target folder, so nothing else builds into it while the runs go.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
runs=5 load=0 logs=
while [ $# -gt 0 ]; do
  case "$1" in
    --runs) runs=$2; shift 2 ;;
    --load) load=$2; shift 2 ;;
    --keep-logs) logs=$2; shift 2 ;;
    *) echo "usage: repeat_tests.sh [--load N] [--runs N] [--keep-logs DIR]" >&2; exit 2 ;;
  esac
done
[[ "$runs" =~ ^[1-9][0-9]*$ && "$load" =~ ^[0-9]+$ ]] || { echo "repeat_tests: --runs must be >= 1 and --load >= 0" >&2; exit 2; }
tmp="${TMPDIR:-/tmp}"
work=$(mktemp -d "$tmp/bwm-repeat-XXXXXX") || exit 1
logs="${logs:-$ROOT/runs/repeat-tests}"
mkdir -p "$logs"
loaders=()
cleanup() {
  [ ${#loaders[@]} -gt 0 ] && kill "${loaders[@]}" 2>/dev/null
  rm -rf "$work"
}
trap cleanup EXIT
trap 'exit 130' INT TERM
git clone -q "$ROOT" "$work/main" || exit 1
# As .ci/run: a ../shared beside the checkout (golden/, data/) is what the tests read (BWM_SHARED).
if [ -d "$ROOT/../shared" ]; then export BWM_SHARED; BWM_SHARED="$(cd "$ROOT/../shared" && pwd)"; fi
commit=$(git -C "$work/main" rev-parse --short HEAD)
export BWM_VENV="${BWM_VENV:-${HOME:-/root}/.cache/bwm-ci/venv}" CARGO_TARGET_DIR="$work/target" CARGO_TERM_COLOR=never
for _ in $(seq 1 "$load"); do yes > /dev/null & loaders+=($!); done
echo "repeat_tests: $runs runs of make test at $commit, $load CPU-bound processes beside, logs in $logs"
before=$(ls -A "$tmp" | sort)
failed=0
for k in $(seq 1 "$runs"); do
  start=$(date +%s)
  (cd "$work/main" && make test) > "$logs/test-$k.log" 2>&1
  rc=$?
  [ $rc = 0 ] || failed=$((failed + 1))
  new=$(comm -13 <(echo "$before") <(ls -A "$tmp" | sort) | grep -v "^$(basename "$work")$" | tr '\n' ' ')
  echo "run $k: exit $rc in $(( $(date +%s) - start )) s; $(grep -a '^test: ' "$logs/test-$k.log" | tr '\n' ' ')${new:+new in $tmp: $new}"
done
echo "repeat_tests: $((runs - failed)) of $runs runs passed at $commit"
[ $failed = 0 ]
