#!/usr/bin/env bash
# Stop the dockerd scripts/docker-up.sh started (if it did), and put back what it changed
# on the host (its docker0 bridge, br_netfilter's sysctl, the FORWARD policy); leave any
# other dockerd alone.
set -euo pipefail
PIDFILE=/run/sdfr-dockerd.pid
STATE=/run/sdfr-dockerd.state
[ -f "$PIDFILE" ] || exit 0
pid=$(cat "$PIDFILE")
if kill -0 "$pid" 2>/dev/null; then
    kill -TERM "$pid"
    for _ in $(seq 1 60); do
        kill -0 "$pid" 2>/dev/null || break
        sleep 0.5
    done
    kill -0 "$pid" 2>/dev/null && kill -KILL "$pid"
fi
rm -f "$PIDFILE"
if [ -f "$STATE" ]; then
    docker0=$(sed -n 's/^docker0=//p' "$STATE")
    nf_call=$(sed -n 's/^nf_call=//p' "$STATE")
    forward=$(sed -n 's/^forward=//p' "$STATE")
    if [ "$docker0" = 0 ] && ip link show docker0 >/dev/null 2>&1; then
        ip link delete docker0
    fi
    if [ -n "$nf_call" ] && [ "$nf_call" != absent ] && [ -w /proc/sys/net/bridge/bridge-nf-call-iptables ]; then
        echo "$nf_call" >/proc/sys/net/bridge/bridge-nf-call-iptables
    elif [ "$nf_call" = absent ] && [ -w /proc/sys/net/bridge/bridge-nf-call-iptables ]; then
        echo 0 >/proc/sys/net/bridge/bridge-nf-call-iptables
    fi
    if [ -n "$forward" ]; then
        iptables -P FORWARD "$forward" 2>/dev/null || true
    fi
    rm -f "$STATE"
fi
