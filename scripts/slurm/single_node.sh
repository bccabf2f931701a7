#!/bin/bash
# Bring up a throw-away single-node SLURM (munge + slurmctld + slurmd, no systemd, no cgroups),
# submit a sharded campaign with `freefall campaign slurm --submit`, wait for the dependent merge
# job, and stop the daemons this script started (by PID).
#
#   scripts/slurm/single_node.sh FREEFALL_BINARY CAMPAIGN.toml SHARDS WORKDIR
#
# Exit 0: WORKDIR/slurm/merged holds the merged tables. Exit 77: SLURM could not be installed or
# started here (the caller reports a visible skip). Anything else: failure.
set -uo pipefail
BIN=$1; CAMPAIGN=$2; SHARDS=$3; WORK=$4
mkdir -p "$WORK"
skip() { echo "SKIP: $*" >&2; exit 77; }

if ! command -v sbatch >/dev/null || ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! [ -x /usr/sbin/munged ]; then
    [ "$(id -u)" = 0 ] || skip "SLURM is not installed and we are not root"
    command -v apt-get >/dev/null || skip "SLURM is not installed and there is no apt-get"
    echo "installing munge and slurm (apt-get)" >&2
    export DEBIAN_FRONTEND=noninteractive
    (apt-get update && apt-get install -y --no-install-recommends munge slurmctld slurmd slurm-client) \
        > "$WORK/apt.log" 2>&1 || skip "apt-get install munge slurmctld slurmd slurm-client failed (see $WORK/apt.log)"
fi
[ "$(id -u)" = 0 ] || skip "starting munged/slurmd needs root"

PIDS=()
cleanup() {
    for p in "${PIDS[@]}"; do
        [ -n "$p" ] && kill "$p" 2>/dev/null
    done
    sleep 1
    for p in "${PIDS[@]}"; do
        [ -n "$p" ] && kill -9 "$p" 2>/dev/null
    done
}
trap cleanup EXIT

# munge: key, /run/munge owned by munge, daemon as the munge user.
if ! [ -s /etc/munge/munge.key ]; then
    mkdir -p /etc/munge
    if [ -x /usr/sbin/mungekey ]; then /usr/sbin/mungekey -c -f -k /etc/munge/munge.key; else dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 2>/dev/null; fi
    chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
fi
mkdir -p /run/munge /var/lib/munge /var/log/munge && chown munge:munge /run/munge /var/lib/munge /var/log/munge
MUNGE_STARTED=0
if ! munge -n </dev/null >/dev/null 2>&1; then
    runuser -u munge -- /usr/sbin/munged || skip "munged does not start"
    MUNGE_STARTED=1
    for _ in $(seq 50); do [ -s /run/munge/munged.pid ] && break; sleep 0.1; done
    PIDS+=("$(cat /run/munge/munged.pid 2>/dev/null)")
fi
munge -n </dev/null | unmunge >/dev/null 2>&1 || skip "munge does not work"

HOST=$(hostname -s)
S="$WORK/slurm-state"
mkdir -p "$S/ctld" "$S/d"
NODE=$(slurmd -C 2>/dev/null | grep '^NodeName=' | sed "s/^NodeName=[^ ]*/NodeName=$HOST/" | sed 's/ UpTime=.*//')
[ -n "$NODE" ] || NODE="NodeName=$HOST CPUs=$(nproc)"
CONF="$S/slurm.conf"
cat > "$CONF" <<CONF
ClusterName=freefall-test
SlurmctldHost=$HOST
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/backfill
ReturnToService=2
MpiDefault=none
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
StateSaveLocation=$S/ctld
SlurmdSpoolDir=$S/d
SlurmctldPidFile=$S/slurmctld.pid
SlurmdPidFile=$S/slurmd.pid
SlurmctldLogFile=$S/slurmctld.log
SlurmdLogFile=$S/slurmd.log
SlurmctldPort=16817
SlurmdPort=16818
$NODE State=UNKNOWN
PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF
export SLURM_CONF="$CONF"
slurmctld -c -f "$CONF" || skip "slurmctld does not start (see $S/slurmctld.log)"
for _ in $(seq 50); do [ -s "$S/slurmctld.pid" ] && break; sleep 0.1; done
PIDS+=("$(cat "$S/slurmctld.pid" 2>/dev/null)")
slurmd -f "$CONF" || skip "slurmd does not start (see $S/slurmd.log)"
for _ in $(seq 50); do [ -s "$S/slurmd.pid" ] && break; sleep 0.1; done
PIDS+=("$(cat "$S/slurmd.pid" 2>/dev/null)")
ok=0
for _ in $(seq 150); do
    st=$(sinfo -h -o %t 2>/dev/null | head -1)
    case "$st" in idle*|mix*|alloc*) ok=1; break;; esac
    sleep 0.2
done
[ $ok = 1 ] || skip "the node never became idle (state '$st'; see $S/slurmd.log)"
echo "slurm up: node $HOST $(sinfo -h -o '%c CPUs %m MB')" >&2

"$BIN" campaign slurm "$CAMPAIGN" --shards "$SHARDS" --out "$WORK/slurm" --time 00:10:00 --mem 200M --cpus-per-task 1 --submit || exit 1
for _ in $(seq 600); do
    [ -s "$WORK/slurm/merged/manifest.json" ] && break
    if [ -z "$(squeue -h 2>/dev/null)" ] && ! [ -s "$WORK/slurm/merged/manifest.json" ]; then
        sleep 1
        [ -s "$WORK/slurm/merged/manifest.json" ] && break
        echo "queue empty but no merged output; logs:" >&2; tail -n 5 "$WORK"/slurm/logs/* >&2; exit 1
    fi
    sleep 0.2
done
[ -s "$WORK/slurm/merged/manifest.json" ] || { echo "timed out waiting for the merge job" >&2; squeue >&2; exit 1; }
echo "merged output in $WORK/slurm/merged" >&2
exit 0
