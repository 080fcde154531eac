#!/usr/bin/env bash
# Avahi for the side-by-side bench's Avahi peer (bench/avahi_node.py): Debian's avahi-daemon
# and avahi-utils (avahi-publish, avahi-browse).  Idempotent; root.  The host's own
# avahi-daemon is not started by the install (a policy-rc.d refuses it for the time of the
# install): the bench runs one daemon per robot, inside the robot.
set -euo pipefail
if command -v avahi-daemon >/dev/null 2>&1 && command -v avahi-browse >/dev/null 2>&1 \
    && command -v dbus-daemon >/dev/null 2>&1; then
    exit 0
fi
[ "$(id -u)" -eq 0 ] || { echo "avahi-setup: FAILED: run as root to install avahi-daemon avahi-utils" >&2; exit 1; }
command -v apt-get >/dev/null 2>&1 || { echo "avahi-setup: FAILED: no apt-get; install avahi-daemon, avahi-utils and dbus-daemon by hand" >&2; exit 1; }
echo "avahi-setup: apt-get install avahi-daemon avahi-utils dbus-daemon"
policy=/usr/sbin/policy-rc.d
made_policy=0
if [ ! -e "$policy" ]; then
    printf '#!/bin/sh\nexit 101\n' > "$policy"
    chmod +x "$policy"
    made_policy=1
fi
log=$(mktemp)
trap 'rm -f "$log"; [ "$made_policy" -eq 0 ] || rm -f "$policy"' EXIT
export DEBIAN_FRONTEND=noninteractive
if ! { apt-get update -q && apt-get install -y -q --no-install-recommends avahi-daemon avahi-utils dbus-daemon; } \
    >"$log" 2>&1 </dev/null; then
    cat "$log" >&2
    echo "avahi-setup: FAILED: apt-get install avahi-daemon avahi-utils dbus-daemon" >&2
    exit 1
fi
