#!/usr/bin/env bash
# A Ray cluster of the project's own, for the cluster tests (make test-cluster).
#   cluster/ray.sh start [NODES]   starts a Ray cluster of NODES nodes (1 or 2, default 2) and
#                                  prints what a client needs, one KEY=VALUE a line:
#                                  RAY_ADDRESS=<head's GCS address>, NETNS=<the namespace its
#                                  clients run in>, NODES=<node names>, and STARTED=<pids>
#                                  when this call started it (the caller owns it and stops it)
#   cluster/ray.sh stop            stops what `start` started, by pid
#
# Layout: each Ray node runs in a Linux network namespace this script creates, so nothing binds
# an interface of the machine: the head (fhr-head, 10.80.0.1, where clients run) and a worker
# node (fhr-n1, 10.80.0.11), each with its name as its host name (a UTS namespace), joined by a
# veth pair on a bridge inside fhr-head. Each node is
# `ray start ... --block` (it stops its own processes when it is sent SIGTERM); every node sees
# this machine's filesystem and Python environment, as the nodes of a real cluster see a shared
# filesystem and one image. A cluster this script started that still answers is reused.
#
# Ray comes from the Python environment FEDHPG_PYTHON (default .venv/bin/python): where it is
# missing, the `ray` extra is installed there (pip, constraints.txt). Exit 3 with one line on
# stderr when no cluster can run here (the tests then skip, saying why).
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
STATE=${FEDHPG_RAY_STATE:-/run/fedhpg-ray}
PYTHON=${FEDHPG_PYTHON:-$ROOT/.venv/bin/python}
NET=10.80.0
HEAD=fhr-head
PORT=6379
CPUS_PER_NODE=8          # logical CPUs: more than the machine has, so tasks wait on nothing

cannot() { echo "no Ray cluster here: $*" >&2; exit 3; }
node_name() { echo "fhr-n$1"; }
in_head() { nsenter --net="/run/netns/$HEAD" "$@"; }

answers() {
    [ -f "$STATE/pids" ] || return 1
    local pid
    for pid in $(cat "$STATE/pids"); do kill -0 "$pid" 2>/dev/null || return 1; done
    timeout 30 nsenter --net="/run/netns/$HEAD" "$(dirname "$PYTHON")/ray" status \
        --address="$NET.1:$PORT" >/dev/null 2>&1
}

install_ray() {
    [ -x "$PYTHON" ] || cannot "no Python environment at $PYTHON (make setup)"
    "$PYTHON" -c "import ray" 2>/dev/null && return 0
    echo "installing the ray extra into $(dirname "$(dirname "$PYTHON")") (pip)" >&2
    mkdir -p "$STATE"
    (cd "$ROOT" && timeout 600 "$PYTHON" -m pip install --quiet -c constraints.txt -e ".[ray]") \
        >"$STATE/pip.log" 2>&1 || cannot "pip install '.[ray]' failed ($STATE/pip.log)"
}

check_machine() {
    [ "$(id -u)" -eq 0 ] || cannot "its network namespaces need root"
    local tool
    for tool in ip nsenter; do command -v $tool >/dev/null || cannot "'$tool' is not installed"; done
    ip netns add fhr-probe 2>/dev/null || cannot "cannot create network namespaces here"
    ip netns del fhr-probe
}

# launch NODE LOG COMMAND...: a node's daemon, detached (setsid), in the node's network namespace
# with the node's name as its host name; the wrappers exec, so $! is its pid.
launch() {
    local name=$1 log=$2; shift 2
    setsid nsenter --net="/run/netns/$name" unshare --uts sh -c 'hostname "$1"; shift; exec "$@"' \
        sh "$name" "$@" >>"$log" 2>&1 </dev/null &
    echo $! >> "$STATE/pids"
}

make_network() {
    local nodes=$1 n name
    for name in "$HEAD" $(for n in $(seq 1 $((nodes - 1))); do node_name "$n"; done); do
        ip netns add "$name"
        echo "$name" >> "$STATE/namespaces"
        ip -n "$name" link set lo up
    done
    ip -n "$HEAD" link add fhr-br type bridge
    ip -n "$HEAD" addr add "$NET.1/24" dev fhr-br
    ip -n "$HEAD" link set fhr-br up
    for n in $(seq 1 $((nodes - 1))); do
        name=$(node_name "$n")
        ip -n "$HEAD" link add "fhr-v$n" type veth peer name eth0 netns "$name"
        ip -n "$HEAD" link set "fhr-v$n" master fhr-br up
        ip -n "$name" addr add "$NET.1$n/24" dev eth0
        ip -n "$name" link set eth0 up
    done
}

