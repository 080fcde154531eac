"""This robot: what it is and announces (`/self`), and its health."""

from __future__ import annotations

import time

from sdfr import __version__
from sdfr.api.http import Request, Response
from sdfr.api.replies import json_response
from sdfr.api.state import FAILING_AFTER, ApiState, DiscoveryState, state_of
from sdfr.records.status import DiscoveryStatus


def _discovery_json(disc: DiscoveryState) -> dict[str, object]:
    s = disc.status
    return {
        "up": disc.up,
        "heartbeat_age": disc.heartbeat_age,
        "pid": None if s is None else s.pid,
        "iface": None if s is None else s.iface,
        "started": None if s is None else s.started,
        "announced_version": None if s is None else s.version,
        "peers_reachable": None if s is None else s.peers_reachable,
        "peers_known": None if s is None else s.peers_known,
    }


async def self_info(request: Request) -> Response:
    state = state_of(request)
    await state.fresh_status()
    disc = state.discovery()
    version, services = state.view.local()
    rec = disc.status
    return json_response(
        {
            "robot_id": state.cfg.robot_id or (None if rec is None else rec.robot_id),
            "fleet": state.cfg.fleet,
            "iface": state.cfg.iface,
            "address": "" if rec is None else rec.address,
            "boot_id": None if rec is None else rec.boot_id,
            "version": version,
            "location": None if rec is None else rec.location,
            "software": f"sdfr/{__version__}",
            "services": [s.to_json() for s in services],
            "discovery": _discovery_json(disc),
        }
    )


def discovery_error(status: DiscoveryStatus) -> str | None:
    """Why the discovery layer, though alive, is failing (None when it is not): its callbacks
    failed FAILING_AFTER times within a minute, or it cannot announce our services."""
    errors = status.errors
    if errors.persistent:
        return errors.persistent
    if errors.recent >= FAILING_AFTER and errors.last is not None:
        return errors.last
    return None


def health_warnings(status: DiscoveryStatus, now: float | None = None) -> list[str]:
    """What an operator should look at while the daemon is up."""
    out = []
    conflict = status.robot_id_conflict
    if conflict is not None:
        ago = max(0.0, (time.time() if now is None else now) - conflict.last_seen)
        out.append(
            f"another sender claims this robot's id {status.robot_id}: {conflict.address} "
            f"(boot {conflict.boot_id}, {ago:.0f} s ago, {conflict.count} datagrams); give "
            "each daemon its own --robot-id"
        )
    for seen in status.auth.unknown:
        ago = max(0.0, (time.time() if now is None else now) - seen.last_seen)
        out.append(
            f"datagrams sealed with key {seen.id}, which the keyring does not hold, are dropped: "
            f"{seen.count} datagrams from {seen.address}, the last {ago:.0f} s ago (a robot left "
            "out of a key rotation?); give it the fleet's key, or `sdfr keys install` its key"
        )
    if status.wifi is not None and status.wifi.warning:
        out.append(status.wifi.warning)
    mode = status.auth.mode
    if mode in ("accept", "sign"):
        out.append(
            f"keyring mode {mode}: unsigned datagrams are accepted; finish with "
            "`sdfr keys mode enforce` on every robot"
        )
    return out


def state_problem(state: ApiState, disc: DiscoveryState) -> tuple[str, str] | None:
    """Why the state directory cannot be written, if it cannot: (full | read-only | error,
    message), from this layer's last failed write (until one works) or the discovery
    layer's report."""
    if state.write_problem is not None and time.time() - state.write_problem[0] < 60.0:
        return state.write_problem[1], state.write_problem[2]
    report = None if disc.status is None else disc.status.state
    if disc.up and report is not None and not report.writable:
        return report.reason or "error", report.error or ""
    return None


async def health(request: Request) -> Response:
    state = state_of(request)
    await state.fresh_status()
    disc = state.discovery()
    failing = discovery_error(disc.status) if disc.up and disc.status else None
    warnings = health_warnings(disc.status) if disc.up and disc.status else []
    cannot_write = state_problem(state, disc)
    starting = disc.up and disc.status is not None and disc.status.starting
    ok = disc.up and not starting and failing is None and cannot_write is None
    return json_response(
        {
            "status": "degraded" if not ok else "warning" if warnings else "ok",
            "api": "up",
            "discovery": ("failing" if failing else "starting" if starting else "up")
            if disc.up
            else "down",
            "discovery_heartbeat_age": disc.heartbeat_age,
            "discovery_error": failing,
            "state": "ok" if cannot_write is None else cannot_write[0],
            "state_error": None if cannot_write is None else cannot_write[1],
            "auth": None if disc.status is None else disc.status.auth.mode,
            "warnings": warnings,
        },
        status=200 if ok else 503,
    )
