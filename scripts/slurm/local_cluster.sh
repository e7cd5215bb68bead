#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, for the tests and for trying the launcher on a laptop:
#   sudo scripts/slurm/local_cluster.sh start     installs slurm-wlm and munge (Debian/Ubuntu) if absent,
#                                                 writes /etc/slurm/slurm.conf for this host, starts
#                                                 munged, slurmctld and slurmd; waits until the node is idle
#   sudo scripts/slurm/local_cluster.sh stop      stops what `start` started (by PID)
#   scripts/slurm/local_cluster.sh status         sinfo, or why not
# Needs root (the daemons, /etc/slurm, jobs run as the submitting user). One partition, `debug`,
# the default, no time limit, every core and the memory of /proc/meminfo. No accounting daemon:
# `sacct` has nothing to show; finished jobs are listed in $STATE/jobcomp.log (and by
# `scontrol show job ID` for five minutes).
# The daemons run in the foreground (-D) of background processes, their PIDs in $STATE/*.pid:
# no systemd is needed (containers, CI).
set -euo pipefail

STATE="${E3CM_SLURM_STATE:-/var/lib/e3cm-slurm}"
CONF=/etc/slurm/slurm.conf
MARK="# written by e3cm-bench scripts/slurm/local_cluster.sh"

die() { echo "local_cluster.sh: $*" >&2; exit 1; }

answers() { timeout 10 sinfo -h >/dev/null 2>&1; }

install() {
  command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v munged >/dev/null && return
  command -v apt-get >/dev/null || die "slurmctld, slurmd or munged not found and no apt-get to install them"
  echo "installing slurm-wlm and munge (apt-get)"
  { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurm-wlm munge; } >/dev/null \
    || die "apt-get install slurm-wlm munge failed"
}

write_conf() {
  if [ -f "$CONF" ] && ! grep -qF "$MARK" "$CONF"; then
    die "$CONF exists and was not written by this script; not replacing it"
  fi
  local host cpus mem
  host="$(hostname -s)"
  cpus="$(nproc)"
  # slurmd refuses a node whose configured memory exceeds what it finds: MemTotal, in MiB
  mem="$(awk '/^MemTotal:/ {print int($2 / 1024)}' /proc/meminfo)"
  mkdir -p /etc/slurm "$STATE/ctld" "$STATE/d"
  cat > "$CONF" <<EOF
$MARK
# one node ($host): $cpus CPUs, $mem MiB; state and logs in $STATE
ClusterName=e3cm-local
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=$STATE/ctld.pid
SlurmdPidFile=$STATE/d.pid
SlurmctldLogFile=$STATE/slurmctld.log
SlurmdLogFile=$STATE/slurmd.log
# no cgroups in a container: processes are tracked through /proc, tasks are not bound
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/filetxt
JobCompLoc=$STATE/jobcomp.log
# a job past its time limit is killed at once (SIGTERM, then SIGKILL 5 s later)
OverTimeLimit=0
KillWait=5
MinJobAge=300
SlurmdTimeout=60
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
}

alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

start() {
  [ "$(id -u)" = 0 ] || die "must run as root (the SLURM daemons and /etc/slurm)"
  if answers; then
    echo "a SLURM controller already answers (sinfo); nothing started"
    sinfo
    return
  fi
  install
  write_conf
  mkdir -p "$STATE"
  # munge: the key the package made (or a new one); munged as the munge user
  if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    if [ ! -s /etc/munge/munge.key ]; then
      mkdir -p /etc/munge
      dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 2>/dev/null
      chown munge:munge /etc/munge/munge.key
      chmod 400 /etc/munge/munge.key
    fi
    mkdir -p /run/munge
    chown munge:munge /run/munge
    # setpriv execs munged as the munge user: the PID recorded is munged's own
    setsid setpriv --reuid=munge --regid=munge --init-groups /usr/sbin/munged -F >"$STATE/munged.out" 2>&1 </dev/null &
    echo $! > "$STATE/munged.pid"
    for _ in $(seq 50); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.2; done
    munge -n | unmunge >/dev/null || die "munged did not start ($STATE/munged.out)"
  fi
  for daemon in slurmctld slurmd; do
    if alive "$STATE/$daemon.pid"; then continue; fi
    # -D: foreground (its PID is the daemon's); -c: forget any old jobs of an earlier cluster
    setsid "$daemon" -D -c >"$STATE/$daemon.out" 2>&1 </dev/null &
    echo $! > "$STATE/$daemon.pid"
  done
  for _ in $(seq 60); do
    if answers && sinfo -h -o %t | grep -q idle; then
      sinfo
      return
    fi
    sleep 0.5
  done
  tail -n 5 "$STATE"/slurmctld.log "$STATE"/slurmd.log >&2 || true
  die "the node did not become idle within 30 s (logs above; stop with: $0 stop)"
}

stop() {
  local stopped=0
  for daemon in slurmd slurmctld munged; do
    local file="$STATE/$daemon.pid"
    [ -f "$file" ] || continue
    local pid
    pid="$(cat "$file")"
    if kill -0 "$pid" 2>/dev/null; then
      kill "$pid"
      for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
      kill -0 "$pid" 2>/dev/null && kill -9 "$pid"
      stopped=$((stopped + 1))
    fi
    rm -f "$file"
  done
  echo "stopped $stopped process(es) started by $0 start"
}

case "${1:-}" in
  start) start ;;
  stop) stop ;;
  status) if answers; then sinfo; else echo "no SLURM controller answers"; exit 1; fi ;;
  *) echo "usage: $0 start|stop|status" >&2; exit 2 ;;
esac
