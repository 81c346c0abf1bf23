#!/usr/bin/env bash
# A SLURM cluster of the project's own, for the cluster tests (make test-cluster).
#   cluster/slurm.sh start [NODES]  starts a cluster of NODES compute nodes (1 or 2, default 2)
#                                   and prints what a client needs, one KEY=VALUE a line:
#                                   SLURM_CONF=<its slurm.conf>, NETNS=<the namespace its
#                                   clients run in>, NODES=<node names>, and STARTED=<pids> when
#                                   this call started it (the caller owns it and stops it)
#   cluster/slurm.sh stop           cancels its jobs and stops what `start` started, by pid
#
# Layout: every daemon runs in a Linux network namespace this script creates, so nothing binds
# an interface of the machine. The controller namespace (fhs-ctl, 10.79.0.1, the "login node")
# holds slurmctld, slurmdbd and a MariaDB of its own (accounting, so that sacct sees every job);
# each compute node is a namespace (fhs-n1 10.79.0.11, fhs-n2 10.79.0.12) with its own host name
# (a UTS namespace) running one slurmd, joined to the controller by a veth pair on a bridge
# inside fhs-ctl. Names resolve through /etc/netns/<namespace>/hosts, which each daemon has
# mounted over /etc/hosts (as `ip netns exec` does for clients). Every node sees this machine's filesystem: the shared filesystem of a
# real cluster. munged (the munge user, a socket and key of its own) authenticates them all.
# Clients (sbatch, squeue, sacct, fedhpg-cluster) run with `ip netns exec fhs-ctl` and
# SLURM_CONF set. A cluster this script started that still answers is reused (no STARTED line).
#
# As root, where Debian's packages are reachable, it installs slurmctld, slurmd, slurmdbd,
# slurm-client, munge and mariadb-server (no daemon is started by the packages). Exit 3 with
# one line on stderr when no cluster can run here (the tests then skip, saying why).
set -euo pipefail
# shellcheck source=cluster/apt_install.sh
source "$(dirname "${BASH_SOURCE[0]}")/apt_install.sh"

STATE=${FEDHPG_SLURM_STATE:-/run/fedhpg-slurm}
NET=10.79.0
CTL=fhs-ctl
CPUS_PER_NODE=8          # more than the machine has (config_overrides): jobs wait on nothing
MEM_PER_NODE_MB=16384
PACKAGES=(slurmctld slurmd slurmdbd slurm-client munge mariadb-server)
export SLURM_CONF=$STATE/slurm.conf

cannot() { echo "no SLURM cluster here: $*" >&2; exit 3; }
node_name() { echo "fhs-n$1"; }
in_ctl() { ip netns exec "$CTL" "$@"; }

# launch_on HOST LOG COMMAND...: a daemon on a "host": its network namespace, its own host name
# and hosts file. nsenter, not `ip netns exec`, which would mount a sysfs without the cgroup
# hierarchy slurmd needs.
launch_on() {
    local name=$1 log=$2; shift 2
    launch "$log" nsenter --net="/run/netns/$name" unshare --uts --mount sh -c \
        'h=$1; shift; hostname "$h" && mount --bind "/etc/netns/$h/hosts" /etc/hosts && exec "$@"' \
        sh "$name" "$@"
}

answers() {
    [ -f "$STATE/pids" ] && [ -f "$SLURM_CONF" ] || return 1
    local pid
    for pid in $(cat "$STATE/pids"); do kill -0 "$pid" 2>/dev/null || return 1; done
    timeout 10 ip netns exec "$CTL" sinfo -h >/dev/null 2>&1
}

install_packages() {
    local missing=() command
    for command in slurmctld slurmd slurmdbd sbatch munged mariadbd; do
        command -v "$command" >/dev/null || missing+=("$command")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    [ "$(id -u)" -eq 0 ] || cannot "${missing[*]} not installed and not root to install them"
    command -v apt-get >/dev/null || cannot "${missing[*]} not installed and no apt-get"
    echo "installing ${PACKAGES[*]} (apt-get)" >&2
    local status=0
    apt_install "$STATE/apt.log" "${PACKAGES[@]}" || status=$?
    [ $status -eq 0 ] || cannot "apt-get install ${PACKAGES[*]} failed (exit $status, $STATE/apt.log)"
}

check_machine() {
    [ "$(id -u)" -eq 0 ] || cannot "its daemons and network namespaces need root"
    local tool
    for tool in ip nsenter unshare setpriv; do
        command -v $tool >/dev/null || cannot "'$tool' is not installed"
    done
    ip netns add fhs-probe 2>/dev/null || cannot "cannot create network namespaces here"
    ip netns del fhs-probe
}

# Start a daemon in the foreground, detached (setsid); the wrappers exec, so $! is its pid.
launch() {
    local log=$1; shift
    setsid "$@" >>"$log" 2>&1 </dev/null &
    echo $! >> "$STATE/pids"
}

