#!/usr/bin/env bash
# Sourced by cluster/slurm.sh and docker/engine.sh: apt_install LOG PACKAGE... installs Debian
# packages as root, apt's output in LOG; returns apt's exit status (1 when another installer
# held the lock for 20 minutes, said in LOG). One installer at a time: the container and
# cluster scripts may run side by side (.ci/run), apt takes its own lock without waiting (the
# other fails at once), and both write /usr/sbin/policy-rc.d, whose exit 101 keeps the
# packages' scripts from starting a daemon (each script starts its own).
apt_install() {
    local log=$1 lock status=0 policy=/usr/sbin/policy-rc.d made_policy=0
    shift
    mkdir -p "$(dirname "$log")"
    exec {lock}>/run/fedhpg-apt.lock
    if ! flock -w 1200 "$lock"; then
        echo "another installer held /run/fedhpg-apt.lock for 20 min" >"$log"
        exec {lock}>&-
        return 1
    fi
    if [ ! -e $policy ]; then printf '#!/bin/sh\nexit 101\n' > $policy; chmod +x $policy; made_policy=1; fi
    { timeout 300 apt-get -o DPkg::Lock::Timeout=240 update -qq \
        && DEBIAN_FRONTEND=noninteractive timeout 600 \
        apt-get -o DPkg::Lock::Timeout=240 install -y -qq --no-install-recommends "$@"; } \
        >"$log" 2>&1 || status=$?
    [ $made_policy -eq 1 ] && rm -f $policy
    exec {lock}>&-
    return $status
}
