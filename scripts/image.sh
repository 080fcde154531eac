#!/usr/bin/env bash
# Build the robot image sdfr-robot:<version> (and :latest) from this checkout.
#   - a wheelhouse of sdfr and its dependencies, made on the host (pip inside a container
#     may not reach the index);
#   - the base: python:3.11-slim when it can be pulled, else sdfr-base:local, built once
#     from Debian packages with mmdebstrap and kept for later builds (rebuilt when its
#     recipe changes: the label org.sdfr.base-recipe).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV_PY=.venv/bin/python
VERSION=$($VENV_PY -c 'import sdfr; print(sdfr.__version__)')
IMAGE=sdfr-robot
# Bump when the base's recipe below changes: a kept base of another recipe is rebuilt.
BASE_RECIPE=2

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
have=$(docker image inspect -f '{{index .Config.Labels "org.sdfr.base-recipe"}}' sdfr-base:local 2>/dev/null || true)
if [ "$base" = sdfr-base:local ] && [ "$have" != "$BASE_RECIPE" ]; then
    command -v mmdebstrap >/dev/null 2>&1 || {
        echo "image: apt-get install mmdebstrap"
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends mmdebstrap >/dev/null
    }
    mirror=$(sed -n 's/^URIs: *//p' /etc/apt/sources.list.d/*.sources 2>/dev/null | head -1)
    mirror=${mirror:-http://deb.debian.org/debian}
    tar=$(mktemp --suffix=.tar)
    echo "image: building sdfr-base:local from Debian (bookworm, $mirror)"
    # Python and what it needs, nothing recommended, no docs but the copyrights, no man
    # pages or translations, merged /usr without the usrmerge package (which pulls in perl).
    log=$(mktemp)
    if ! mmdebstrap --quiet --variant=minbase --include=python3,python3-venv \
        --hook-dir=/usr/share/mmdebstrap/hooks/merged-usr \
        --aptopt='APT::Install-Recommends "false"' \
        --dpkgopt='path-exclude=/usr/share/man/*' --dpkgopt='path-exclude=/usr/share/info/*' \
        --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-exclude=/usr/share/doc/*' \
        --dpkgopt='path-include=/usr/share/doc/*/copyright' \
        --customize-hook='rm -rf "$1"/var/cache/apt/* "$1"/var/lib/apt/lists/*' \
        bookworm "$tar" "$mirror" >"$log" 2>&1; then
        tail -30 "$log" >&2
        rm -f "$tar" "$log"
        echo "image: FAILED: mmdebstrap could not build the base (above)" >&2
        exit 1
    fi
    rm -f "$log"
    old=$(docker image inspect -f '{{.Id}}' sdfr-base:local 2>/dev/null || true)
    docker import --change "LABEL org.sdfr.base-recipe=$BASE_RECIPE" "$tar" sdfr-base:local >/dev/null
    rm -f "$tar"
    [ -z "$old" ] || docker image rm "$old" >/dev/null 2>&1 || true # unless a container uses it
fi

rm -rf compose/build/wheelhouse
mkdir -p compose/build/wheelhouse
PIP_FIND_LINKS= $VENV_PY -m pip wheel -q --disable-pip-version-check -w compose/build/wheelhouse .
docker build -q --build-arg BASE="$base" --build-arg VERSION="$VERSION" \
    -t "$IMAGE:$VERSION" -t "$IMAGE:latest" compose >/dev/null
# What the build left untagged: its build stage, and a previous sdfr-robot it re-tagged.
docker image prune -f --filter label=org.sdfr.stage=build >/dev/null
docker image prune -f --filter label=org.opencontainers.image.title=$IMAGE >/dev/null
size=$(docker image inspect -f '{{.Size}}' "$IMAGE:$VERSION")
echo "image: $IMAGE:$VERSION on $base, $((size / 1024 / 1024)) MiB"
