#!/usr/bin/env bash
# Stops the daemons that scripts/slurm/start-local.sh DIR started (by their pid files in DIR).
set -uo pipefail
DIR="${1:?usage: $0 DIR}"
pids=()
for f in "$DIR/slurmd.pid" "$DIR/slurmctld.pid" "$DIR/munge/munged.pid"; do
  [ -f "$f" ] || continue
  pid="$(cat "$f")"
  if [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null; then
    kill -TERM "$pid" && pids+=("$pid")
  fi
done
for _ in $(seq 1 100); do
  alive=()
  for pid in "${pids[@]}"; do kill -0 "$pid" 2>/dev/null && alive+=("$pid"); done
  [ ${#alive[@]} -eq 0 ] && exit 0
  sleep 0.1
done
echo "stop-local: killing ${alive[*]}, still running 10 s after SIGTERM" >&2
kill -KILL "${alive[@]}" 2>/dev/null
exit 0
