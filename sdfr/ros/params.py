"""The node's parameters, the same for ROS 1 and ROS 2, validated in one place."""

from __future__ import annotations

import shlex
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from sdfr.client import split_api
from sdfr.endpoints import DEFAULT_API
from sdfr.errors import ConfigError

#: Bounds of the polling interval: polling faster only loads the daemon, slower makes the
#: node late by that much.
POLL_MIN, POLL_MAX = 0.02, 10.0
DIAG_MIN, DIAG_MAX = 0.1, 60.0


@dataclass(frozen=True, slots=True)
class NodeParams:
    """Every parameter of the `sdfr` node (its ROS parameter of the same name)."""

    api: str = DEFAULT_API
    spawn: bool = True
    sdfrd_command: str = "sdfrd"
    sdfrd_config: str = ""
    fleet: int = -1
    sdfrd_args: str = ""
    sdfrd_log: str = ""
    spawn_timeout: float = 20.0
    poll_interval: float = 0.25
    diagnostics_period: float = 1.0

    def __post_init__(self) -> None:
        try:
            split_api(self.api)
        except ValueError as exc:
            raise ConfigError(f"parameter {exc}") from None
        if not self.sdfrd_command.strip():
            raise ConfigError("parameter sdfrd_command: must name a program (e.g. sdfrd)")
        for name in ("sdfrd_command", "sdfrd_args"):
            try:
                shlex.split(getattr(self, name))
            except ValueError as exc:
                raise ConfigError(f"parameter {name}: {exc}") from None
        if not -1 <= self.fleet <= 255:
            raise ConfigError(f"parameter fleet: must be 0-255 (or -1: sdfrd's), got {self.fleet}")
        if not 1.0 <= self.spawn_timeout <= 300.0:
            raise ConfigError(
                f"parameter spawn_timeout: must be 1-300 seconds, got {self.spawn_timeout}"
            )
        if not POLL_MIN <= self.poll_interval <= POLL_MAX:
            raise ConfigError(
                f"parameter poll_interval: must be {POLL_MIN}-{POLL_MAX} seconds, "
                f"got {self.poll_interval}"
            )
        if not DIAG_MIN <= self.diagnostics_period <= DIAG_MAX:
            raise ConfigError(
                f"parameter diagnostics_period: must be {DIAG_MIN}-{DIAG_MAX} seconds, "
                f"got {self.diagnostics_period}"
            )

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> NodeParams:
        """Parameters from ROS (name -> value); a wrong type or an unknown name is an error
        naming it."""
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ConfigError(
                f"unknown parameter(s) {', '.join(unknown)} (known: {', '.join(known)})"
            )
        kw: dict[str, Any] = {}
        for name, value in values.items():
            default = getattr(cls(), name)
            kw[name] = _coerce(name, value, type(default))
        return cls(**kw)

    def sdfrd_argv(self) -> list[str]:
        """The command that starts sdfrd for this node's API, fleet and config."""
        argv = [*shlex.split(self.sdfrd_command), "--api", self.api]
        if self.sdfrd_config:
            argv += ["--config", self.sdfrd_config]
        if self.fleet >= 0:
            argv += ["--fleet", str(self.fleet)]
        return argv + shlex.split(self.sdfrd_args)


def _coerce(name: str, value: Any, kind: type) -> Any:
    if kind is bool:
        if isinstance(value, bool):
            return value
    elif kind is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif kind is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
    elif isinstance(value, str):
        return value
    raise ConfigError(f"parameter {name}: expected {kind.__name__}, got {value!r}")


#: What each parameter means: for the YAML file, the launch file and `--help`.
DESCRIPTIONS = {
    "api": "HOST:PORT of the local sdfrd's REST API",
    "spawn": "start sdfrd when none answers at `api` (and stop it on shutdown; never one the "
    "node did not start)",
    "sdfrd_command": "the command that starts sdfrd (split like a shell would)",
    "sdfrd_config": "sdfrd's TOML configuration for a daemon the node starts (--config)",
    "fleet": "fleet id 0-255 for a daemon the node starts (--fleet); -1: its config's or 1",
    "sdfrd_args": "more sdfrd flags for a daemon the node starts, e.g. '--iface wlan0'",
    "sdfrd_log": "file for the output of a daemon the node starts (default: a file in /tmp)",
    "spawn_timeout": "seconds to wait for a started sdfrd to answer",
    "poll_interval": "seconds between reads of the neighbour list when sdfrd has no change "
    f"stream (GET /events) to follow ({POLL_MIN}-{POLL_MAX})",
    "diagnostics_period": "seconds between health reports on /diagnostics",
}
