#!/usr/bin/env bash
# Wheels of every dependency of `fedhpg[envs]`, pinned by constraints.txt, for an image build
# that reaches no index (`--build-arg PIP_SOURCE=wheelhouse --network none`). They come from
# this machine's pip configuration (its offline CPU torch wheel included), so a build never
# pulls a CUDA torch. Packages published only as source (e.g. antlr4-python3-runtime) are built
# into wheels here, so the image needs no compiler.
#   docker/make-wheelhouse.sh [PYTHON]     (default: python3; must be the image's Python 3.11)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${1:-python3}
OUT=docker/wheelhouse
"$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
    || { echo "error: $PYTHON is not Python 3.11 (the image's)" >&2; exit 2; }
# Only the dependencies: the project itself is installed from the build context's source.
"$PYTHON" -m pip wheel --quiet --wheel-dir "$OUT" -c constraints.txt \
    setuptools ".[envs]" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
rm -f "$OUT"/fedhpg-*.whl
echo "wheelhouse: $(ls "$OUT"/*.whl | wc -l) wheels, $(du -sh "$OUT" | cut -f1)" >&2
