"""/metrics: the Prometheus text exposition of the API's and discovery's counters."""

from __future__ import annotations

import os
import platform
from collections.abc import Callable
from pathlib import Path

from sdfr import DIST_NAME, __version__, wire
from sdfr.api.http import Request, Response
from sdfr.api.state import LATENCY_BUCKETS, ApiState, state_of
from sdfr.host import procfs
from sdfr.records.status import DiscoveryStatus

#: The Prometheus text format's content type.
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
_TICKS = os.sysconf("SC_CLK_TCK")
_PAGE = os.sysconf("SC_PAGE_SIZE")


def _boot_time() -> float:
    """When the machine booted (Unix seconds): process start times count from it."""
    try:
        for line in Path("/proc/stat").read_text().splitlines():
            if line.startswith("btime "):
                return float(line.split()[1])
    except OSError:
        pass
    return 0.0


_BOOT = _boot_time()


def process_stats(pid: int) -> dict[str, float] | None:
    """CPU seconds, resident and virtual memory, start time, open descriptors of `pid`
    (None when it is gone): the standard process_* metrics, from /proc."""
    fields = procfs.stat_fields(pid)
    if fields is None or len(fields) < 22:
        return None
    try:
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        fds = -1
    return {
        "cpu": (int(fields[11]) + int(fields[12])) / _TICKS,
        "start": _BOOT + int(fields[19]) / _TICKS,
        "virtual": float(fields[20]),
        "resident": float(int(fields[21]) * _PAGE),
        "fds": float(fds),
    }


# -- /metrics ----------------------------------------------------------------------------------


