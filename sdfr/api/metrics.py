"""/metrics: the Prometheus text exposition of the API's and discovery's counters."""

from __future__ import annotations

from aiohttp import web

from sdfr import wire
from sdfr.api.state import LATENCY_BUCKETS, ApiState, state_of
from sdfr.status import DiscoveryStatus

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
        "sdfr_robot_id_conflicts_total",
        "counter",
        "Datagrams from another sender claiming this robot's id.",
    )
    conflict = status.robot_id_conflict
    out.append(f"sdfr_robot_id_conflicts_total {0 if conflict is None else conflict.count}")
    family(
        "sdfr_api_request_seconds",
        "histogram",
        "Time the REST API took to answer, by method and route template.",
    )
    for (method, route), hist in sorted(state.latency.items()):
        labels = f'method="{method}",route="{_label(route)}"'
        cumulative = 0
        for bound, n in zip(LATENCY_BUCKETS, hist.buckets, strict=True):
            cumulative += n
            out.append(f'sdfr_api_request_seconds_bucket{{{labels},le="{bound}"}} {cumulative}')
        out.append(f'sdfr_api_request_seconds_bucket{{{labels},le="+Inf"}} {hist.count}')
        out.append(f"sdfr_api_request_seconds_sum{{{labels}}} {hist.total!r}")
        out.append(f"sdfr_api_request_seconds_count{{{labels}}} {hist.count}")
    return "\n".join(out) + "\n"


async def metrics(request: web.Request) -> web.Response:
    body = metrics_text(state_of(request)).encode()
    return web.Response(body=body, headers={"Content-Type": "text/plain; version=0.0.4"})
