#!/usr/bin/env bash
# The VM tiers: tests that need kernel modules this machine's kernel lacks, run inside a
# Debian kernel that has them.
#
#   scripts/vm.sh netem [PYTEST ARGS...]   sch_netem: link shaping (default: -v -s tests/netem)
#   scripts/vm.sh radio [PYTEST ARGS...]   mac80211_hwsim: 802.11 radios (default: -v -s tests/radio)
#
# This machine's kernel has no modules at all (see ../shared/ENVIRONMENT.md), so the
# newest /boot/vmlinuz-*-amd64 is booted with virtme-ng under QEMU: the guest
# sees the host's filesystem read-only (with a writable overlay on /tmp, /etc,
# /var...), so the project's .venv and the host's iw and wpa_supplicant run there as they
# are. Results come back through a --rwdir: pytest's output, its JUnit XML and its exit
# status, which becomes this script's. Every test must run: a skip inside the VM fails the
# tier.
#
# Environment:
#   SDFR_SKIP_VM=1        skip every VM tier (says so; exit 0)
#   SDFR_SKIP_NETEM=1     skip the netem tier; SDFR_SKIP_RADIO=1 the radio tier
#   SDFR_VM_TIMEOUT=S     seconds before the VM is killed and the tier fails (900; radio 2100)
#   SDFR_VM_KERNEL=PATH   the kernel image to boot (default: newest Debian amd64)
#   SDFR_VM_KVM=1         use KVM (default off: it hangs on the CI machines)
#   SDFR_KEEP_LOGS=DIR    where a failed test's lab folders go (default: $TMPDIR or /tmp)
#   SDFR_VM_PLAN=1        say which module and tests the VM would have, and stop there
#
# A failed test's lab folders (every robot's sdfrd.log and state, the pcaps) are copied out
# of the guest as the test fails (tests/support/vmkeep.py), into a new folder
# sdfr-vm-TIER-logs.XXXXXX under SDFR_KEEP_LOGS that the guest may write, with vm-load.log
# (the guest's load and busiest processes every 30 s); the failure and this script's last lines
# say where. No test failed: the folder is removed.
#
# No leftovers: the VM runs in a process group of its own (timeout's), which is
# killed on timeout, Ctrl-C or any exit; the results directory is removed.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)

tier=${1:-}
case "$tier" in
netem)
    skip_var=SDFR_SKIP_NETEM
    modules='modprobe sch_netem'
    ;;
radio)
    skip_var=SDFR_SKIP_RADIO
    # No radio at load: each lab makes its own over generic netlink (netlab/hwsim.py).
    modules='modprobe mac80211_hwsim radios=0'
    ;;
*)
    echo "vm: usage: scripts/vm.sh netem|radio [PYTEST ARGS...] (got ${tier:-nothing})" >&2
    exit 2
    ;;
esac
shift
me="vm-$tier"

if [ "${SDFR_SKIP_VM:-0}" = 1 ]; then
    echo "$me: SKIPPED (SDFR_SKIP_VM=1): the $tier tier did not run"
    exit 0
fi
if [ "${!skip_var:-0}" = 1 ]; then
    echo "$me: SKIPPED ($skip_var=1): the $tier tier did not run"
    exit 0
