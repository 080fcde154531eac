#!/bin/sh
# sdfrd as the container's main process (run it with --init, or `init: true` in compose, so a
# tiny init is PID 1 and SIGTERM reaches sdfrd, which says Byebye).  The robot id is
# SDFR_ROBOT_ID, else the container's hostname; the fleet is SDFR_FLEET (default 1).  More
# flags can follow, and a config mounted at /etc/sdfr/robot.toml replaces the image's.
set -eu
exec /opt/sdfr/bin/sdfrd --config /etc/sdfr/robot.toml \
    --robot-id "${SDFR_ROBOT_ID:-$(hostname)}" --fleet "${SDFR_FLEET:-1}" "$@"
