#!/usr/bin/env bash
# make bench-device on a lent GPU machine, whose python3 holds a CUDA torch (and numpy, numba,
# msgpack) but not the rest of fedhpg's stack, and which cannot reach an index.
#
#   bash benchmarks/on_device.sh fetch   # here: the missing wheels (Python 3.12) into .whl/
#   bash benchmarks/on_device.sh run     # there (device run, carry .whl): results in $OUT
#
# `run` installs the wheels into /tmp/site (SITE), maps the repository's folders to fedhpg.* the
# way pyproject.toml does (links under /tmp/pkg), runs a whole federation the way
# fedhpg-run does (server and agent hosts forked, each host's maths on the device: the path
# the in-process benchmark does not take), then checks the placement properties and doubles
# K (benchmarks/scale_device.py). Extra arguments go to scale_device.
#
# A rehearsal here, on the CPU, of everything but CUDA (a python3 holding only what the GPU
# machine's does: torch, numpy, numba, msgpack, matplotlib, rich, tensorboard):
#   PYVER=3.11 WHEELS=/tmp/whl311 bash benchmarks/on_device.sh fetch
#   PYTHON=/tmp/bare/bin/python WHEELS=/tmp/whl311 SITE=/tmp/site311 OUT=/tmp/rehearsal \
#     DEVICE=cpu bash benchmarks/on_device.sh run --start 100 --max-agents 200
set -euo pipefail
cd "$(dirname "$0")/.."
WHEELS=${WHEELS:-.whl}
SITE=${SITE:-/tmp/site}
PLATFORMS=(--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64
           --platform manylinux2014_x86_64)
mode=${1:-}
shift || true
case "$mode" in
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
    export PYTHONPATH="$SITE:/tmp/pkg:$PWD" OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
    out=${OUT:-benchmarks/results}
    device=${DEVICE:-cuda}
    mkdir -p "$out"
    "${PYTHON:-python3}" -c 'import torch; print("torch", torch.__version__, "cuda", torch.cuda.is_available())'
    # 1,000 agents on 4 forked hosts, 3 rounds; its log and run directory come back in $OUT
    rm -rf "$out/federation"
    status=0
    "${PYTHON:-python3}" -c 'import sys; from fedhpg.server.launcher import main
sys.argv[0] = "fedhpg-run"; main()' env=cartpole agents=population agents.num_agents=1000 \
        agents.per_host=250 algo.engine=torch algo.device="$device" rounds=3 \
        hydra.run.dir="$out/federation" > "$out/federation.log" 2>&1 || status=$?
    grep -v '^agent-' "$out/federation.log" | tail -12
    echo "federation on the device (fedhpg-run's forked path): exit status $status"
    "${PYTHON:-python3}" -m benchmarks.scale_device --device "$device" --out "$out/scale_device.json" "$@"
    exit "$status"
    ;;
*)
    echo "usage: bash benchmarks/on_device.sh fetch|run [scale_device arguments]" >&2
    exit 2
    ;;
esac
