#!/usr/bin/env bash
# A Slurm cluster of N nodes (default 2) on this one machine, for tests/slurm.rs and for trying
# `bwm submit`: each node is a network namespace of its own (`ip netns`, with its own host name in
# a UTS namespace) whose eth0 is one end of a veth pair; the other ends hang on a bridge in the root
# namespace. The cluster's subnet is 10.213.K.0/24 (K the first number free here): the bridge is .1,
# node i is .(i+1) and is named <tag>n<i>, which /etc/netns/<namespace>/hosts resolves inside
# every node (bound over its /etc/hosts, as `ip netns exec` does), so that ranks on node 2 reach node 1's
# MASTER_ADDR over the veths, as on a real cluster. Node 1 also runs munged and slurmctld; the
# client commands (sbatch, scontrol, ...) work from the root namespace through the bridge. The
# nodes share the filesystem (the run folder, DIR), as a cluster's shared filesystem would.
# Configuration, munge key and socket, state, spool folders and logs live under DIR; the daemons
# run as root (namespaces need root). Needs Debian's slurm-wlm, munge and iproute2 (scripts/setup.sh --tests).
#   scripts/slurm/start-local.sh DIR      then   export SLURM_CONF=DIR/slurm.conf
# BWM_SLURM_NODES: number of nodes (default 2). BWM_SLURM_OWNER_PID: a process (the test) whose
# end makes the cluster a leftover: every start removes the clusters whose owner is gone (a test
# killed before its cleanup ran). Names carry a random tag (DIR/cluster.env records it and the
# addresses), so clusters of parallel runs do not collide.
# Stop it with scripts/slurm/stop-local.sh DIR (daemons, namespaces, veths, bridge and hosts files).
set -Eeuo pipefail
DIR="${1:?usage: $0 DIR}"
NODES="${BWM_SLURM_NODES:-2}"
OWNER="${BWM_SLURM_OWNER_PID:-}"
HERE="$(cd "$(dirname "$0")" && pwd)"
REGISTRY=/run/bwm-slurm
for tool in munged mungekey slurmctld slurmd sinfo ip nsenter unshare flock; do
  command -v "$tool" >/dev/null || { echo "start-local: $tool is not installed (scripts/setup.sh --tests installs slurm-wlm, munge and iproute2)" >&2; exit 1; }
done
[[ "$NODES" =~ ^[1-9][0-9]?$ ]] || { echo "start-local: BWM_SLURM_NODES=$NODES is not a number of nodes (1-99)" >&2; exit 1; }
[ "$(id -u)" = 0 ] || { echo "start-local: network namespaces need root" >&2; exit 1; }
mkdir -p "$DIR" "$REGISTRY"
DIR="$(cd "$DIR" && pwd)"
[ -e "$DIR/cluster.env" ] && { echo "start-local: $DIR already holds a cluster (stop-local.sh $DIR first)" >&2; exit 1; }
mkdir -p "$DIR/munge" "$DIR/state" "$DIR/spool" "$DIR/log"
chmod 700 "$DIR/munge"

# "pid start-time": a process id alone could be reused by another process.
process_id() { [ -r "/proc/$1/stat" ] && echo "$1 $(awk '{ print $22 }' "/proc/$1/stat")"; }
OWNER_ID=""
if [ -n "$OWNER" ]; then
  OWNER_ID="$(process_id "$OWNER")" || { echo "start-local: BWM_SLURM_OWNER_PID=$OWNER is not running" >&2; exit 1; }
fi

# Leftovers, the choice of tag and subnet, and the namespaces, under one lock: parallel starts
# neither take the same subnet nor remove a cluster being made.
exec 9>"$REGISTRY/lock"
flock 9
for entry in "$REGISTRY"/bws*; do
  [ -f "$entry" ] || continue
  owner="$(sed -n 's/^OWNER_ID=//p' "$entry")"
  [ -n "$owner" ] || continue
  if [ "$(process_id "${owner%% *}" || true)" != "$owner" ]; then
    echo "start-local: removing the cluster $(basename "$entry") of a run that has ended (owner $owner)" >&2
    bash "$HERE/stop-local.sh" --tag "$(basename "$entry")" || true
  fi
done
while :; do
  TAG="bws$(od -An -N3 -tx1 /dev/urandom | tr -d ' \n')"
  [ -e "$REGISTRY/$TAG" ] || break
done
used="$(ip -4 -o addr show; cat "$REGISTRY"/bws* 2>/dev/null || true)"
NET=""
for k in $(seq 1 254); do
  if ! grep -q "10\.213\.$k\." <<<"$used"; then NET="10.213.$k"; break; fi
done
[ -n "$NET" ] || { echo "start-local: no free subnet 10.213.K.0/24 left" >&2; exit 1; }
ns() { echo "$TAG-n$1"; }
node() { echo "${TAG}n$1"; }
addr() { echo "$NET.$(($1 + 1))"; }
# Registered before anything is made, so that stop-local.sh --tag removes also a half-made cluster.
printf 'DIR=%s\nNET=%s\nNODES=%s\nOWNER_ID=%s\n' "$DIR" "$NET" "$NODES" "$OWNER_ID" >"$REGISTRY/$TAG"
{
  echo "TAG=$TAG"
  echo "NODES=$NODES"
  for i in $(seq 1 "$NODES"); do echo "NODE$i=$(node "$i") NS$i=$(ns "$i") ADDR$i=$(addr "$i")"; done
} >"$DIR/cluster.env"
trap 'echo "start-local: failed; removing the half-made cluster $TAG" >&2; bash "$HERE/stop-local.sh" "$DIR" >&2 || true' ERR

