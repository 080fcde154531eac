"""The REST API's records, once: what sdfrd answers and accepts, as msgspec types.

The server builds and validates its bodies with them and generates the OpenAPI document's
schemas from them (`sdfr.api.models`); the clients' answers are these records as JSON
objects (`sdfr.client.calls`), and the ROS bridge decodes its answers into them. Nothing of the
daemon is imported here: the clients load this without the wire codec or the protocol.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from msgspec import Meta, Struct

from sdfr.records.model import ServiceInput, ServiceOutput

#: A JSON object as decoded from an answer.
JsonObject = dict[str, Any]

Mode = Literal["accept", "sign", "enforce"]
Seconds = Annotated[float, Meta(description="Unix time")]


class Error(Struct):
    """An error; `field` names the offending field or parameter."""

    error: str
    field: str | None


Ttl = Annotated[
    float,
    Meta(
        ge=1,
        le=366 * 86400,
        description="Seconds the registration lives unless renewed (a lease): its owner renews "
        "it (POST /services/{id}/renew, or holds it with POST /services/{id}/hold); when it "
        "runs out the service is withdrawn from the fleet like an unpublish. Left out or "
        "null: it lives until unpublished.",
    ),
]
Expires = Annotated[float, Meta(description="Unix time the lease runs out unless renewed")]


class Registration(ServiceInput, forbid_unknown_fields=True):
    """A registration: a service, optionally with a lease (`ttl`)."""

    ttl: Ttl | None = None


class Published(Struct):
    id: str
    service: ServiceOutput
    version: int
    ttl: Annotated[float, Meta(description="The lease's ttl; null: no lease")] | None
    expires: Expires | None
    owner_token: (
        Annotated[
            str,
            Meta(
                description="The token the service belongs to: send it as X-SDFR-Owner to "
                "unpublish, renew, hold or publish it again (the one the request sent, or one "
                "made for it). Null in GET /services/{id}, and in a publish again allowed by "
                "the unix socket's user"
            ),
        ]
        | None
    )


class LocalService(ServiceOutput):
    """A registration of this robot: the service, and its lease (nulls when it has none)."""

    ttl: float | None
    expires: Expires | None


class Services(Struct):
    services: list[LocalService]
    version: Annotated[int, Meta(description="Bumped by every publish and unpublish")]


class Renewal(Struct, forbid_unknown_fields=True):
    ttl: Ttl | None = None


class Renewed(Struct):
    id: str
    ttl: float
    expires: Expires


class ChangeEvent(Struct):
    """One change (the `data` of a Server-Sent Event; its `event` names the kind). More
    fields by kind: `address`, `indicator`, `new`, `services` (robot.appeared); `added`,
    `removed`, `changed` (robot.services); `previous` (robot.address); `threshold`,
    `direction` (robot.indicator); `last_seen` (robot.left, robot.unreachable); `service`,
    `ttl`, `expires` (service.*); `after` (resync). A services list over 8 KiB is left out
    (`services_truncated`, `services_count`)."""

    id: Annotated[int, Meta(description="Grows with every event; resume with Last-Event-ID")]
    event: str
    time: Seconds
    robot_id: Annotated[str | None, Meta(description="null: this robot")]


class Events(Struct):
    events: list[ChangeEvent]
    last_id: Annotated[int, Meta(description="Ask again with since=last_id for what follows")]


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
    """A robot of the history map (`sdfr.records.model.PeerRecord` as the API shows it)."""

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
            description="degraded: the discovery layer is down, starting or failing, or the state "
            "directory cannot be written (503); warning: up, with warnings"
        ),
    ]
    api: Literal["up"]
    discovery: Annotated[
        Literal["up", "starting", "failing", "down"],
        Meta(
            description="starting: alive, not yet speaking on the fleet's network (its "
            "address not yet bound, its description not yet served; 503); failing: alive, "
            "but its work keeps failing or it cannot announce this robot's services (see "
            "discovery_error)"
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


class UnknownKeyInfo(Struct):
    id: Annotated[str, Meta(description="8 hex characters, as the refused seals name it")]
    address: Annotated[str, Meta(description="Where the latest came from")]
    count: Annotated[int, Meta(description="Datagrams refused since first_seen")]
    first_seen: float
    last_seen: float


class Keys(Struct):
    mode: Literal["open", "accept", "sign", "enforce"]
    primary: Annotated[str | None, Meta(description="The key that signs")]
    keyed: bool
    ssdp_interop: bool
    keys: list[KeyInfo]
    unknown: Annotated[
        list[UnknownKeyInfo],
        Meta(
            description="Key ids of datagrams refused lately (within the miss window) because "
            "the keyring does not hold them: a robot left out of a key rotation; left out "
            "when there are none"
        ),
    ] = []


class KeyInstall(Struct, forbid_unknown_fields=True):
    key: Annotated[str, Meta(description="base64, 32 bytes")]


class KeyMode(Struct, forbid_unknown_fields=True):
    mode: Mode