def _label(value: object) -> str:
    return str(value).replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def metrics_text(state: ApiState) -> str:
    """The Prometheus text exposition (format 0.0.4)."""
    disc = state.discovery()
    status = disc.status or DiscoveryStatus(pid=0, heartbeat=0.0)  # zeros while there is none
    c = status.counters
    peers = state.view.peers()
    _, local = state.view.local()
    out: list[str] = []

    def family(name: str, kind: str, text: str) -> None:
        out.append(f"# HELP {name} {text}")
        out.append(f"# TYPE {name} {kind}")

    def per_robot(name: str, text: str, values: list[tuple[str, float]]) -> None:
        """A gauge with one sample a robot (its id the label)."""
        family(name, "gauge", text)
        for robot_id, value in values:
            out.append(f'{name}{{robot_id="{_label(robot_id)}"}} {value!r}')

    family(
        "sdfr_datagrams_total",
        "counter",
        "SDfR datagrams received and sent by the discovery layer, by message type.",
    )
    for direction, by_type in (("in", c.datagrams_in), ("out", c.datagrams_out)):
        for kind in [*wire.MESSAGE_TYPES, *sorted(set(by_type) - set(wire.MESSAGE_TYPES))]:
            out.append(
                f'sdfr_datagrams_total{{direction="{direction}",type="{_label(kind)}"}} '
                f"{by_type.get(kind, 0)}"
            )
    family("sdfr_bytes_total", "counter", "UDP payload bytes received and sent.")
    out.append(f'sdfr_bytes_total{{direction="in"}} {c.bytes_in}')
    out.append(f'sdfr_bytes_total{{direction="out"}} {c.bytes_out}')
    family(
        "sdfr_rejects_total",
        "counter",
        "Datagrams rejected (malformed, foreign, unauthenticated, replayed, refused or "
        "rate-limited), by reason.",
    )
    for reason, count in sorted(c.rejects.items()):
        out.append(f'sdfr_rejects_total{{reason="{_label(reason)}"}} {count}')
    family("sdfr_peers", "gauge", "Robots in the history map: reachable now, and known ever.")
    reachable = sum(1 for p in peers if p.reachable)
    out.append(f'sdfr_peers{{state="reachable"}} {reachable}')
    out.append(f'sdfr_peers{{state="known"}} {len(peers)}')
    per_robot(
        "sdfr_peer_indicator",
        "Connection indicator of each reachable robot: the share of recent pings answered.",
        [(p.robot_id, p.indicator) for p in peers if p.reachable and p.indicator is not None],
    )
    per_robot(
        "sdfr_peer_rtt_seconds",
        "Smoothed round-trip time of the pings to each reachable robot.",
        [(p.robot_id, p.rtt_ms / 1000) for p in peers if p.reachable and p.rtt_ms is not None],
    )
    family("sdfr_local_services", "gauge", "Services this robot publishes.")
    out.append(f"sdfr_local_services {len(local)}")
    family("sdfr_discovery_up", "gauge", "1 when the discovery layer is alive and heartbeating.")
    out.append(f"sdfr_discovery_up {int(disc.up)}")
    family(
        "sdfr_discovery_errors",
        "gauge",
        "Failures of the discovery layer's callbacks in the last minute.",
    )
    out.append(f"sdfr_discovery_errors {status.errors.recent}")
    family("sdfr_auth_mode", "gauge", "The keyring's mode (open: no key).")
    for name in ("open", "accept", "sign", "enforce"):
        out.append(f'sdfr_auth_mode{{mode="{name}"}} {int(status.auth.mode == name)}')
    family("sdfr_auth_verified_total", "counter", "Datagrams whose seal checked out, by key id.")
    for kid, count in sorted(status.auth.received.items()):
        out.append(f'sdfr_auth_verified_total{{key="{_label(kid)}"}} {count}')
    family(
        "sdfr_challenges_total",
        "counter",
        "Pings sent to check a claim before believing it (a new robot, an older boot, ...).",
    )
    out.append(f"sdfr_challenges_total {c.challenges}")
    family(
        "sdfr_challenges_limited_total",
        "counter",
        "Challenges not sent because too many were due at once (a flood of claims).",
    )
    out.append(f"sdfr_challenges_limited_total {c.challenges_limited}")
    family(
        "sdfr_invites_total",
        "counter",
        "Extra beacons inviting robots whose first beacon did not pay for a challenge.",
    )
    out.append(f"sdfr_invites_total {c.invites}")
    family(
        "sdfr_robot_id_conflicts_total",
        "counter",
        "Datagrams from another sender claiming this robot's id.",
    )
    conflict = status.robot_id_conflict
    out.append(f"sdfr_robot_id_conflicts_total {0 if conflict is None else conflict.count}")
    family(
        "sdfr_api_request_duration_seconds",
        "histogram",
        "Time the REST API took to answer, by method and route template (an event stream "
        "counts when it ends).",
    )
    for (method, route), hist in sorted(state.latency.items()):
        labels = f'method="{method}",route="{_label(route)}"'
        cumulative = 0
        name = "sdfr_api_request_duration_seconds"
        for bound, n in zip(LATENCY_BUCKETS, hist.buckets, strict=True):
            cumulative += n
            out.append(f'{name}_bucket{{{labels},le="{bound}"}} {cumulative}')
        out.append(f'{name}_bucket{{{labels},le="+Inf"}} {hist.count}')
        out.append(f"{name}_sum{{{labels}}} {hist.total!r}")
        out.append(f"{name}_count{{{labels}}} {hist.count}")
    family("sdfr_event_streams", "gauge", "GET /events streams open now.")
    out.append(f"sdfr_event_streams {state.hub.streams if state.hub is not None else 0}")
    family(
        "sdfr_leases_expired_total", "counter", "Registrations withdrawn as their lease ran out."
    )
    out.append(f"sdfr_leases_expired_total {state.leases.expired if state.leases else 0}")
    family("sdfr_build_info", "gauge", "Always 1; the labels say what runs.")
    out.append(
        f'sdfr_build_info{{version="{__version__}",distribution="{DIST_NAME}",'
        f'python="{platform.python_version()}"}} 1'
    )
    pids = {"api": os.getpid(), "discovery": status.pid if disc.up else 0}
    if pids["discovery"] == pids["api"]:  # --layers threads: one process
        pids = {"both": pids["api"]}
    _process_metrics(out, family, pids)
    return "\n".join(out) + "\n"


def _process_metrics(
    out: list[str], family: Callable[[str, str, str], None], pids: dict[str, int]
) -> None:
    """The standard process_* metrics of both layers' processes, by `layer`."""
    stats = {layer: process_stats(pid) for layer, pid in pids.items() if pid > 0}
    rows = (
        ("process_cpu_seconds_total", "counter", "User and system CPU time spent.", "cpu"),
        ("process_resident_memory_bytes", "gauge", "Resident memory size.", "resident"),
        ("process_virtual_memory_bytes", "gauge", "Virtual memory size.", "virtual"),
        ("process_start_time_seconds", "gauge", "Start time, Unix seconds.", "start"),
        ("process_open_fds", "gauge", "Open file descriptors.", "fds"),
    )
    for name, kind, text, key in rows:
        family(name, kind, text + " By layer (api, discovery; both: threads of one process).")
        for layer, values in sorted(stats.items()):
            if values is not None and values[key] >= 0:
                out.append(f'{name}{{layer="{layer}"}} {values[key]!r}')


async def metrics(request: Request) -> Response:
    state = state_of(request)
    await state.fresh_status()
    body = metrics_text(state).encode()
    return Response(body=body, headers={"Content-Type": CONTENT_TYPE})
