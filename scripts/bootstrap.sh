#!/usr/bin/env bash
# Set up a fresh machine (Debian 12 or similar) for SDfR development and tests.
# Idempotent and quiet: installs missing system tools (as root), creates .venv
# and installs the project into it, re-running pip only when pyproject.toml is
# newer than the stamp .venv/.installed.
set -euo pipefail
cd "$(dirname "$0")/.."

# package:command pairs; an empty command means "check with dpkg only"
APT_NEEDS=(
    "iproute2:ip"
    "nftables:nft"
    "tcpdump:tcpdump"
    "iputils-ping:ping"
    "procps:pgrep"
    "python3-venv:"
    "systemd:systemd-analyze"
    "systemd-container:systemd-nspawn"
    "openssh-client:ssh"
    "openssh-server:/usr/sbin/sshd"
)

missing=()
for need in "${APT_NEEDS[@]}"; do
    pkg=${need%%:*}
    cmd=${need#*:}
    if [ -n "$cmd" ] && command -v "$cmd" >/dev/null 2>&1; then
        continue
    fi
    if dpkg -s "$pkg" >/dev/null 2>&1; then
        continue
    fi
    missing+=("$pkg")
done

if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" -ne 0 ]; then
        echo "bootstrap: not root, not installing: ${missing[*]} (root-only tests will skip)"
    elif ! command -v apt-get >/dev/null 2>&1; then
        echo "bootstrap: no apt-get, install by hand: ${missing[*]}"
    else
        echo "bootstrap: apt-get install ${missing[*]}"
        export DEBIAN_FRONTEND=noninteractive
        log=$(mktemp)
        if ! { apt-get update -q && apt-get install -y -q --no-install-recommends "${missing[@]}"; } \
            >"$log" 2>&1 </dev/null; then
            cat "$log" >&2
            rm -f "$log"
            echo "bootstrap: apt-get failed" >&2
            exit 1
        fi
        rm -f "$log"
    fi
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi

stamp=.venv/.installed
if [ ! -e "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "bootstrap: pip install -e '.[dev,netlab]'"
    log=$(mktemp)
    # The distribution was called sdfr before it became sdfr-robots: drop a stale install.
    .venv/bin/python -m pip uninstall -y -q sdfr >/dev/null 2>&1 || true
    if ! .venv/bin/python -m pip install -q --disable-pip-version-check --no-input \
        -e '.[dev,netlab]' >"$log" 2>&1 </dev/null; then
        cat "$log" >&2
        rm -f "$log"
        echo "bootstrap: pip install failed" >&2
        exit 1
    fi
    rm -f "$log"
    touch "$stamp"
fi
