#!/usr/bin/env bash
# make bench-device: one prepared script that ends within 8 minutes on a GPU machine.
#
#   bash benchmarks/on_device.sh local   # in this checkout's .venv (make bench-device)
#   bash benchmarks/on_device.sh fetch   # here: the wheels a bare GPU machine lacks, into .whl/
#   bash benchmarks/on_device.sh run     # on a GPU machine whose python3 holds a CUDA torch
#                                        # (and numpy, numba, msgpack, PyYAML, rich) but not the
#                                        # rest of the stack, and which reaches no index: the
#                                        # wheels of .whl/ (carried there) go into SITE, and the
#                                        # repository's folders are mapped to fedhpg.* the way
#                                        # pyproject.toml does (links under /tmp/pkg)
#
# Each part runs in its own process under its own time limit (a part that outruns it is
# stopped and the next starts; what it measured so far is kept), all within TOTAL_S:
#   1. placement: an agent's θ after 3 rounds alone, in four companies and on a second run,
#      on DEVICE, for CartPole, GridWorld, Pendulum, Acrobot and MountainCar;
#   2. K = 1,000, 16,000, 65,536 CartPole agents (16-16 MLP, B = 16): the whole local
#      iteration's env steps/s and peak memory, and the reference (benchmarks/device_reference.py)
#      re-measured in the same process;
#   3. where the time of one iteration goes (benchmarks/device_profile.py) at PROFILE_AGENTS
#      agents (16,000 on a GPU): by section of the engine, and torch's top operators;
#   4. a whole fedhpg-run federation of FED_AGENTS agents (65,536 on a GPU) on one host, 3
#      rounds, θ̃ evaluated in every agent's environment at the end;
#   5. the report: one table, bench_device.json; in `local` mode, when every part finished,
#      BENCHMARKS.md's tables of it (record, below).
# Results: OUT if set (bench_device.json, device_profile.json, bench_device.log,
# federation.log), else benchmarks/results/device/. DEVICE=cpu is the rehearsal: K = 100 and
# 1,000, a profile of 200 agents, 2,000 agents in the federation (~5 min on 2 cores). The exit
# status is 0 when every part finished.
set -euo pipefail
cd "$(dirname "$0")/.."
WHEELS=${WHEELS:-.whl}
SITE=${SITE:-/tmp/site}
PLATFORMS=(--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64
           --platform manylinux2014_x86_64)
mode=${1:-}
shift || true

# part NAME LIMIT_S COMMAND...: COMMAND under min(LIMIT_S, what is left before the deadline),
# one progress line before and after; its exit status in PART_STATUS.
part() {
    local name=$1 limit=$2 left started
    shift 2
    left=$((deadline - SECONDS - REPORT_S))
    if [ "$left" -lt "$limit" ]; then limit=$left; fi
    if [ "$limit" -lt 10 ]; then
        echo "[bench-device $(date -u +%T)] $name: skipped, $((deadline - SECONDS)) s left"
        PART_STATUS=124
        failed=1
        return 0
    fi
    echo "[bench-device $(date -u +%T)] $name: started, limit $limit s"
    started=$SECONDS
    PART_STATUS=0
    timeout -k 10 "$limit" "$@" || PART_STATUS=$?
    if [ "$PART_STATUS" = 124 ] || [ "$PART_STATUS" = 137 ]; then
        echo "[bench-device $(date -u +%T)] $name: STOPPED at its limit after $((SECONDS - started)) s"
    else
        echo "[bench-device $(date -u +%T)] $name: exit status $PART_STATUS after $((SECONDS - started)) s"
    fi
    if [ "$PART_STATUS" != 0 ]; then failed=1; fi
    return 0
}

