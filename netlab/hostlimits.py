"""The one host-wide limit a lab can hit: the kernel's ARP table.

The neighbour table is shared by every network namespace, and its limits
(``net.ipv4.neigh.default.gc_thresh2/3``) exist only in the root
namespace. A full mesh of N robots holds about N*(N+1) entries (each robot
resolves every peer, plus its multicast entries); past gc_thresh3 (1024 by
default, about 31 robots) the kernel refuses new entries ("neighbor table
overflow"), and robots silently stop sending, multicast included.

So a lab that needs more raises the limits, never lowers them, and
remembers the values it found in ``/run/netlab/.host.json``; the last lab
to go down puts them back, unless someone changed them meanwhile.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path

from netlab import manifest
from netlab.errors import NetlabError, kernel_errors

log = logging.getLogger("netlab")

NEIGH_DIR = Path("/proc/sys/net/ipv4/neigh/default")
KEYS = ("gc_thresh2", "gc_thresh3")
HOST_MARGIN = 256  # the host's own neighbours


def mesh_entries(robots: int) -> int:
    """ARP table entries a full mesh of `robots` may hold."""
    return robots * (robots + 1)


def max_mesh(gc_thresh3: int) -> int:
    """The largest full mesh that fits under `gc_thresh3`, with room for the host."""
    n = 0
    while mesh_entries(n + 1) + HOST_MARGIN <= gc_thresh3:
        n += 1
    return n


def _state_file() -> Path:
    return manifest.run_dir() / ".host.json"


def current(neigh: Path = NEIGH_DIR) -> dict[str, int]:
    """The ARP table limits now (only readable from the root namespace)."""
    with kernel_errors("reading the ARP table limits"):
        return {key: int((neigh / key).read_text()) for key in KEYS}


def ensure(entries: int, neigh: Path = NEIGH_DIR) -> bool:
    """Raise the ARP table limits so that `entries` (see `mesh_entries`) fit; True if raised."""
    need = entries + HOST_MARGIN
    if not neigh.exists():
        # Not the initial namespace (a simulated host's ssh session: netlab.hostsim): the
        # limits are the machine's, set from where they are visible, by its own labs.
        return False
    found = current(neigh)
    if found["gc_thresh3"] >= need:
        return False
    wanted = {
        "gc_thresh2": max(found["gc_thresh2"], need),
        "gc_thresh3": max(found["gc_thresh3"], 2 * need),
    }
    state = _state_file()
    with kernel_errors(f"recording the host's ARP table limits in {state}"):
        state.parent.mkdir(parents=True, exist_ok=True)
        saved: dict[str, dict[str, int]] = {"found": found}
        with contextlib.suppress(FileNotFoundError):
            saved = json.loads(state.read_text())  # an earlier lab's originals stay
        saved["set"] = wanted
        tmp = state.with_name(f".host.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(saved))
        tmp.replace(state)
    with kernel_errors("raising the ARP table limits (net.ipv4.neigh.default.gc_thresh3)"):
        # thresh3 first: thresh2 may never exceed it.
        (neigh / "gc_thresh3").write_text(str(wanted["gc_thresh3"]))
        (neigh / "gc_thresh2").write_text(str(wanted["gc_thresh2"]))
    log.warning(
        "netlab: raised the host's ARP table limit gc_thresh3 from %d to %d (labs need about "
        "%d entries); restored when the last lab goes down",
        found["gc_thresh3"],
        wanted["gc_thresh3"],
        entries,
    )
    return True


def restore_if_last(neigh: Path = NEIGH_DIR) -> bool:
    """Put back the limits found before the first raise, once no lab is up; True if done."""
    state = _state_file()
    if manifest.names() or not state.exists():
        return False
    if not neigh.exists():  # not the initial namespace: left to it (see `ensure`)
        return False
    try:
        saved = json.loads(state.read_text())
        found, wanted = saved["found"], saved["set"]
        now = current(neigh)
        if all(now[k] == wanted[k] for k in KEYS):  # nobody else changed them since
            with kernel_errors("restoring the ARP table limits"):
                (neigh / "gc_thresh2").write_text(str(found["gc_thresh2"]))
                (neigh / "gc_thresh3").write_text(str(found["gc_thresh3"]))
    except (NetlabError, OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("netlab: could not restore the ARP table limits: %s", exc)
    state.unlink(missing_ok=True)
    return True
