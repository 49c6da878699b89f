#!/usr/bin/env bash
# A one-host Slurm cluster (munged, slurmctld, slurmd) for tests/slurm.rs and for trying
# `bwm submit`: configuration, keys, state, sockets and logs all live under DIR, and the daemons
# run as the calling user (root). Needs Debian's slurm-wlm and munge (scripts/setup.sh).
#   scripts/slurm/start-local.sh DIR      then   export SLURM_CONF=DIR/slurm.conf
# Ports: BWM_SLURMCTLD_PORT (default 6817) and BWM_SLURMD_PORT (default 6818).
# Stop it with scripts/slurm/stop-local.sh DIR.
set -euo pipefail
DIR="${1:?usage: $0 DIR}"
CTLD_PORT="${BWM_SLURMCTLD_PORT:-6817}"
SLURMD_PORT="${BWM_SLURMD_PORT:-6818}"
for tool in munged slurmctld slurmd sinfo; do
  command -v "$tool" >/dev/null || { echo "start-local: $tool is not installed (scripts/setup.sh installs slurm-wlm and munge)" >&2; exit 1; }
done
mkdir -p "$DIR"
DIR="$(cd "$DIR" && pwd)"
mkdir -p "$DIR/munge" "$DIR/state" "$DIR/spool" "$DIR/log"
chmod 700 "$DIR/munge"

KEY="$DIR/munge/munge.key"
[ -f "$KEY" ] || mungekey --create --keyfile="$KEY"
SOCKET="$DIR/munge/munge.socket"
# --force: the key and socket live under a world-writable temporary folder.
munged --force --key-file="$KEY" --socket="$SOCKET" --pid-file="$DIR/munge/munged.pid" \
  --log-file="$DIR/log/munged.log" --seed-file="$DIR/munge/munged.seed"

NODE="$(hostname -s)"
# slurmd -C prints this host's node line (CPUs, sockets, cores, memory) as slurmd will see them.
NODE_LINE="$(slurmd -C | head -n1)"
cat > "$DIR/slurm.conf" <<CONF
ClusterName=bwmlocal
SlurmctldHost=$NODE(127.0.0.1)
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
# cred_expire: also how long a requeued job waits before it starts again (default 120 s).
AuthInfo=socket=$SOCKET,cred_expire=10
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
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
$NODE_LINE NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=debug Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
CONF
export SLURM_CONF="$DIR/slurm.conf"
slurmctld -f "$SLURM_CONF"
slurmd -f "$SLURM_CONF" -N "$NODE"

for _ in $(seq 1 60); do
  state="$(sinfo -h -n "$NODE" -o %T 2>/dev/null || true)"
  if [ "$state" = idle ]; then
    echo "start-local: cluster up (node $NODE idle); export SLURM_CONF=$SLURM_CONF" >&2
    exit 0
  fi
  sleep 1
done
echo "start-local: node $NODE is not idle after 60 s (state: ${state:-none}); logs in $DIR/log" >&2
tail -n 20 "$DIR/log/slurmctld.log" "$DIR/log/slurmd.log" >&2 || true
exit 1
