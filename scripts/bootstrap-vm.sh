#!/usr/bin/env bash
# Set up what a VM tier (`make test-netem`, `make test-radio`: scripts/vm.sh TIER) needs.
# Idempotent and quiet: installs only what is missing.
#
#   scripts/bootstrap-vm.sh [netem|radio]     (default: netem)
#
#  * Debian packages (root): qemu-system-x86 (the emulator), linux-image-amd64
#    (a kernel with sch_netem and mac80211_hwsim as modules), busybox-static (virtme-ng
#    builds its initramfs from busybox); for the radio tier also iw and wpasupplicant,
#    which the guest runs from the host's filesystem (sdfrd joins the fleet's WiFi with
#    them). One apt-get run, so the kernel's initramfs is generated once.
#  * virtme-ng in its own venv, .venv/vm: its dependencies stay out of the
#    project's environment (the host tests run against exactly the project's),
#    and under .venv it is ignored by git and removed by `make distclean`.
#
# Exits non-zero, saying why, when something cannot be installed.
set -euo pipefail
cd "$(dirname "$0")/.."

VIRTME_NG="virtme-ng==1.42"
tier=${1:-netem}
case "$tier" in
netem) module=net/sched/sch_netem.ko ;;
radio) module=drivers/net/wireless/mac80211_hwsim.ko ;;
*)
    echo "bootstrap-vm: usage: scripts/bootstrap-vm.sh [netem|radio] (got $tier)" >&2
    exit 2
    ;;
esac
VM_VENV=.venv/vm

# Both VM tiers may start at once (`make test-vms`): one installs while the other waits.
mkdir -p .venv
exec 9>.venv/.bootstrap-vm.lock
flock 9

die() {
    echo "bootstrap-vm: $*" >&2
    exit 1
}

# A kernel image whose modules include the tier's.
have_kernel() {
    local img ver
    for img in /boot/vmlinuz-*-amd64; do
        [ -e "$img" ] || continue
        ver=${img#/boot/vmlinuz-}
        if compgen -G "/lib/modules/$ver/kernel/$module*" >/dev/null; then
            return 0
        fi
    done
    return 1
}

missing=()
command -v qemu-system-x86_64 >/dev/null 2>&1 || missing+=(qemu-system-x86)
have_kernel || missing+=(linux-image-amd64)
command -v busybox >/dev/null 2>&1 || missing+=(busybox-static)
if [ "$tier" = radio ]; then
    command -v iw >/dev/null 2>&1 || missing+=(iw)
    command -v wpa_supplicant >/dev/null 2>&1 || missing+=(wpasupplicant)
fi

if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" -ne 0 ]; then
        die "not root: cannot install ${missing[*]} (run as root, or install them by hand)"
    fi
    command -v apt-get >/dev/null 2>&1 || die "no apt-get: install by hand: ${missing[*]}"
    echo "bootstrap-vm: apt-get install ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    log=$(mktemp)
    if ! { apt-get update -q && apt-get install -y -q --no-install-recommends "${missing[@]}"; } \
        >"$log" 2>&1 </dev/null; then
        cat "$log" >&2
        rm -f "$log"
        die "apt-get failed"
    fi
    rm -f "$log"
    have_kernel || die "linux-image-amd64 installed, but no /boot/vmlinuz-*-amd64 with $module"
fi

stamp=$VM_VENV/.installed
if [ ! -x "$VM_VENV/bin/vng" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$VIRTME_NG" ]; then
    echo "bootstrap-vm: pip install $VIRTME_NG into $VM_VENV"
    PY=${PYTHON:-python3}
    [ -x .venv/bin/python ] && PY=.venv/bin/python
    log=$(mktemp)
    if ! { [ -x "$VM_VENV/bin/python" ] || "$PY" -m venv "$VM_VENV"; } >"$log" 2>&1 ||
        ! "$VM_VENV/bin/python" -m pip install -q --disable-pip-version-check --no-input \
            "$VIRTME_NG" >>"$log" 2>&1 </dev/null; then
        cat "$log" >&2
        rm -f "$log"
        die "pip install $VIRTME_NG failed"
    fi
    rm -f "$log"
    echo "$VIRTME_NG" >"$stamp"
fi
