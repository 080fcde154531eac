"""systemd's readiness and watchdog protocol (sd_notify), without libsystemd.

A service of `Type=notify` is given the path of a unix datagram socket in NOTIFY_SOCKET
(`@name` for the abstract namespace); the service sends it newline-separated assignments:
`READY=1` once it serves, `STATUS=...` for `systemctl status`, `WATCHDOG=1` at least every
WATCHDOG_USEC microseconds when the unit sets WatchdogSec=, and `STOPPING=1` on the way out.
Without NOTIFY_SOCKET (not under systemd) every call does nothing.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger("sdfrd")


def _address() -> str | None:
    path = os.environ.get("NOTIFY_SOCKET")
    if not path:
        return None
    if path.startswith("@"):  # the abstract namespace
        return "\0" + path[1:]
    return path


def notify(*assignments: str) -> bool:
    """Send `assignments` (e.g. "READY=1", "STATUS=serving") to systemd; False when not
    under a notify service manager, or when the message could not be sent (logged)."""
    address = _address()
    if address is None:
        return False
    message = "\n".join(assignments).encode()
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.sendall(message)
    except OSError as exc:
        log.warning("cannot notify systemd at %s: %s", address.lstrip("\0"), exc)
        return False
    return True


def watchdog_interval() -> float | None:
    """Seconds within which systemd wants WATCHDOG=1 from this process (None: it does not)."""
    usec = os.environ.get("WATCHDOG_USEC", "")
    pid = os.environ.get("WATCHDOG_PID", "")
    if not usec.isdigit() or int(usec) == 0:
        return None
    if pid and (not pid.isdigit() or int(pid) != os.getpid()):
        return None  # meant for another process
    return int(usec) / 1_000_000
