#!/usr/bin/env bash
# Make Docker usable here: install the engine (docker.io) and docker-compose when missing,
# and start dockerd when none answers.  A dockerd started here is recorded in
# /run/sdfr-dockerd.pid, and scripts/docker-down.sh stops it (and only it).
# Fails, saying why, when Docker cannot run on this machine.
set -euo pipefail

PIDFILE=/run/sdfr-dockerd.pid
STATE=/run/sdfr-dockerd.state
LOG=/var/log/sdfr-dockerd.log

need=()
command -v dockerd >/dev/null 2>&1 || need+=(docker.io)
command -v docker-compose >/dev/null 2>&1 || docker compose version >/dev/null 2>&1 || need+=(docker-compose)
if [ ${#need[@]} -gt 0 ]; then
    if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null 2>&1; then
        echo "docker-up: ${need[*]} missing and cannot be installed here (needs root and apt-get)" >&2
        exit 1
    fi
    echo "docker-up: apt-get install ${need[*]}"
    export DEBIAN_FRONTEND=noninteractive
    out=$(mktemp)
    if ! { apt-get update -q && apt-get install -y -q --no-install-recommends "${need[@]}"; } >"$out" 2>&1; then
        tail -20 "$out" >&2
        echo "docker-up: installing ${need[*]} failed" >&2
        exit 1
    fi
    rm -f "$out"
fi

if docker info >/dev/null 2>&1; then
    exit 0
fi
if [ "$(id -u)" -ne 0 ]; then
    echo "docker-up: no Docker engine answers, and starting one needs root" >&2
    exit 1
fi
# What dockerd changes on the host, as it was, for docker-down.sh to put back: its bridge,
# br_netfilter's sysctl (bridged traffic through iptables) and the FORWARD chain's policy.
{
    if ip link show docker0 >/dev/null 2>&1; then echo "docker0=1"; else echo "docker0=0"; fi
    echo "nf_call=$(cat /proc/sys/net/bridge/bridge-nf-call-iptables 2>/dev/null || echo absent)"
    echo "forward=$(iptables -S FORWARD 2>/dev/null | sed -n 's/^-P FORWARD //p')"
} >"$STATE"
echo "docker-up: starting dockerd (log $LOG)"
setsid dockerd >"$LOG" 2>&1 </dev/null &
echo $! >"$PIDFILE"
for _ in $(seq 1 120); do
    if docker info >/dev/null 2>&1; then
        exit 0
    fi
    if ! kill -0 "$(cat "$PIDFILE")" 2>/dev/null; then
        tail -20 "$LOG" >&2
        rm -f "$PIDFILE"
        echo "docker-up: dockerd exited (log above)" >&2
        exit 1
    fi
    sleep 0.5
done
echo "docker-up: dockerd did not answer within 60 s (log $LOG)" >&2
exit 1