bench() {
    local python=$1 out=$2 device=$3
    shift 3
    local agents counts work fed_limit profile_agents profile_limit
    # the limits (s) of each part; their sum stays below TOTAL_S
    if [ "$device" = cpu ]; then
        agents=${FED_AGENTS:-2000}
        counts=${COUNTS:-100,1000}
        TOTAL_S=${TOTAL_S:-600}
        limits=(120 60 200 0 0)
        profile_agents=${PROFILE_AGENTS:-200}
        profile_limit=90
        fed_limit=120
    else
        agents=${FED_AGENTS:-65536}
        counts=${COUNTS:-1000,16000,65536}
        TOTAL_S=${TOTAL_S:-460}
        limits=(60 50 65 110 0)
        profile_agents=${PROFILE_AGENTS:-16000}
        profile_limit=60
        fed_limit=110
    fi
    REPORT_S=15
    deadline=$((started_at + TOTAL_S))
    failed=0
    work=${WORK:-$(mktemp -d /tmp/bench_device.XXXXXX)}
    mkdir -p "$work"
    export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
    echo "[bench-device $(date -u +%T)] $device, K = $counts, federation of $agents agents;" \
        "within $TOTAL_S s; parts in $work, results in $out"
    "$python" -c 'import sys, torch; from fedhpg.common.learning.engine.devices import device_problem
print("python", sys.version.split()[0], "torch", torch.__version__, "cuda", torch.cuda.is_available())
problem = device_problem(sys.argv[1]); sys.exit(f"error: DEVICE: {problem}" if problem else 0)' \
        "$device" || return 1
    [ "$device" = cpu ] || nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
    local scale=("$python" -m benchmarks.scale_device --device "$device")
    part placement "${limits[0]}" "${scale[@]}" --only placement --out "$work/placement.json" "$@"
    local i=1 k
    for k in ${counts//,/ }; do
        part "K=$k" "${limits[$i]:-120}" "${scale[@]}" --only iteration --agents "$k" \
            --time-limit-s "$(( ${limits[$i]:-120} * 2 / 3 ))" --out "$work/k$k.json" "$@"
        i=$((i + 1))
    done
    part "profile of $profile_agents agents" "$profile_limit" "$python" -m benchmarks.device_profile \
        --device "$device" --agents "$profile_agents" --out "$out/device_profile.json"
    rm -rf "$work/federation"
    local fed_started=$SECONDS
    part "federation of $agents agents" "$fed_limit" "$python" -c 'import sys
from fedhpg.server.commands.launcher import main
sys.argv[0] = "fedhpg-run"; main()' env=cartpole agents.num_agents="$agents" \
        agents.per_host="$agents" agents.budget.batch_size=[16] agents.speeds=[1] \
        agents.step_delays_s=[0] algo.engine=torch algo.device="$device" rounds=3 \
        eval.every=3 eval.episodes=1 server.register_timeout_s=600 server.tensorboard=false \
        hydra.run.dir="$work/federation" > "$work/federation.log" 2>&1
    local fed_status=$PART_STATUS fed_seconds=$((SECONDS - fed_started))
    # per-agent lines (the evaluation's table) stay in $work
    grep -v '^agent-' "$work/federation.log" > "$out/federation.log" || true
    tail -8 "$out/federation.log"
    echo "[bench-device $(date -u +%T)] report"
    local report_status=0 parts=("$work/placement.json")
    for k in ${counts//,/ }; do parts+=("$work/k$k.json"); done
    timeout -k 5 "$REPORT_S" "${scale[@]}" --report "${parts[@]}" --out "$out/bench_device.json" \
        --federation "$work/federation" "$agents" "$fed_status" "$fed_seconds" || report_status=$?
    echo "[bench-device $(date -u +%T)] done after $((SECONDS - started_at)) s;" \
        "every part finished: $([ "$failed$report_status" = 00 ] && echo yes || echo NO)"
    [ "$failed$report_status" = 00 ]
}

# bench with everything it prints also in OUT/bench_device.log; its exit status
logged() {
    local out=${OUT:-benchmarks/results/device}
    mkdir -p "$out"
    bench "$1" "$out" "${DEVICE:-cuda}" "${@:2}" 2>&1 | tee "$out/bench_device.log"
    return "${PIPESTATUS[0]}"
}

# record PYTHON OUT: a finished run's report as BENCHMARKS.md's device tables (the data files
# copied where the tables name them): DEVICE=cpu the CPU rehearsal's, an H200 the GPU's; another
# GPU's report stays in OUT (its table names the H200 it was measured on).
record() {
    local python=$1 out=$2 name
    if [ "${DEVICE:-cuda}" = cpu ]; then
        cp "$out/bench_device.json" benchmarks/results/bench_device_cpu.json
        cp "$out/device_profile.json" benchmarks/results/device_profile_cpu.json
        "$python" -m benchmarks.device_tables device_cpu_rehearsal \
            benchmarks/results/bench_device_cpu.json benchmarks/results/device_profile_cpu.json
        echo "[bench-device] BENCHMARKS tables written: python -m benchmarks.render to show them"
        return
    fi
    name=$("$python" -c 'import json, sys; print(json.load(open(sys.argv[1]))["device_name"])' \
        "$out/bench_device.json")
    case "$name" in
    *H200*)
        cp "$out/bench_device.json" benchmarks/results/device/bench_device_h200.json
        cp "$out/bench_device.log" benchmarks/results/device/bench_device_h200.log
        "$python" -m benchmarks.device_tables device_h200 \
            benchmarks/results/device/bench_device_h200.json
        echo "[bench-device] BENCHMARKS tables written: python -m benchmarks.render to show them"
        ;;
    *) echo "[bench-device] $name: no BENCHMARKS table for it; the report stays in $out" ;;
    esac
}

started_at=$SECONDS
case "$mode" in
local)
    logged "${PYTHON:-.venv/bin/python}" "$@"
    record "${PYTHON:-.venv/bin/python}" "${OUT:-benchmarks/results/device}"
    ;;
fetch)
    mkdir -p "$WHEELS"
    pip() { "${PYTHON:-python3}" -m pip "$@"; }
    # pure-Python wheels, and the two compiled ones for CPython ${PYVER:-3.12}
    pip download --quiet --no-deps --only-binary=:all: --python-version "${PYVER:-3.12}" \
        --implementation cp "${PLATFORMS[@]}" -d "$WHEELS" \
        gymnasium==1.4.0 Farama-Notifications==0.0.6 hydra-core==1.3.8 omegaconf==2.3.1 \
        cloudpickle==3.1.2 pyzmq==27.3.0 orjson==3.13.0
    # antlr4 4.9.3 (Hydra's parser) is published as a source archive only: built here
    pip wheel --quiet --no-deps -w "$WHEELS" antlr4-python3-runtime==4.9.3
    ls "$WHEELS"
    ;;
run)
    ls "$WHEELS"/*.whl > /dev/null || { echo "error: no wheels in $WHEELS: run 'fetch' here and carry it" >&2; exit 1; }
    "${PYTHON:-python3}" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target "$SITE" "$WHEELS"/*.whl
    mkdir -p /tmp/pkg/fedhpg
    for d in agent common envs server conf; do ln -sfn "$PWD/$d" "/tmp/pkg/fedhpg/$d"; done
    export PYTHONPATH="$SITE:/tmp/pkg:$PWD"
    logged "${PYTHON:-python3}" "$@"
    ;;
*)
    echo "usage: bash benchmarks/on_device.sh local|fetch|run [scale_device arguments]" >&2
    exit 2
    ;;
esac
