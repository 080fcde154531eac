#!/usr/bin/env bash
# Build the robot image sdfr-robot:<version> (and :latest) from this checkout.
#   - a wheelhouse of sdfr and its dependencies, made on the host (pip inside a container
#     may not reach the index);
#   - the base: python:3.11-slim when it can be pulled, else sdfr-base:local, built once
#     from Debian packages with mmdebstrap and kept for later builds.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV_PY=.venv/bin/python
VERSION=$($VENV_PY -c 'import sdfr; print(sdfr.__version__)')
IMAGE=sdfr-robot

bash scripts/docker-up.sh

base=${SDFR_IMAGE_BASE:-}
if [ -z "$base" ]; then
    if docker image inspect python:3.11-slim >/dev/null 2>&1 \
        || timeout 60 docker pull -q python:3.11-slim >/dev/null 2>&1; then
        base=python:3.11-slim
    else
        base=sdfr-base:local
    fi
fi
if [ "$base" = sdfr-base:local ] && ! docker image inspect sdfr-base:local >/dev/null 2>&1; then
    command -v mmdebstrap >/dev/null 2>&1 || {
        echo "image: apt-get install mmdebstrap"
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends mmdebstrap >/dev/null
    }
    mirror=$(sed -n 's/^URIs: *//p' /etc/apt/sources.list.d/*.sources 2>/dev/null | head -1)
    mirror=${mirror:-http://deb.debian.org/debian}
    tar=$(mktemp --suffix=.tar)
    echo "image: building sdfr-base:local from Debian (bookworm, $mirror)"
    mmdebstrap --quiet --variant=minbase --include=python3,python3-venv bookworm "$tar" "$mirror"
    docker import "$tar" sdfr-base:local >/dev/null
    rm -f "$tar"
fi

rm -rf compose/build/wheelhouse
mkdir -p compose/build/wheelhouse
PIP_FIND_LINKS= $VENV_PY -m pip wheel -q --disable-pip-version-check -w compose/build/wheelhouse .
docker build -q --build-arg BASE="$base" --build-arg VERSION="$VERSION" \
    -t "$IMAGE:$VERSION" -t "$IMAGE:latest" compose >/dev/null
size=$(docker image inspect -f '{{.Size}}' "$IMAGE:$VERSION")
echo "image: $IMAGE:$VERSION on $base, $((size / 1024 / 1024)) MiB"