wait_for() {  # wait_for SECONDS WHAT COMMAND...: until COMMAND succeeds
    local seconds=$1 what=$2; shift 2
    local i pid why="did not start within $seconds s"
    for i in $(seq 1 $((seconds * 4))); do
        "$@" >/dev/null 2>&1 && return 0
        for pid in $(cat "$STATE/pids"); do
            kill -0 "$pid" 2>/dev/null || { why="exited (pid $pid)"; break 2; }
        done
        sleep 0.25
    done
    rm -rf "$STATE.log" && cp -r "$STATE/log" "$STATE.log"  # stop removes the state
    stop >/dev/null 2>&1 || true
    cannot "$what $why (logs in $STATE.log)"
}

make_network() {
    local nodes=$1 n name hosts
    hosts="127.0.0.1 localhost\n$NET.1 $CTL"
    for n in $(seq 1 "$nodes"); do hosts="$hosts\n$NET.1$n $(node_name "$n")"; done
    for name in "$CTL" $(for n in $(seq 1 "$nodes"); do node_name "$n"; done); do
        ip netns add "$name"
        echo "$name" >> "$STATE/namespaces"
        ip -n "$name" link set lo up
        mkdir -p "/etc/netns/$name"
        printf "$hosts\n" > "/etc/netns/$name/hosts"
    done
    ip -n "$CTL" link add fhs-br type bridge
    ip -n "$CTL" addr add "$NET.1/24" dev fhs-br
    ip -n "$CTL" link set fhs-br up
    for n in $(seq 1 "$nodes"); do
        name=$(node_name "$n")
        ip -n "$CTL" link add "fhs-v$n" type veth peer name eth0 netns "$name"
        ip -n "$CTL" link set "fhs-v$n" master fhs-br up
        ip -n "$name" addr add "$NET.1$n/24" dev eth0
        ip -n "$name" link set eth0 up
    done
}

write_config() {
    local nodes=$1 n password
    password=$(head -c 18 /dev/urandom | base64 | tr -d '/+=')
    echo "$password" > "$STATE/db/password"
    cat > "$SLURM_CONF" <<EOF
# Written by cluster/slurm.sh: a private cluster in network namespaces.
ClusterName=fedhpg
SlurmctldHost=$CTL($NET.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$STATE/munge/munge.socket
CredType=cred/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/spool/%n
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd-%n.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd-%n.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SlurmdParameters=config_overrides
SchedulerType=sched/backfill
SchedulerParameters=sched_interval=2
ReturnToService=2
MpiDefault=none
SwitchType=switch/none
KillWait=5
MinJobAge=600
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=127.0.0.1
AccountingStoragePass=$STATE/munge/munge.socket
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
EOF
    for n in $(seq 1 "$nodes"); do
        echo "NodeName=$(node_name "$n") NodeAddr=$NET.1$n CPUs=$CPUS_PER_NODE RealMemory=$MEM_PER_NODE_MB State=UNKNOWN" >> "$SLURM_CONF"
    done
    # LLN: each job on the least loaded node, so a federation spreads over the nodes.
    echo "PartitionName=fedhpg Nodes=ALL Default=YES MaxTime=INFINITE LLN=YES State=UP" >> "$SLURM_CONF"
    cat > "$STATE/slurmdbd.conf" <<EOF
AuthType=auth/munge
AuthInfo=socket=$STATE/munge/munge.socket
DbdHost=$CTL
DbdAddr=127.0.0.1
SlurmUser=root
PidFile=$STATE/slurmdbd.pid
LogFile=$STATE/log/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort=3306
StorageUser=slurm
StoragePass=$password
StorageLoc=slurm_acct_db
EOF
    chmod 600 "$STATE/slurmdbd.conf"
}

start_munge() {
    local dir=$STATE/munge
    mkdir -p "$dir"
    head -c 1024 /dev/urandom > "$dir/munge.key"
    chmod 755 "$dir"; chmod 400 "$dir/munge.key"; chown -R munge:munge "$dir"
    launch "$STATE/log/munged.out" setpriv --reuid=munge --regid=munge --clear-groups \
        munged --foreground --socket="$dir/munge.socket" --key-file="$dir/munge.key" \
        --pid-file="$dir/munged.pid" --log-file="$dir/munged.log" --seed-file="$dir/munged.seed"
    wait_for 20 munged sh -c "munge -n -S '$dir/munge.socket' | unmunge -S '$dir/munge.socket'"
}

start_database() {
    local db=$STATE/db
    mkdir -p "$db/data" "$db/run"; chown -R mysql:mysql "$db/data" "$db/run"
    mariadb-install-db --no-defaults --user=mysql --datadir="$db/data" --skip-test-db \
        --auth-root-authentication-method=socket >"$STATE/log/mariadb-install.log" 2>&1 \
        || cannot "mariadb-install-db failed ($STATE/log/mariadb-install.log)"
    launch "$STATE/log/mariadb.log" nsenter --net="/run/netns/$CTL" mariadbd --no-defaults --user=mysql \
        --datadir="$db/data" --socket="$db/run/mysqld.sock" --pid-file="$db/run/mariadbd.pid" \
        --bind-address=127.0.0.1 --port=3306 --skip-log-bin --innodb-buffer-pool-size=32M
    wait_for 60 MariaDB mariadb-admin --no-defaults --socket="$db/run/mysqld.sock" ping
    local password; password=$(cat "$db/password")
    mariadb --no-defaults --socket="$db/run/mysqld.sock" -u root -e "
        CREATE USER 'slurm'@'127.0.0.1' IDENTIFIED BY '$password';
        CREATE USER 'slurm'@'localhost' IDENTIFIED BY '$password';
        GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';
        GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost';"
}

start() {
    local nodes=${1:-2}
    case "$nodes" in 1|2) ;; *) echo "usage: $0 start [1|2]" >&2; exit 2 ;; esac
    if answers; then
        echo "SLURM_CONF=$SLURM_CONF"; echo "NETNS=$CTL"; echo "NODES=$(cat "$STATE/nodes")"
        return 0
    fi
    check_machine
    stop >/dev/null 2>&1 || true  # what a failed start may have left
    install_packages
    mkdir -p "$STATE/log" "$STATE/ctld" "$STATE/spool" "$STATE/db"
    : > "$STATE/pids"; : > "$STATE/namespaces"
    make_network "$nodes"
    write_config "$nodes"
    start_munge
    start_database
    launch_on "$CTL" "$STATE/log/slurmdbd.out" slurmdbd -D
    wait_for 60 slurmdbd in_ctl bash -c "exec 3<>/dev/tcp/127.0.0.1/6819"
    launch_on "$CTL" "$STATE/log/slurmctld.out" slurmctld -D -i
    wait_for 60 slurmctld in_ctl sinfo -h
    local n names=()
    for n in $(seq 1 "$nodes"); do
        names+=("$(node_name "$n")")
        mkdir -p "$STATE/spool/$(node_name "$n")"
        launch_on "$(node_name "$n")" "$STATE/log/slurmd-$(node_name "$n").out" slurmd -D
    done
    echo "${names[*]}" | tr ' ' ',' > "$STATE/nodes"
    # every node idle (registered), and the cluster known to the accounting database
    wait_for 60 "the compute nodes" in_ctl sh -c \
        "[ \"\$(sinfo -h -N -t idle -o %N | sort -u | wc -l)\" -eq $nodes ]"
    wait_for 30 "accounting" in_ctl sh -c "sacctmgr -n -P list cluster format=cluster | grep -qx fedhpg"
    echo "SLURM_CONF=$SLURM_CONF"; echo "NETNS=$CTL"; echo "NODES=$(cat "$STATE/nodes")"
    echo "STARTED=$(tr '\n' ',' < "$STATE/pids" | sed 's/,$//')"
}

