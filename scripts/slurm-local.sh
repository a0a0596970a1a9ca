#!/usr/bin/env bash
# A single-node SLURM on this Debian machine, for tests/test_slurm.py and for trying
# `hydra/launcher=slurm` without a cluster:
#
#   scripts/slurm-local.sh          # (make slurm-local) install if missing, configure, start, wait idle
#   scripts/slurm-local.sh stop     # (make slurm-local SLURM_LOCAL=stop) stop the daemons it starts
#   scripts/slurm-local.sh status   # which daemons run, and sinfo
#
# As root. Rerunning is fine: a daemon already running is left alone; a changed slurm.conf restarts
# slurmctld and slurmd. Logs: /var/log/slurm/.
#
# What it takes to run in a container (no systemd, no cgroup delegation):
# - The daemons are started directly, each in the background, not through systemctl or invoke-rc.d
#   (Docker images carry a policy-rc.d that forbids service starts, so apt-get installs them stopped).
# - ProctrackType=proctrack/linuxproc (process tree from /proc) and TaskPlugin=task/none: the cgroup
#   plugins need a writable cgroup hierarchy that a container does not have.
# - Accounting: submitit (hydra-submitit-launcher) polls `sacct` for the state of its jobs; without
#   accounting sacct fails, and a job that ends without writing its result (scancel, node failure)
#   leaves the launcher waiting forever. So slurmdbd runs too, on a MariaDB that listens on its Unix
#   socket only (--skip-networking).
# - NodeAddr/SlurmctldHost are 127.0.0.1: nothing has to resolve the host name, no traffic leaves
#   the machine. CPUs is what `nproc` counts, each CPU a core (SelectTypeParameters=CR_Core then
#   runs one 1-CPU job per CPU at once); RealMemory is 90 % of MemTotal (or of the cgroup limit);
#   SlurmdParameters=config_overrides keeps the node up when the container's view of the hardware
#   differs from the host's.
# - KillWait=5: `scancel` sends SIGTERM, and SIGKILL 5 s later (submitit ignores SIGTERM).
set -euo pipefail

ACTION=${1:-start}
CONF_DIR=/etc/slurm
SLURM_CONF=$CONF_DIR/slurm.conf
DBD_CONF=$CONF_DIR/slurmdbd.conf
RUN_DIR=/run/slurm
LOG_DIR=/var/log/slurm
CLUSTER=pgnn-local
PARTITION=debug
NODE=$(hostname -s)
WAIT_S=${SLURM_LOCAL_WAIT:-180}    # generous: a loaded machine starts MariaDB slowly

say() { echo "slurm-local: $*"; }
die() { echo "slurm-local: error: $*" >&2; exit 1; }
# the CPUs this machine lets us use (GNU nproc would answer OMP_NUM_THREADS, which make exports as 1)
cpus() { env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc; }

# pid of a running daemon from its pid file, if its process still has that name
running() {  # running PIDFILE NAME
  local pid
  [[ -s $1 ]] || return 1
  pid=$(<"$1")
  [[ -r /proc/$pid/comm ]] && [[ $(<"/proc/$pid/comm") == "$2"* ]] && echo "$pid"
}

wait_for() {  # wait_for WHAT COMMAND...: poll until COMMAND succeeds, at most WAIT_S seconds
  local what=$1 deadline=$((SECONDS + WAIT_S)); shift
  until "$@" >/dev/null 2>&1; do
    ((SECONDS < deadline)) || die "$what not ready after ${WAIT_S} s"
    sleep 1
  done
}

stop_pid() {  # stop_pid PIDFILE NAME: SIGTERM, wait up to WAIT_S s for the process to end
  local pid deadline=$((SECONDS + WAIT_S))
  pid=$(running "$1" "$2") || return 0
  say "stopping $2 (pid $pid)"
  kill "$pid" 2>/dev/null || true
  while [[ -e /proc/$pid ]] && ((SECONDS < deadline)); do sleep 0.5; done
  [[ -e /proc/$pid ]] && die "$2 (pid $pid) still running after ${WAIT_S} s"
  rm -f "$1"
}

