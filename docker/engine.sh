#!/usr/bin/env bash
# A Docker engine of the project's own, for the container tests (make test-containers).
#   docker/engine.sh start   prints DOCKER_HOST=... for an engine that answers, starting one if
#                            needed (then also STARTED=<pid>: the caller owns it and stops it)
#   docker/engine.sh stop    stops the engine this script started (by its pid), nothing else
# An engine that already answers on the default socket is used as it is and never stopped.
# Otherwise, as root and where Debian's packages are reachable, it installs docker.io,
# docker-compose and debootstrap and starts dockerd on a socket of its own, so that it never
# takes over or stops an engine the machine runs for something else. What dockerd changes on the
# host and leaves when it exits (its bridges, its iptables chains, net.ipv4.ip_forward) is saved
# before it starts and put back by `stop`. Exit 3 with one line on stderr when no engine can run
# here (the tests then skip, saying why).
set -euo pipefail
# shellcheck source=cluster/apt_install.sh
source "$(dirname "${BASH_SOURCE[0]}")/../cluster/apt_install.sh"

STATE=${FEDHPG_DOCKER_STATE:-/run/fedhpg-docker}
SOCKET=$STATE/docker.sock
PIDFILE=$STATE/dockerd.pid
DATA=${FEDHPG_DOCKER_DATA:-/var/lib/fedhpg-docker}   # images stay here between runs (a cache)
PACKAGES=(docker.io docker-compose debootstrap)

cannot() { echo "no Docker engine here: $*" >&2; exit 3; }

answers() { timeout 10 docker -H "$1" info >/dev/null 2>&1; }

install_packages() {
    local missing=()
    command -v dockerd >/dev/null || missing+=(docker.io)
    command -v docker-compose >/dev/null || missing+=(docker-compose)
    command -v debootstrap >/dev/null || missing+=(debootstrap)
    [ ${#missing[@]} -eq 0 ] && return 0
    [ "$(id -u)" -eq 0 ] || cannot "${missing[*]} not installed and not root to install them"
    command -v apt-get >/dev/null || cannot "${missing[*]} not installed and no apt-get"
    echo "installing ${missing[*]} (apt-get)" >&2
    local status=0
    apt_install "$STATE/apt.log" "${missing[@]}" || status=$?
    [ $status -eq 0 ] || cannot "apt-get install ${missing[*]} failed (exit $status, $STATE/apt.log)"
}

start() {
    if answers unix:///var/run/docker.sock; then
        echo "DOCKER_HOST=unix:///var/run/docker.sock"; return 0
    fi
    if [ -S "$SOCKET" ] && answers "unix://$SOCKET"; then
        echo "DOCKER_HOST=unix://$SOCKET"; return 0
    fi
    install_packages
    [ "$(id -u)" -eq 0 ] || cannot "dockerd needs root"
    mkdir -p "$STATE" "$DATA"
    save_host_state
    # setsid: the engine outlives this script but not `stop`; its own containerd is its child.
    setsid dockerd --host "unix://$SOCKET" --pidfile "$PIDFILE" --data-root "$DATA" \
        --exec-root "$STATE/exec" --log-level warn >"$STATE/dockerd.log" 2>&1 < /dev/null &
    for _ in $(seq 1 120); do
        if answers "unix://$SOCKET"; then
            echo "DOCKER_HOST=unix://$SOCKET"; echo "STARTED=$(cat "$PIDFILE")"; return 0
        fi
        if ! kill -0 $! 2>/dev/null; then
            cannot "dockerd exited: $(tail -n 3 "$STATE/dockerd.log" | tr '\n' ' ')"
        fi
        sleep 0.5
    done
    kill $! 2>/dev/null || true
    cannot "dockerd did not answer within 60 s ($STATE/dockerd.log)"
}

bridges() { ip -o link show type bridge 2>/dev/null | awk -F': ' '{print $2}' | sort; }

save_host_state() {
    bridges > "$STATE/bridges.before"
    cat /proc/sys/net/ipv4/ip_forward > "$STATE/ip_forward.before"
    iptables-save > "$STATE/iptables.before" 2>/dev/null || rm -f "$STATE/iptables.before"
    ip6tables-save > "$STATE/ip6tables.before" 2>/dev/null || rm -f "$STATE/ip6tables.before"
}

restore_host_state() {
    if [ -f "$STATE/bridges.before" ]; then
        comm -13 "$STATE/bridges.before" <(bridges) | while read -r bridge; do
            case "$bridge" in docker0|br-*) ip link delete "$bridge" ;; esac
        done
    fi
    [ -f "$STATE/iptables.before" ] && iptables-restore < "$STATE/iptables.before"
    [ -f "$STATE/ip6tables.before" ] && ip6tables-restore < "$STATE/ip6tables.before"
    [ -f "$STATE/ip_forward.before" ] && cat "$STATE/ip_forward.before" > /proc/sys/net/ipv4/ip_forward
    rm -f "$STATE"/*.before
}

stop() {
    [ -f "$PIDFILE" ] || return 0
    local pid; pid=$(cat "$PIDFILE")
    if kill -0 "$pid" 2>/dev/null; then
        kill "$pid"
        for _ in $(seq 1 60); do kill -0 "$pid" 2>/dev/null || break; sleep 0.5; done
        kill -9 "$pid" 2>/dev/null || true
    fi
    restore_host_state
    rm -rf "$PIDFILE" "$SOCKET" "$STATE/exec"
}

case "${1:-}" in
    start) start ;;
    stop) stop ;;
    *) echo "usage: $0 start|stop" >&2; exit 2 ;;
esac
