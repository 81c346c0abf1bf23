#!/usr/bin/env bash
# The image's base where Docker Hub is out of reach: a Debian bookworm root filesystem made
# with debootstrap from Debian's own packages (bookworm's python3 is 3.11), imported as an
# image. Where the official python:3.11-slim can be pulled, this is not needed.
#   docker/make-base.sh [TAG]     (default fedhpg-base:bookworm; needs root, debootstrap, docker)
# Skips the work when TAG exists already. The root filesystem is made in a temporary
# directory that is removed on any exit.
set -euo pipefail

TAG=${1:-fedhpg-base:bookworm}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
# libstdc++6 and libgomp1: torch's CPU wheel links them and does not bundle them.
INCLUDE=python3,python3-venv,libstdc++6,libgomp1

if docker image inspect "$TAG" >/dev/null 2>&1; then
    echo "base image $TAG exists" >&2; exit 0
fi
command -v debootstrap >/dev/null || { echo "error: debootstrap is not installed" >&2; exit 3; }
[ "$(id -u)" -eq 0 ] || { echo "error: debootstrap needs root" >&2; exit 3; }

ROOT=$(mktemp -d /var/tmp/fedhpg-base.XXXXXX)
trap 'rm -rf "$ROOT"' EXIT
echo "debootstrap bookworm ($MIRROR) into $ROOT" >&2
timeout 900 debootstrap --variant=minbase --include="$INCLUDE" bookworm "$ROOT" "$MIRROR" \
    >"$ROOT.log" 2>&1 || { echo "error: debootstrap failed: $(tail -n 2 "$ROOT.log")" >&2; rm -f "$ROOT.log"; exit 1; }
rm -f "$ROOT.log"
# Smaller and reproducible enough: no apt lists, caches or docs in the base.
rm -rf "$ROOT"/var/lib/apt/lists/* "$ROOT"/var/cache/apt/* "$ROOT"/usr/share/doc/* \
    "$ROOT"/usr/share/man/* "$ROOT"/usr/share/locale/*
tar --numeric-owner -C "$ROOT" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["python3"]' - "$TAG" >/dev/null
echo "base image $TAG: $(docker image inspect -f '{{.Size}}' "$TAG" | awk '{printf "%.0f MB", $1/1e6}')" >&2
