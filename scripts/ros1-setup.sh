#!/usr/bin/env bash
# The ROS 1 environment of the ROS tiers and of the ROS 1 node, from Debian 12's own packages
# (ROS 1 reached its end of life in May 2025; Debian still ships Noetic-era rospy):
#   - apt: roscore, rospy, rostopic, rosservice, roslaunch, genpy, diagnostic_msgs;
#   - .venv/ros1: a venv of /usr/bin/python3 (which sees rospy) with this project in it;
#   - sdfr_msgs generated from ros/sdfr_msgs with genpy (no catkin) into .venv/ros1/msgs,
#     which the venv finds by a .pth file and the command-line tools by PYTHONPATH.
# Idempotent and quick when nothing changed (stamps under .venv/ros1).
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
venv=$repo/.venv/ros1
PY=/usr/bin/python3 # Debian's interpreter: the one rospy is installed for

log=$(mktemp)
trap 'rm -f "$log"' EXIT
run() { # run "what" cmd...: quiet unless it fails
    local what=$1
    shift
    if ! "$@" >"$log" 2>&1 </dev/null; then
        cat "$log" >&2
        echo "ros1-setup: FAILED: $what" >&2
        exit 1
    fi
}

APT=(ros-core python3-rospy python3-rosservice python3-rostopic python3-roslaunch
    python3-genpy python3-genmsg ros-std-msgs python3-std-msgs python3-diagnostic-msgs
    ros-diagnostic-msgs python3-venv)
missing=()
for pkg in "${APT[@]}"; do
    dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    [ "$(id -u)" -eq 0 ] || { echo "ros1-setup: FAILED: need ${missing[*]} (run as root to install)" >&2; exit 1; }
    command -v apt-get >/dev/null || { echo "ros1-setup: FAILED: no apt-get to install ${missing[*]}" >&2; exit 1; }
    echo "ros1-setup: apt-get install ${missing[*]} (about 30 s)"
    export DEBIAN_FRONTEND=noninteractive
    run "apt-get install ${missing[*]}" bash -c "apt-get update -q && apt-get install -y -q --no-install-recommends ${missing[*]}"
fi

[ -x "$venv/bin/python" ] || run "venv $venv" "$PY" -m venv --system-site-packages "$venv"

stamp=$venv/.project
if [ ! -e "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "ros1-setup: pip install -e . into $venv"
    run "pip install -e ." "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-input -e .
    touch "$stamp"
fi

# sdfr_msgs from the same files as ROS 2's; ROS 1 has no builtin_interfaces: its `time`.
stamp=$venv/.sdfr_msgs
src=$repo/ros/sdfr_msgs
out=$venv/msgs
if [ ! -e "$stamp" ] || [ -n "$(find "$src" -newer "$stamp" -print -quit)" ]; then
    echo "ros1-setup: generating sdfr_msgs (genpy)"
    tmp=$(mktemp -d)
    mkdir -p "$tmp/msg" "$tmp/srv"
    for f in "$src"/msg/*.msg "$src"/srv/*.srv; do
        rel=${f#"$src"/}
        sed 's#builtin_interfaces/Time#time#' "$f" >"$tmp/$rel"
    done
    rm -rf "$out/sdfr_msgs"
    mkdir -p "$out/sdfr_msgs"
    inc=(-Isdfr_msgs:"$tmp/msg" -Istd_msgs:/usr/share/std_msgs/msg)
    run "genmsg_py" "$PY" /usr/lib/genpy/genmsg_py.py -p sdfr_msgs -o "$out/sdfr_msgs/msg" "${inc[@]}" "$tmp"/msg/*.msg
    run "genmsg_py --initpy" "$PY" /usr/lib/genpy/genmsg_py.py --initpy -p sdfr_msgs -o "$out/sdfr_msgs/msg"
    run "gensrv_py" "$PY" /usr/lib/genpy/gensrv_py.py -p sdfr_msgs -o "$out/sdfr_msgs/srv" "${inc[@]}" "$tmp"/srv/*.srv
    run "gensrv_py --initpy" "$PY" /usr/lib/genpy/gensrv_py.py --initpy -p sdfr_msgs -o "$out/sdfr_msgs/srv"
    touch "$out/sdfr_msgs/__init__.py"
    rm -rf "$tmp"
    site=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
    echo "$out" >"$site/sdfr_msgs_ros1.pth"
    touch "$stamp"
fi

run "import rospy and sdfr_msgs" "$venv/bin/python" -c '
import rospy, sdfr_msgs.msg, sdfr_msgs.srv, diagnostic_msgs.msg, sdfr.ros.ros1'