fi
pytest_args=("$@")
[ ${#pytest_args[@]} -gt 0 ] || pytest_args=(-v -s "tests/$tier")
hot_dirs=("tests/$tier")
if [ "${SDFR_VM_PLAN:-0}" = 1 ]; then
    echo "$me: would boot with \`$modules\` and run pytest $(printf '%q ' "${pytest_args[@]}")"
    exit 0
fi

bash scripts/bootstrap-vm.sh "$tier"
export PATH="$repo/.venv/vm/bin:$PATH" # vng runs virtme-run from PATH

kernel=${SDFR_VM_KERNEL:-}
if [ -z "$kernel" ]; then
    kernel=$(printf '%s\n' /boot/vmlinuz-*-amd64 | sort -V | tail -n 1)
fi
kver=${kernel#/boot/vmlinuz-}
[ -r "$kernel" ] || {
    echo "$me: FAILED: no kernel image $kernel" >&2
    exit 1
}
[ -d "/lib/modules/$kver" ] || {
    echo "$me: FAILED: no modules for $kver in /lib/modules" >&2
    exit 1
}

# The radio tier's labs take minutes each to join their WiFi under emulation (about 20 in all).
default_limit=900
[ "$tier" = radio ] && default_limit=2100
limit=${SDFR_VM_TIMEOUT:-$default_limit}

res=$(mktemp -d -t sdfr-$me.XXXXXX)

# The guest reads the host's files over 9p with no page cache, under emulation: each Python
# process reads libpython and every module it imports through the emulated device again.
# The files the tier's Python processes read at start (scripts/vm_hot.py) go into the
# guest's memory, laid over their folders (about twice as fast a start; see vm_hot.py).
# Without them (a failure here, or in the guest) the tier runs as before, only slower.
hot_roots=""
if .venv/bin/python scripts/vm_hot.py "${hot_dirs[@]}" >"$res/hot.list" 2>"$res/hot.err" &&
    sed 's,^/,,' "$res/hot.list" | tar -C / -cf "$res/hot.tar" -T - 2>>"$res/hot.err"; then
    base=$(.venv/bin/python -c 'import os, sys; print(os.path.realpath(sys.base_prefix))')
    real=$(pwd -P)
    hot_roots=$( {
        echo "$real"
        echo "$base"
        grep -v -e "^$real/" -e "^$base/" "$res/hot.list" | xargs -r -n1 dirname
    } | sort -u | tr '\n' ' ')
else
    echo "$me: the files Python reads at start stay on 9p (slower):" \
        "$(tail -n 1 "$res/hot.err")" >&2
fi
keep_root=${SDFR_KEEP_LOGS:-${TMPDIR:-/tmp}}
mkdir -p "$keep_root"
keep=$(mktemp -d "$keep_root/sdfr-$me-logs.XXXXXX")
keep=$(cd "$keep" && pwd -P) # the same path in the guest: absolute, no links
vm_pgid="" # timeout's pid, and the id of the process group of the whole VM
vm_reaped=""
tail_pid=""

stop_vm() {
    # The group: timeout, vng, virtme-run and qemu. Ask timeout to stop it (it passes the
    # signal on to the group), give it 20 s to go, then kill what is left.
    [ -n "$vm_pgid" ] || return 0
    # Only while timeout is our unreaped child: its pid cannot have been reused.
    [ -n "$vm_reaped" ] || kill -TERM "$vm_pgid" 2>/dev/null || true
    for _ in $(seq 40); do
        kill -0 -- "-$vm_pgid" 2>/dev/null || break
        sleep 0.5
    done
    kill -KILL -- "-$vm_pgid" 2>/dev/null || true
    wait "$vm_pgid" 2>/dev/null || true
    vm_pgid=""
}

cleanup() {
    trap '' INT TERM # a second Ctrl-C must not cut the clean-up short
    stop_vm
    if [ -n "$tail_pid" ]; then
        kill "$tail_pid" 2>/dev/null || true
        wait "$tail_pid" 2>/dev/null || true
    fi
    if [ -n "$(ls -A "$keep" 2>/dev/null)" ] && [ -s "$res/vm-load.log" ]; then
        cp "$res/vm-load.log" "$keep/" 2>/dev/null || true
    fi
    rm -rf "$res"
    if [ -n "$(ls -A "$keep" 2>/dev/null)" ]; then
        echo "$me: the failed tests' lab folders (daemon logs, state, pcaps) are kept" \
            "in $keep" >&2
    else
        rmdir "$keep" 2>/dev/null || true
    fi
}
trap cleanup EXIT
trap 'echo "$me: interrupted, stopping the VM" >&2; exit 130' INT
trap 'echo "$me: terminated, stopping the VM" >&2; exit 143' TERM

# What runs inside the guest (as root, cwd the repository); its $ expand there.
# shellcheck disable=SC2016
{
    echo 'set -u'
    printf 'res=%q\n' "$res"
    printf 'cd %q\n' "$repo"
    echo 'echo "vm: up after $(cut -d" " -f1 /proc/uptime)s: kernel $(uname -r), $(nproc) cpu"'
    printf 'if ! %s; then touch "$res/no-module"; exit 0; fi\n' "$modules"
    echo 'export PYTHONDONTWRITEBYTECODE=1 # the repository is read-only in the guest'
    printf 'hot_roots=%q\n' "$hot_roots"
    echo 'if [ -n "$hot_roots" ] && mkdir -p /run/sdfr-hot &&'
    echo '    mount -t tmpfs -o mode=0755 sdfr-hot /run/sdfr-hot && tar -C /run/sdfr-hot -xf "$res/hot.tar"; then'
    echo '    for d in $hot_roots; do'
    echo '        [ -d "/run/sdfr-hot$d" ] || continue'
    echo '        mount -t overlay -o "ro,lowerdir=/run/sdfr-hot$d:$d" sdfr-hot "$d" ||'
    echo '            echo "vm: $d stays on 9p (slower): no overlay" >&2'
    echo '    done'
    echo '    echo "vm: $(du -sh /run/sdfr-hot | cut -f1) of files Python reads at start in memory"'
    printf '    cd %q # through the overlay\n' "$repo"
    echo 'fi'
    printf 'export SDFR_KEEP_LOGS=%q # a failed test copies its lab folders there\n' "$keep"
    # What loads the guest's one CPU, every 30 s (kept beside a failed test's folders): a
    # fleet's deadlines fail when the CPU cannot keep up, and this says whether it could:
    # the CPU's busy and idle ticks so far, and the processes that used most of it (their
    # CPU time so far). (`top` every 10 s cost the guest 5-13 % of its CPU; this, less.)
    echo '( while :; do echo "== $(cut -d" " -f1 /proc/uptime)s up, load $(cut -d" " -f1-4 /proc/loadavg), $(head -n 1 /proc/stat), MemAvailable $(awk "/MemAvailable/ {print \$2}" /proc/meminfo) kB";'
    echo '    ps -eo pid,times,args --sort=-times | head -n 9 | cut -c1-160; sleep 30; done ) >"$res/vm-load.log" 2>&1 &'
    echo 'load_pid=$!'
    # The guest's /tmp is an overlay whose lower layer is the host's /tmp, live: pytest there
    # numbers its folder after the host's pytest-of-root/pytest-N and sweeps old ones, while the
    # host's runs make and delete theirs underneath (undefined for an overlay). The tests' folders
    # (the labs, their daemons' sockets and state) go on a tmpfs of the guest's own instead.
    echo 'mkdir -p /run/sdfr-vm && mount -t tmpfs -o mode=0700 sdfr-vm /run/sdfr-vm ||'
    echo '    { echo "vm: cannot mount a tmpfs on /run/sdfr-vm for the tests folders" >&2; exit 1; }'
    echo 'export TMPDIR=/run/sdfr-vm SDFR_VM_GUEST=1'
    # Not the hypothesis, schemathesis and anyio plugins: these tests use none of them, and
    # importing them was most of pytest's start-up (natively 5.4 s with them, 1.1 s without;
    # under emulation that is minutes).
    printf '.venv/bin/python -m pytest -p no:cacheprovider -p no:hypothesispytest -p no:schemathesis -p no:anyio -p no:xdist --durations=20 --basetemp=/run/sdfr-vm/pytest --junitxml="$res/junit.xml" %s 2>&1 | tee "$res/pytest.log"\n' \
        "$(printf '%q ' "${pytest_args[@]}")"
    echo 'echo "${PIPESTATUS[0]}" >"$res/rc"'
    echo 'kill "$load_pid" 2>/dev/null'
    echo 'echo "vm: pytest done after $(cut -d" " -f1 /proc/uptime)s of uptime"'
} >"$res/inner.sh"

# One vCPU: under software emulation on a 2-core machine a second one made the guest
# 2-3 times slower (its vCPU threads contend with each other and the host).
vng_args=(--run "$kernel" --user root --cpus 1 --memory 1G --rwdir "$res" --rwdir "$keep"
    --cwd "$repo")
[ "${SDFR_VM_KVM:-0}" = 1 ] || vng_args+=(--disable-kvm)

echo "$me: booting $kver under QEMU$([ "${SDFR_VM_KVM:-0}" = 1 ] || echo ' (software emulation)'), limit ${limit}s"
start=$SECONDS
# timeout puts itself and the VM in a new process group, killed as a whole on expiry.
# vng's own temporary files go under $res too (TMPDIR), so they go with it.
mkdir "$res/tmp"
: >"$res/vm.log" # before tail follows it: the VM's redirection may come later
TMPDIR="$res/tmp" timeout -k 20 "$limit" vng "${vng_args[@]}" --exec "bash $res/inner.sh" \
    </dev/null >"$res/vm.log" 2>&1 &
vm_pgid=$!
tail -n +1 -s 0.5 -f --pid="$vm_pgid" "$res/vm.log" &
tail_pid=$!
vm_status=0
wait "$vm_pgid" || vm_status=$?
vm_reaped=1
stop_vm # whatever of the VM outlived vng (qemu exits after it)
wait "$tail_pid" 2>/dev/null || true
tail_pid=""
elapsed=$((SECONDS - start))

if [ "$vm_status" = 124 ] || [ "$vm_status" = 137 ]; then
    echo "$me: FAILED: the VM ran over ${limit}s and was killed (SDFR_VM_TIMEOUT)" >&2
    exit 1
fi
if [ -e "$res/no-module" ]; then
    echo "$me: FAILED: \`$modules\` failed in the guest ($kver)" >&2
    exit 1
fi
if [ ! -s "$res/rc" ]; then
    echo "$me: FAILED: the VM (vng exit $vm_status, ${elapsed}s) reported no test result;" \
        "its output is above" >&2
    exit 1
fi
rc=$(cat "$res/rc")

# The JUnit totals: every collected test must have run (no skips in the VM).
summary=$(.venv/bin/python - "$res/junit.xml" <<'EOF'
import sys
import xml.etree.ElementTree as ET

root = ET.parse(sys.argv[1]).getroot()
suite = root if root.tag == "testsuite" else root.find("testsuite")
n = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
print(n["tests"], n["failures"], n["errors"], n["skipped"], suite.get("time", "?"))
EOF
) || summary=""
read -r tests failures errors skipped ptime <<<"${summary:-0 0 0 0 ?}"
echo "$me: $tests tests in the VM: $((tests - failures - errors - skipped)) passed," \
    "$failures failed, $errors errors, $skipped skipped (pytest ${ptime}s, VM ${elapsed}s in all)"
if [ "$rc" != 0 ]; then
    echo "$me: FAILED: pytest exited $rc in the VM" >&2
    exit "$rc"
fi
if [ "$tests" = 0 ] || [ "$skipped" != 0 ]; then
    echo "$me: FAILED: tests were skipped or none ran in the VM, where the $tier tier must work" >&2
    exit 1
fi
echo "$me: passed"