ip link add "${TAG}br" type bridge
ip addr add "$NET.1/24" dev "${TAG}br"
ip link set "${TAG}br" up
hosts="127.0.0.1 localhost"$'\n'
for i in $(seq 1 "$NODES"); do hosts+="$(addr "$i") $(node "$i")"$'\n'; done
for i in $(seq 1 "$NODES"); do
  ip netns add "$(ns "$i")"
  ip link add "${TAG}v$i" type veth peer name eth0 netns "$(ns "$i")"
  ip link set "${TAG}v$i" master "${TAG}br"
  ip link set "${TAG}v$i" up
  ip -n "$(ns "$i")" addr add "$(addr "$i")/24" dev eth0
  ip -n "$(ns "$i")" link set eth0 up
  ip -n "$(ns "$i")" link set lo up
  mkdir -p "/etc/netns/$(ns "$i")"
  printf '%s' "$hosts" >"/etc/netns/$(ns "$i")/hosts"
done
flock -u 9

# Runs a command on node i: in its network namespace, with its host name and its hosts file (in
# a mount namespace of its own; not `ip netns exec`, whose fresh /sys hides the cgroup mounts that
# slurmd reads).
on_node() {
  local i="$1"
  shift
  nsenter --net="/run/netns/$(ns "$i")" unshare --uts --mount --propagation private \
    sh -c 'mount --bind "/etc/netns/$1/hosts" /etc/hosts && hostname "$0" && shift && exec "$@"' "$(node "$i")" "$(ns "$i")" "$@"
}

KEY="$DIR/munge/munge.key"
[ -f "$KEY" ] || mungekey --create --keyfile="$KEY"
# Unix sockets (munge's, slurmstepd's in the spool folder) must have paths under 108 bytes, and DIR
# can be deep (make test's temporary folders): they live under a short folder of the registry.
SHORT="$REGISTRY/$TAG.d"
mkdir -p "$SHORT/munge" "$SHORT/spool"
chmod 700 "$SHORT/munge"
SOCKET="$SHORT/munge/munge.socket"
# --force: the key and socket live under a world-writable temporary folder. The socket is a file,
# so every namespace (and the root one) reaches it.
on_node 1 munged --force --key-file="$KEY" --socket="$SOCKET" --pid-file="$DIR/munge/munged.pid" \
  --log-file="$DIR/log/munged.log" --seed-file="$DIR/munge/munged.seed"

# slurmd -C prints this machine's node line (CPUs, sockets, cores, memory); every node gets it.
HARDWARE="$(slurmd -C | head -n1 | sed 's/^NodeName=[^ ]* //')"
cat > "$DIR/slurm.conf" <<CONF
ClusterName=bwm$TAG
SlurmctldHost=$(node 1)($(addr 1))
SlurmctldPort=6817
SlurmdPort=6818
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
# cred_expire: also how long a requeued job waits before it starts again (default 120 s).
AuthInfo=socket=$SOCKET,cred_expire=10
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$SHORT/spool/%n
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd-%n.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd-%n.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/builtin
# Pending jobs are tested every 5 s (default 60), so a requeued job starts soon after it may.
SchedulerParameters=sched_interval=5
MpiDefault=none
SwitchType=switch/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MailProg=/bin/true
ReturnToService=2
MinJobAge=3600
KillWait=30
$(for i in $(seq 1 "$NODES"); do echo "NodeName=$(node "$i") NodeAddr=$(addr "$i") $HARDWARE State=UNKNOWN"; done)
PartitionName=debug Nodes=$(node 1)$( [ "$NODES" -gt 1 ] && for i in $(seq 2 "$NODES"); do printf ',%s' "$(node "$i")"; done ) Default=YES MaxTime=INFINITE State=UP
CONF
export SLURM_CONF="$DIR/slurm.conf"
on_node 1 slurmctld -f "$SLURM_CONF"
for i in $(seq 1 "$NODES"); do
  mkdir -p "$SHORT/spool/$(node "$i")"
  on_node "$i" slurmd -f "$SLURM_CONF" -N "$(node "$i")"
done
trap - ERR

for _ in $(seq 1 60); do
  states="$(sinfo -h -N -o %T 2>/dev/null | sort -u | tr '\n' ' ' || true)"
  if [ "$states" = "idle " ] && [ "$(sinfo -h -N -o %N | wc -l)" = "$NODES" ]; then
    echo "start-local: cluster $TAG up ($NODES nodes idle: $(for i in $(seq 1 "$NODES"); do printf '%s=%s ' "$(node "$i")" "$(addr "$i")"; done)); export SLURM_CONF=$SLURM_CONF" >&2
    exit 0
  fi
  sleep 1
done
echo "start-local: the nodes are not idle after 60 s (states: ${states:-none}); logs in $DIR/log" >&2
tail -n 20 "$DIR"/log/*.log >&2 || true
bash "$HERE/stop-local.sh" "$DIR" >&2 || true
exit 1
