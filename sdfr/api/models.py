"""The local API's bodies as typed models: the OpenAPI document's schemas are generated from
these (with the service models of `sdfr.model`), and schemathesis checks in `make test` that
every answer the handlers build keeps to them."""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta, Struct

from sdfr.model import ServiceInput, ServiceOutput

Mode = Literal["accept", "sign", "enforce"]
Seconds = Annotated[float, Meta(description="Unix time")]


class Error(Struct):
    """An error; `field` names the offending field or parameter."""

    error: str
    field: str | None


class Published(Struct):
    id: str
    service: ServiceOutput
    version: int


class Services(Struct):
    services: list[ServiceOutput]
    version: Annotated[int, Meta(description="Bumped by every publish and unpublish")]


class Neighbor(Struct):
    robot_id: str
    address: Annotated[str, Meta(description="IPv4 address on the fleet network")]
    reachable: bool
    indicator: (
        Annotated[float, Meta(description="Connection indicator: success rate 0-1 of recent pings")]
        | None
    )
    rtt_ms: Annotated[float, Meta(description="Mean round-trip time of recent pings")] | None
    last_seen: Annotated[float, Meta(description="Unix time the robot was last heard")]
    services: list[ServiceOutput]


class Neighbors(Struct):
    neighbors: list[Neighbor]


class PeerJson(Struct):
    """A robot of the history map (`sdfr.model.PeerRecord` as the API shows it)."""

    robot_id: str
    address: str
    location: Annotated[str, Meta(description="URL of its description")]
    reachable: bool
    indicator: float | None
    rtt_ms: float | None
    boot_id: int
    version: Annotated[int, Meta(description="Version of its service set")]
    first_seen: Seconds
    last_seen: Seconds
    services: list[ServiceOutput]


class History(Struct):
    robots: list[PeerJson]


class DiscoveryInfo(Struct):
    up: bool
    heartbeat_age: float | None
    pid: int | None
    iface: str | None
    started: float | None
    announced_version: int | None
    peers_reachable: int | None
    peers_known: int | None


class Self(Struct):
    robot_id: str | None
    fleet: int
    iface: str | None
    address: str
    boot_id: int | None
    version: int
    location: str | None
    software: str
    services: list[ServiceOutput]
    discovery: DiscoveryInfo


class Health(Struct):
    status: Annotated[
        Literal["ok", "warning", "degraded"],
        Meta(
            description="degraded: the discovery layer is down or failing, or the state "
            "directory cannot be written (503); warning: up, with warnings"
        ),
    ]
    api: Literal["up"]
    discovery: Annotated[
        Literal["up", "failing", "down"],
        Meta(
            description="failing: alive, but its work keeps failing or it cannot announce "
            "this robot's services (see discovery_error)"
        ),
    ]
    discovery_heartbeat_age: float | None
    discovery_error: str | None
    state: Annotated[
        Literal["ok", "full", "read-only", "error"],
        Meta(
            description="Whether the state directory can be written (publishes need it); not "
            "ok answers 503 with the discovery layer up"
        ),
    ]
    state_error: str | None
    auth: Annotated[
        Literal["open", "accept", "sign", "enforce"] | None,
        Meta(description="The keyring's mode; open: no fleet key"),
    ]
    warnings: Annotated[list[str], Meta(description="e.g. another daemon claims this robot's id")]


class KeyInfo(Struct):
    id: Annotated[str, Meta(description="8 hex characters")]
    primary: bool
    installed: float | None
    received: Annotated[
        int, Meta(description="Datagrams verified with it since the discovery layer started")
    ]


class Keys(Struct):
    mode: Literal["open", "accept", "sign", "enforce"]
    primary: Annotated[str | None, Meta(description="The key that signs")]
    keyed: bool
    ssdp_interop: bool
    keys: list[KeyInfo]


class KeyInstall(Struct, forbid_unknown_fields=True):
    key: Annotated[str, Meta(description="base64, 32 bytes")]


class KeyMode(Struct, forbid_unknown_fields=True):
    mode: Mode


MODELS = (
    ServiceInput,
    ServiceOutput,
    Error,
    Published,
    Services,
    Neighbors,
    History,
    Self,
    Health,
    Keys,
    KeyInstall,
    KeyMode,
)
#: Component names other than the class's own.
RENAMED = {"ServiceOutput": "Service", "PeerJson": "PeerRecord"}


def components() -> dict[str, Any]:
    """Every model's JSON Schema, by component name, with references between them."""
    _, schemas = msgspec.json.schema_components(MODELS, ref_template="#/components/schemas/{name}")
    text = json.dumps(schemas)
    for old, new in RENAMED.items():
        text = text.replace(f'"#/components/schemas/{old}"', f'"#/components/schemas/{new}"')
    out: dict[str, Any] = {RENAMED.get(k, k): v for k, v in json.loads(text).items()}
    for schema in out.values():
        schema.pop("title", None)
    return out
