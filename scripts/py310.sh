#!/usr/bin/env bash
# The Python 3.10 tier of `make test` (Ubuntu 22.04, ROS 2 Humble and Jetson images ship
# 3.10): the unit tests and namespace fleet tests under a 3.10 interpreter, in .venv310.
#
# The interpreter: $SDFR_PYTHON310, else python3.10 on PATH (Ubuntu 22.04's own), else a
# pyenv build (~/.pyenv/versions/3.10.*; this project's CI machine kind has one), else one
# uv manages (`uv python find 3.10`), else `uv python install 3.10` (uv from PyPI; it
# downloads a python-build-standalone build, which needs more than PyPI). SDFR_SKIP_PY310=1
# skips the tier, saying so; anything else that stops it fails `make test`.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "${SDFR_SKIP_PY310:-}" = 1 ]; then
    echo "py310: SKIPPED (SDFR_SKIP_PY310=1): the Python 3.10 tier did not run"
    exit 0
fi

fail() {
    echo "py310: FAILED: $*" >&2
    echo "py310: (SDFR_SKIP_PY310=1 skips this tier; SDFR_PYTHON310=PATH names an interpreter)" >&2
    exit 1
}

is310() { "$1" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 10))' 2>/dev/null; }

find310() {
    local c
    for c in "${SDFR_PYTHON310:-}" "$(command -v python3.10 || true)" \
        "$HOME"/.pyenv/versions/3.10.*/bin/python3.10 /root/.pyenv/versions/3.10.*/bin/python3.10; do
        if [ -n "$c" ] && [ -x "$c" ] && is310 "$c"; then
            echo "$c"
            return 0
        fi
    done
    if [ -x .venv/bin/uv ] || .venv/bin/python -m pip install -q --disable-pip-version-check uv \
        >/dev/null 2>&1; then
        c=$(.venv/bin/uv python find 3.10 2>/dev/null || true)
        if [ -n "$c" ] && is310 "$c"; then
            echo "$c"
            return 0
        fi
        log=$(mktemp)
        if .venv/bin/uv python install 3.10 >"$log" 2>&1; then
            rm -f "$log"
            c=$(.venv/bin/uv python find 3.10)
            echo "$c"
            return 0
        fi
        echo "py310: uv python install 3.10 failed:" >&2
        sed 's/^/py310:   /' "$log" >&2
        rm -f "$log"
    fi
    return 1
}

PY=$(find310) || fail "no Python 3.10 interpreter: not SDFR_PYTHON310, python3.10 on PATH, \
~/.pyenv/versions/3.10.*, nor uv's (see above)"
echo "py310: $PY ($("$PY" -c 'import platform; print(platform.python_version())'))"

V=.venv310
if [ ! -x $V/bin/python ] || ! is310 $V/bin/python; then
    rm -rf $V
    "$PY" -m venv $V || fail "$PY -m venv $V"
fi
stamp=$V/.installed
if [ ! -e "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "py310: pip install -e '.[dev,netlab]' into $V"
    log=$(mktemp)
    if ! $V/bin/python -m pip install -q --disable-pip-version-check --no-input \
        -e '.[dev,netlab]' >"$log" 2>&1 </dev/null; then
        cat "$log" >&2
        rm -f "$log"
        fail "pip install into $V"
    fi
    rm -f "$log"
    touch "$stamp"
fi

# The unit tests, and fleets of real daemons (under 3.10: sdfrd runs as sys.executable).
$V/bin/pytest -q -p no:cacheprovider -n auto --maxprocesses=4 tests/unit
$V/bin/pytest -q -p no:cacheprovider \
    "tests/ns/test_daemon.py::test_three_daemons_discover_publish_leave_die_and_restore" \
    tests/ns/test_changes.py tests/ns/test_supervision.py
