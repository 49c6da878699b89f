#!/usr/bin/env bash
# Stops the cluster that scripts/slurm/start-local.sh DIR started and removes what it made: every
# process in its nodes' network namespaces (the daemons, and what jobs left) gets SIGTERM, then
# SIGKILL after 10 s; then the namespaces, veths, bridge, /etc/netns/<namespace> folders and the
# registry entry /run/bwm-slurm/<tag> go. DIR itself (logs, state) stays.
#   scripts/slurm/stop-local.sh DIR        or   scripts/slurm/stop-local.sh --tag TAG
# (--tag: a cluster known by its tag alone, e.g. a leftover whose DIR is gone; start-local.sh uses it.)
set -uo pipefail
if [ "${1:-}" = --tag ]; then
  TAG="${2:?usage: $0 DIR | --tag TAG}"
else
  DIR="${1:?usage: $0 DIR | --tag TAG}"
  [ -f "$DIR/cluster.env" ] || { echo "stop-local: no cluster in $DIR (no cluster.env)" >&2; exit 0; }
  TAG="$(sed -n 's/^TAG=//p' "$DIR/cluster.env")"
fi
[[ "$TAG" =~ ^bws[a-z0-9]+$ ]] || { echo "stop-local: $TAG is not a cluster tag of start-local.sh" >&2; exit 1; }
namespaces=()
while read -r name _; do
  [[ "$name" =~ ^$TAG-n[0-9]+$ ]] && namespaces+=("$name")
done < <(ip netns list 2>/dev/null)

alive() { for ns in "${namespaces[@]}"; do ip netns pids "$ns" 2>/dev/null; done; }
pids=$(alive)
if [ -n "$pids" ]; then
  # shellcheck disable=SC2086
  kill -TERM $pids 2>/dev/null
  for _ in $(seq 1 100); do
    pids=$(alive)
    [ -z "$pids" ] && break
    sleep 0.1
  done
  if [ -n "$pids" ]; then
    echo "stop-local: killing $(echo $pids), still running 10 s after SIGTERM" >&2
    # shellcheck disable=SC2086
    kill -KILL $pids 2>/dev/null
    sleep 0.5
  fi
fi
for ns in "${namespaces[@]}"; do
  ip netns del "$ns" 2>/dev/null
  rm -rf "/etc/netns/$ns"
done
rm -rf /etc/netns/"$TAG"-n*
while read -r link; do
  ip link del "$link" 2>/dev/null
done < <(ip -o link show 2>/dev/null | awk -F': ' '{ sub(/@.*/, "", $2); print $2 }' | grep -E "^${TAG}(v[0-9]+|br)$")
rm -rf "/run/bwm-slurm/$TAG.d"
rm -f "/run/bwm-slurm/$TAG"
exit 0