pids_in_namespace() { ip netns pids "$1" 2>/dev/null || true; }

stop() {
    [ -d "$STATE" ] || return 0
    # its jobs first (while the controller still runs): their steps end with them
    if [ -f "$STATE/pids" ] && in_ctl squeue -h >/dev/null 2>&1; then
        local jobs; jobs=$(in_ctl squeue -h -o %A 2>/dev/null || true)
        if [ -n "$jobs" ]; then
            # shellcheck disable=SC2086
            in_ctl scancel $jobs 2>/dev/null || true
            for _ in $(seq 1 60); do
                [ -z "$(in_ctl squeue -h -o %A 2>/dev/null)" ] && break
                sleep 0.5
            done
        fi
    fi
    # the daemons, by the pids recorded when each started; last started, first stopped
    local pid
    if [ -f "$STATE/pids" ]; then
        for pid in $(tac "$STATE/pids"); do kill "$pid" 2>/dev/null || true; done
        for pid in $(tac "$STATE/pids"); do
            for _ in $(seq 1 60); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
            kill -9 "$pid" 2>/dev/null || true
        done
    fi
    # anything else still in its namespaces (a job step's processes), by pid, then the namespaces
    local name
    if [ -f "$STATE/namespaces" ]; then
        for name in $(cat "$STATE/namespaces"); do
            for pid in $(pids_in_namespace "$name"); do kill -9 "$pid" 2>/dev/null || true; done
        done
        for name in $(cat "$STATE/namespaces"); do
            for _ in $(seq 1 20); do [ -z "$(pids_in_namespace "$name")" ] && break; sleep 0.25; done
            ip netns del "$name" 2>/dev/null || true
            rm -rf "/etc/netns/$name"
        done
    fi
    # apt.log stays: it says what an install did
    find "$STATE" -mindepth 1 -maxdepth 1 ! -name apt.log -exec rm -rf {} +
    rmdir "$STATE" /etc/netns 2>/dev/null || true  # when nothing else is left there
}

case "${1:-}" in
    start) start "${2:-2}" ;;
    stop) stop ;;
    *) echo "usage: $0 start [1|2] | stop" >&2; exit 2 ;;
esac