status() {
  local name file
  for name in munged:/run/munge/munged.pid mariadbd:/run/mysqld/mysqld.pid slurmdbd:$RUN_DIR/slurmdbd.pid \
              slurmctld:$RUN_DIR/slurmctld.pid slurmd:$RUN_DIR/slurmd.pid; do
    file=${name#*:}; name=${name%%:*}
    if pid=$(running "$file" "$name"); then echo "  $name running (pid $pid)"; else echo "  $name stopped"; fi
  done
  command -v sinfo >/dev/null && sinfo 2>&1 || true
}

stop() {
  [[ $EUID -eq 0 ]] || die "run as root"
  stop_pid $RUN_DIR/slurmd.pid slurmd
  stop_pid $RUN_DIR/slurmctld.pid slurmctld
  stop_pid $RUN_DIR/slurmdbd.pid slurmdbd
  stop_pid /run/mysqld/mysqld.pid mariadbd
  stop_pid /run/munge/munged.pid munged
  say "stopped"
}

install_packages() {
  local missing=()
  command -v slurmctld >/dev/null || missing+=(slurmctld)
  command -v slurmd >/dev/null || missing+=(slurmd)
  command -v sbatch >/dev/null || missing+=(slurm-client)
  command -v slurmdbd >/dev/null || missing+=(slurmdbd)
  command -v munged >/dev/null || missing+=(munge)
  command -v mariadbd >/dev/null || missing+=(mariadb-server)
  ((${#missing[@]})) || return 0
  say "installing slurm-wlm munge slurmdbd mariadb-server (missing: ${missing[*]})"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    slurm-wlm munge slurmdbd mariadb-server >/dev/null
}

write_if_changed() {  # write_if_changed FILE MODE OWNER < content; returns 0 if the file changed
  local tmp; tmp=$(mktemp "$1.XXXXXX")
  cat >"$tmp"
  if [[ -f $1 ]] && cmp -s "$tmp" "$1"; then rm -f "$tmp"; return 1; fi
  chmod "$2" "$tmp"; chown "$3" "$tmp"; mv -f "$tmp" "$1"
  return 0
}

start_munge() {
  if [[ ! -s /etc/munge/munge.key ]]; then
    say "creating the munge key"
    mungekey --create --keyfile=/etc/munge/munge.key
  fi
  chown munge:munge /etc/munge/munge.key; chmod 0400 /etc/munge/munge.key
  install -d -o munge -g munge -m 0755 /run/munge
  if ! running /run/munge/munged.pid munged >/dev/null; then
    say "starting munged"
    runuser -u munge -- /usr/sbin/munged   # daemonizes itself
  fi
  wait_for "munge" bash -c 'munge -n | unmunge'
}

start_mariadb() {
  install -d -o mysql -g mysql -m 0755 /run/mysqld
  if [[ ! -d /var/lib/mysql/mysql ]]; then
    say "initialising MariaDB's data directory"
    mariadb-install-db --user=mysql --datadir=/var/lib/mysql >/dev/null
  fi
  if ! running /run/mysqld/mysqld.pid mariadbd >/dev/null; then
    say "starting MariaDB (Unix socket only)"
    setsid /usr/sbin/mariadbd --user=mysql --skip-networking --innodb-lock-wait-timeout=900 \
      </dev/null >>$LOG_DIR/mariadb.log 2>&1 &
  fi
  wait_for "MariaDB" mariadb-admin ping
}

db_password() {  # the slurm database user's password: the one slurmdbd.conf holds, else a new one
  local pass=""
  [[ -f $DBD_CONF ]] && pass=$(sed -n 's/^StoragePass=//p' "$DBD_CONF")
  [[ -n $pass ]] || pass=$(head -c 18 /dev/urandom | base64 | tr -d '/+=')
  echo "$pass"
}

start_slurmdbd() {
  local pass; pass=$(db_password)
  mariadb -e "CREATE USER IF NOT EXISTS 'slurm'@'localhost'; ALTER USER 'slurm'@'localhost' IDENTIFIED BY '$pass';
              CREATE DATABASE IF NOT EXISTS slurm_acct_db; GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost';"
  write_if_changed "$DBD_CONF" 0600 slurm:slurm <<EOF || true
# written by scripts/slurm-local.sh
AuthType=auth/munge
DbdHost=localhost
DbdAddr=127.0.0.1
SlurmUser=slurm
StorageType=accounting_storage/mysql
StorageHost=localhost
StorageUser=slurm
StoragePass=$pass
StorageLoc=slurm_acct_db
LogFile=$LOG_DIR/slurmdbd.log
PidFile=$RUN_DIR/slurmdbd.pid
EOF
  if ! running $RUN_DIR/slurmdbd.pid slurmdbd >/dev/null; then
    say "starting slurmdbd"
    /usr/sbin/slurmdbd             # daemonizes itself
  fi
  wait_for "slurmdbd" sacctmgr -n list cluster
  if ! sacctmgr -n -P list cluster format=cluster | grep -qx "$CLUSTER"; then
    sacctmgr -i add cluster "$CLUSTER" >/dev/null
  fi
}

slurm_conf() {
  local cpus mem_mb limit_mb
  cpus=$(cpus)
  mem_mb=$(awk '/^MemTotal:/ {print int($2 / 1024)}' /proc/meminfo)
  for f in /sys/fs/cgroup/memory.max /sys/fs/cgroup/memory/memory.limit_in_bytes; do
    if [[ -r $f ]] && [[ $(<"$f") =~ ^[0-9]+$ ]]; then
      limit_mb=$(($(<"$f") / 1048576))
      ((limit_mb < mem_mb)) && mem_mb=$limit_mb
    fi
  done
  mem_mb=$((mem_mb * 9 / 10))
  cat <<EOF
# written by scripts/slurm-local.sh: one node, this machine, controller and compute node at once
ClusterName=$CLUSTER
SlurmctldHost=$NODE(127.0.0.1)
SlurmUser=slurm
AuthType=auth/munge
MpiDefault=none
# no cgroups in a container
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/linux
# several 1-CPU jobs at once
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
# sacct (submitit polls it) through slurmdbd
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=127.0.0.1
JobCompType=jobcomp/none
ReturnToService=2
SlurmdParameters=config_overrides
KillWait=5
StateSaveLocation=/var/spool/slurmctld
SlurmdSpoolDir=/var/spool/slurmd
SlurmctldPidFile=$RUN_DIR/slurmctld.pid
SlurmdPidFile=$RUN_DIR/slurmd.pid
SlurmctldLogFile=$LOG_DIR/slurmctld.log
SlurmdLogFile=$LOG_DIR/slurmd.log
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=$PARTITION Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
}

node_state() { sinfo -h -n "$NODE" -o %t 2>/dev/null | head -1; }

node_idle() { [[ $(node_state) == idle* || $(node_state) == mix* || $(node_state) == alloc* ]]; }

start() {
  [[ $EUID -eq 0 ]] || die "run as root"
  command -v apt-get >/dev/null || die "needs a Debian machine (apt-get)"
  install_packages
  install -d -o slurm -g slurm -m 0755 $RUN_DIR $LOG_DIR /var/spool/slurmctld
  install -d -m 0755 /var/spool/slurmd
  local changed=false           # first: sacctmgr (in start_slurmdbd) reads it too
  if slurm_conf | write_if_changed "$SLURM_CONF" 0644 root:root; then changed=true; fi
  start_munge
  start_mariadb
  start_slurmdbd
  if $changed; then            # a new configuration: daemons started with the old one restart
    stop_pid $RUN_DIR/slurmd.pid slurmd
    stop_pid $RUN_DIR/slurmctld.pid slurmctld
  fi
  if ! running $RUN_DIR/slurmctld.pid slurmctld >/dev/null; then
    say "starting slurmctld"
    /usr/sbin/slurmctld          # daemonizes itself
  fi
  wait_for "slurmctld" scontrol ping
  if ! running $RUN_DIR/slurmd.pid slurmd >/dev/null; then
    say "starting slurmd"
    /usr/sbin/slurmd             # daemonizes itself
  fi
  # a node left down or drained by an earlier run (e.g. the machine rebooted with jobs on it)
  case $(node_state) in
    down*|drain*|drng*|fail*) scontrol update NodeName="$NODE" State=RESUME || true ;;
  esac
  wait_for "node $NODE idle in sinfo (see $LOG_DIR/slurmd.log)" node_idle
  say "up: partition $PARTITION, node $NODE, $(cpus) CPUs"
  sinfo
}

case $ACTION in
  start) start ;;
  stop) stop ;;
  status) status ;;
  *) die "usage: $0 [start|stop|status]" ;;
esac