wait_for() {  # wait_for SECONDS WHAT COMMAND...: until COMMAND succeeds
    local seconds=$1 what=$2; shift 2
    local i pid why="did not start within $seconds s"
    for i in $(seq 1 $((seconds * 2))); do
        "$@" >/dev/null 2>&1 && return 0
        for pid in $(cat "$STATE/pids"); do
            kill -0 "$pid" 2>/dev/null || { why="exited (pid $pid)"; break 2; }
        done
        sleep 0.5
    done
    rm -rf "$STATE.log" && cp -r "$STATE/log" "$STATE.log"  # stop removes the state
    stop >/dev/null 2>&1 || true
    cannot "$what $why (logs in $STATE.log)"
}

start() {
    local nodes=${1:-2}
    case "$nodes" in 1|2) ;; *) echo "usage: $0 start [1|2]" >&2; exit 2 ;; esac
    if answers; then
        echo "RAY_ADDRESS=$NET.1:$PORT"; echo "NETNS=$HEAD"; echo "NODES=$(cat "$STATE/nodes")"
        return 0
    fi
    check_machine
    stop >/dev/null 2>&1 || true  # what a failed start may have left
    install_ray
    local ray n names=("$HEAD")
    ray="$(dirname "$PYTHON")/ray"
    mkdir -p "$STATE/log" "$STATE/tmp"
    : > "$STATE/pids"; : > "$STATE/namespaces"
    make_network "$nodes"
    local common=(--num-cpus="$CPUS_PER_NODE" --disable-usage-stats --block)
    # the head keeps Ray's session files under $STATE/tmp (other nodes: their default)
    RAY_USAGE_STATS_ENABLED=0 launch "$HEAD" "$STATE/log/head.log" "$ray" start --head \
        --node-ip-address="$NET.1" --port="$PORT" --include-dashboard=false \
        --temp-dir="$STATE/tmp" "${common[@]}"
    wait_for 120 "the Ray head" in_head "$ray" status --address="$NET.1:$PORT"
    for n in $(seq 1 $((nodes - 1))); do
        names+=("$(node_name "$n")")
        RAY_USAGE_STATS_ENABLED=0 launch "$(node_name "$n")" "$STATE/log/$(node_name "$n").log" \
            "$ray" start --address="$NET.1:$PORT" --node-ip-address="$NET.1$n" "${common[@]}"
    done
    echo "${names[*]}" | tr ' ' ',' > "$STATE/nodes"
    wait_for 120 "the Ray nodes" in_head "$PYTHON" -c "
import ray, sys
ray.init(address='$NET.1:$PORT', logging_level='ERROR', log_to_driver=False)
sys.exit(0 if sum(n['Alive'] for n in ray.nodes()) == $nodes else 1)"
    echo "RAY_ADDRESS=$NET.1:$PORT"; echo "NETNS=$HEAD"; echo "NODES=$(cat "$STATE/nodes")"
    echo "STARTED=$(tr '\n' ',' < "$STATE/pids" | sed 's/,$//')"
}

pids_in_namespace() { ip netns pids "$1" 2>/dev/null || true; }

stop() {
    [ -d "$STATE" ] || return 0
    local pid name
    # each node's `ray start --block` stops its own processes on SIGTERM
    if [ -f "$STATE/pids" ]; then
        for pid in $(tac "$STATE/pids"); do kill "$pid" 2>/dev/null || true; done
        for pid in $(tac "$STATE/pids"); do
            for _ in $(seq 1 60); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
            kill -9 "$pid" 2>/dev/null || true
        done
    fi
    # anything else still in its namespaces (workers, a task's commands), by pid
    if [ -f "$STATE/namespaces" ]; then
        for name in $(cat "$STATE/namespaces"); do
            for pid in $(pids_in_namespace "$name"); do kill -9 "$pid" 2>/dev/null || true; done
        done
        for name in $(cat "$STATE/namespaces"); do
            for _ in $(seq 1 20); do [ -z "$(pids_in_namespace "$name")" ] && break; sleep 0.25; done
            ip netns del "$name" 2>/dev/null || true
        done
    fi
    find "$STATE" -mindepth 1 -maxdepth 1 ! -name pip.log -exec rm -rf {} +
    rmdir "$STATE" 2>/dev/null || true  # when nothing else is left there
}

case "${1:-}" in
    start) start "${2:-2}" ;;
    stop) stop ;;
    *) echo "usage: $0 start [1|2] | stop" >&2; exit 2 ;;
esac
