"""sdfrd's REST API as data, written once for both clients (`sdfr.client`, `sdfr.aio`).

Each API call is a function that returns a `Call`: the method, the path, the JSON body, the
error statuses whose body is an answer, whether it may be sent again when sdfrd could not be
reached, and how its answer becomes the result (a record of `sdfr.records.schema` as a JSON object).
Each is a method of both clients (`sdfr.client.core.Api`), with its signature and docstring;
the clients only carry calls over their transport (`http.client` in threads, aiohttp in
asyncio), and both read answers, errors and Server-Sent Events with the functions here.
No I/O here.
"""

from __future__ import annotations

import base64
import functools
import json
import secrets
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, Generic, ParamSpec, TypedDict, TypeVar, cast
from urllib.parse import quote, urlencode

from sdfr.endpoints import DEFAULT_API
from sdfr.endpoints import OWNER_HEADER as OWNER_HEADER  # (where `sdfr.cli` takes it)
from sdfr.errors import ApiError
from sdfr.records import schema
from sdfr.records.model import AttrValue, attr_text

T = TypeVar("T")
P = ParamSpec("P")
JsonObject = schema.JsonObject

#: Pauses before sending a publish again when sdfrd could not be reached (it may restart).
RETRY_DELAYS = (0.2, 1.0)
#: A kept lease is renewed each time this share of its ttl has passed.
RENEW_EVERY = 1 / 3
#: An event stream is given up as dead after this long without a byte (sdfrd sends a
#: keep-alive comment every 15 s).
STREAM_IDLE = 45.0


# -- the answers, typed ------------------------------------------------------------------------
# Answers are the records of `sdfr.records.schema` as decoded JSON objects: each is typed as a dict
# annotated with the record it keeps to.

ServiceJson = Annotated[JsonObject, schema.ServiceOutput]
PublishedJson = Annotated[JsonObject, schema.Published]
RenewedJson = Annotated[JsonObject, schema.Renewed]
LocalServiceJson = Annotated[JsonObject, schema.LocalService]
NeighborJson = Annotated[JsonObject, schema.Neighbor]
PeerJson = Annotated[JsonObject, schema.PeerJson]
SelfJson = Annotated[JsonObject, schema.Self]
HealthJson = Annotated[JsonObject, schema.Health]
KeysJson = Annotated[JsonObject, schema.Keys]


@dataclass(frozen=True, slots=True)
class Change:
    """One event of GET /events: `event` is its kind (robot.appeared, service.expired, ...;
    see docs/api.md), `robot_id` the robot it is about (None: this robot), `data` the whole
    JSON object (`data["services"]`, `data["address"]`, ...)."""

    id: int
    event: str
    time: float
    robot_id: str | None
    data: JsonObject = field(repr=False)

    @classmethod
    def from_json(cls, obj: JsonObject) -> Change:
        return cls(
            id=int(obj["id"]),
            event=str(obj["event"]),
            time=float(obj["time"]),
            robot_id=obj.get("robot_id"),
            data=obj,
        )


class EventsPage(TypedDict):
    events: list[Change]
    last_id: int


# -- the calls ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Call(Generic[T]):
    """One request of the API and how to read its answer."""

    method: str
    path: str
    read: Callable[[Any], T]
    body: JsonObject | None = None
    #: Error statuses whose body is the answer (503 of /health).
    accept: tuple[int, ...] = ()
    #: Safe to send again when sdfrd could not be reached (an idempotent publish).
    retry_unreachable: bool = False


def _field(key: str, method: str, path: str) -> Callable[[Any], Any]:
    def read(answer: Any) -> Any:
        if not isinstance(answer, dict) or key not in answer:
            raise ApiError(0, f"unexpected answer from sdfrd for {method} {path}: no {key!r}")
        return answer[key]

    return read


def _whole(answer: Any) -> Any:
    return answer


def _nothing(answer: Any) -> None:
    return None


def new_service_id() -> str:
    """A fresh service id (12 hex characters), chosen by the client so that a retry of the
    same publish cannot store it twice."""
    return secrets.token_hex(6)


def new_owner_token() -> str:
    """A fresh owner token (256 bits, URL-safe base64): a client's own, sent with each call."""
    return secrets.token_urlsafe(32)


def request_headers(owner_token: str, api_token: str | None) -> dict[str, str]:
    """What every request of a client carries: its owner token, and the token of sdfrd's
    api_token_file when it talks to another machine's API."""
    headers = {"Accept": "application/json", OWNER_HEADER: owner_token}
    if api_token is not None:
        headers["Authorization"] = f"Bearer {api_token}"
    return headers


def service_path(service_id: str) -> str:
    return "/services/" + quote(service_id, safe="")


def neighbors_path(include_unreachable: bool = False) -> str:
    return "/neighbors?all=1" if include_unreachable else "/neighbors"


def search_path(type: str | None = None, attrs: Mapping[str, AttrValue] | None = None) -> str:
    """The search URL; numbers match by value (`30` finds 30.0), booleans as true/false."""
    query: list[tuple[str, str]] = []
    if type is not None:
        query.append(("type", type))
    query += [(f"attr.{key}", attr_text(value)) for key, value in (attrs or {}).items()]
    return "/neighbors/search?" + urlencode(query)


def events_path(since: int | None = None, kinds: Iterable[str] | None = None) -> str:
    query: list[tuple[str, str]] = [] if since is None else [("since", str(since))]
    query += [("event", k) for k in kinds or ()]
    return "/events" + ("?" + urlencode(query) if query else "")


def request(method: str, path: str, body: Any = None, *, accept: tuple[int, ...] = ()) -> Call[Any]:
    """One call of any path: the decoded JSON answer (None when empty); errors raise
    ApiError. `accept` lists error statuses whose body is returned instead."""
    return Call(method, path, _whole, body, accept)


def publish_service(
    name: str,
    type: str,
    url: str | None = None,
    attributes: Mapping[str, AttrValue] | None = None,
    *,
    service_id: str | None = None,
    ttl: float | None = None,
) -> Call[PublishedJson]:
    """Publish a service of this robot; the daemon's answer (id, service, version, ttl,
    expires).

    The id is chosen here (`service_id`, or a fresh one) and sent with the service, so the
    publish is idempotent: when the daemon cannot be reached or the answer is lost, it is
    sent again, and a daemon that stored it already answers 200 instead of storing it
    twice. With `ttl` (seconds) it is a lease: renew it (`renew`), or let `lease` do it.
    """
    body: JsonObject = {"name": name, "type": type, "id": service_id or new_service_id()}
    if url is not None:
        body["url"] = url
    if attributes is not None:
        body["attributes"] = dict(attributes)
    if ttl is not None:
        body["ttl"] = ttl
    return Call("POST", "/services", _whole, body, retry_unreachable=True)


def _answering_id(make: Callable[P, Call[PublishedJson]]) -> Callable[P, Call[str]]:
    @functools.wraps(make)
    def call(*args: P.args, **kwargs: P.kwargs) -> Call[str]:
        made = make(*args, **kwargs)
        read = _field("id", made.method, made.path)
        return Call(made.method, made.path, read, made.body, made.accept, made.retry_unreachable)

    call.__name__ = call.__qualname__ = "publish"
    call.__doc__ = "Publish a service of this robot; returns its id (see `publish_service`)."
    return call


publish = _answering_id(publish_service)


def unpublish(service_id: str) -> Call[None]:
    """Withdraw a service of this robot (only its owner may)."""
    return Call("DELETE", service_path(service_id), _nothing)


def service(service_id: str) -> Call[PublishedJson]:
    """One of this robot's registrations, with its lease."""
    return Call("GET", service_path(service_id), _whole)


def renew(service_id: str, ttl: float | None = None) -> Call[RenewedJson]:
    """Renew a lease: it runs its ttl (or `ttl`) from now again."""
    body = None if ttl is None else {"ttl": ttl}
    return Call("POST", service_path(service_id) + "/renew", _whole, body)


def services() -> Call[list[LocalServiceJson]]:
    """This robot's registrations (with their leases' ttl and end)."""
    return Call("GET", "/services", _field("services", "GET", "/services"))


def neighbors(include_unreachable: bool = False) -> Call[list[NeighborJson]]:
    """The robots reachable now (with `include_unreachable`, all of the history map)."""
    path = neighbors_path(include_unreachable)
    return Call("GET", path, _field("neighbors", "GET", path))


def search(
    type: str | None = None,
    attrs: Mapping[str, AttrValue] | None = None,
    **more_attrs: AttrValue,
) -> Call[list[NeighborJson]]:
    """Reachable robots with a service of `type` whose attributes match the given ones
    (numbers by value, booleans as true/false, text exactly).

    Each robot lists only its matching services. Attributes as keywords
    (`search("camera", fps=30)`) or, for any key, as `attrs={"frame-rate": 30}`.
    """
    path = search_path(type, {**(attrs or {}), **more_attrs})
    return Call("GET", path, _field("neighbors", "GET", path))


def history() -> Call[list[PeerJson]]:
    """Every robot ever seen, reachable or not."""
    return Call("GET", "/history", _field("robots", "GET", "/history"))


def self_info() -> Call[SelfJson]:
    """This robot: its id, address, services and its discovery layer's state."""
    return Call("GET", "/self", _whole)


def health() -> Call[HealthJson]:
    """The daemon's health (`sdfr.records.schema.Health`), also when it answers 503: `status` is
    "ok", "warning" (up, with `warnings`) or "degraded" (HTTP 503: the discovery layer is
    down, starting or failing, or the state directory cannot be written); `discovery` is
    "up", "starting", "failing" or "down"; `state` is "ok", "full", "read-only" or "error"."""
    return Call("GET", "/health", _whole, accept=(503,))


def metrics() -> Call[str]:
    """The Prometheus text of GET /metrics."""
    return Call("GET", "/metrics", str)


def _page(answer: Any) -> EventsPage:
    if not isinstance(answer, dict) or not isinstance(answer.get("events"), list):
        raise ApiError(0, "unexpected answer from sdfrd for GET /events: no 'events'")
    return {
        "events": [Change.from_json(e) for e in answer["events"]],
        "last_id": int(answer["last_id"]),
    }


def events(since: int | None = 0, kinds: Iterable[str] | None = None) -> Call[EventsPage]:
    """The changes kept after `since` (0: all of them), at once; ask again from `last_id`
    (with `since` None: none, and `last_id` is the newest, where to start watching from).
    `kinds`: only these (e.g. `["robot.appeared", "service"]`)."""
    return Call("GET", events_path(since, kinds), _page)


# -- the fleet keyring (over the unix socket only) ---------------------------------------------


def keys() -> Call[KeysJson]:
    """The keyring: mode, the key that signs, and per key its id (never the key)."""
    return Call("GET", "/keys", _whole)


def install_key(key: bytes) -> Call[JsonObject]:
    """Accept `key` from now on (and, for a robot that had no key, sign with it in mode
    accept); the answer has its `id`."""
    return Call("POST", "/keys", _whole, {"key": base64.b64encode(key).decode()})


def use_key(key_id: str) -> Call[JsonObject]:
    """Sign with the installed key `key_id` from now on."""
    return Call("POST", f"/keys/{quote(key_id, safe='')}/use", _whole)


def remove_key(key_id: str, open_fleet: bool = False) -> Call[None]:
    """`open_fleet`: the last key too (in mode accept), leaving an open fleet."""
    query = "?open_fleet=1" if open_fleet else ""
    return Call("DELETE", f"/keys/{quote(key_id, safe='')}{query}", _nothing)


def set_key_mode(mode: str) -> Call[JsonObject]:
    """The keyring's mode: accept, sign or enforce."""
    return Call("PUT", "/keys/mode", _whole, {"mode": mode})


# -- answers, errors, event streams ---------------------------------------------------------------


def split_api(api: str) -> tuple[str, int]:
    hostport = api.removeprefix("http://").rstrip("/")
    host, sep, port = hostport.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"api: expected HOST:PORT (e.g. {DEFAULT_API}), got {api!r}")
    return host.strip("[]"), int(port)


class Unreachable(ApiError):
    """sdfrd could not be reached (status 0): nothing was sent, or no answer came."""


def unreachable(where: str, reason: str, unix: bool) -> Unreachable:
    """sdfrd could not be reached: say what to check."""
    if unix:
        hint = (
            "is sdfrd running with that state directory (the socket is STATE_DIR/api.sock), "
            "and may you open it (root, or the socket's group)?"
        )
    else:
        hint = (
            "is sdfrd running (`systemctl status sdfrd`), and is this its `api` address "
            f"(--api HOST:PORT; default {DEFAULT_API})?"
        )
    return Unreachable(0, f"cannot reach sdfrd at {where}: {reason}; {hint}")


def answer(call: Call[T], status: int, content_type: str, data: bytes) -> T:
    """The result of `call` from sdfrd's answer; ApiError for an error answer."""
    decoded: Any = None
    if data and content_type.startswith("application/json"):
        try:
            decoded = json.loads(data)
        except ValueError:
            raise ApiError(
                status, f"sdfrd sent invalid JSON for {call.method} {call.path}"
            ) from None
    elif data:
        decoded = data.decode("utf-8", errors="replace")
    if status >= 400 and status not in call.accept:
        if isinstance(decoded, dict) and isinstance(decoded.get("error"), str):
            err_field = decoded.get("field")
            raise ApiError(
                status, decoded["error"], err_field if isinstance(err_field, str) else None
            )
        text = decoded.strip()[:200] if isinstance(decoded, str) else ""
        raise ApiError(status, f"HTTP {status} {text}".strip())
    return call.read(decoded)


class SseParser:
    """Server-Sent Events from the lines of a stream (text/event-stream): `feed` one line
    (without its end), get the event it completes, if any."""

    def __init__(self) -> None:
        self._event = ""
        self._data: list[str] = []
        self.last_id: str | None = None

    def feed(self, line: str) -> tuple[str, str] | None:
        """(event name, data) when `line` ends an event."""
        if not line:
            if not self._data:
                self._event = ""
                return None
            out = (self._event or "message", "\n".join(self._data))
            self._event, self._data = "", []
            return out
        if line.startswith(":"):
            return None
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "event":
            self._event = value
        elif name == "data":
            self._data.append(value)
        elif name == "id" and "\0" not in value:
            self.last_id = value
        return None


def change(data: str) -> Change:
    obj = json.loads(data)
    if not isinstance(obj, dict):
        raise ApiError(0, f"sdfrd sent an event that is not a JSON object: {data[:100]!r}")
    return Change.from_json(cast(JsonObject, obj))


#: Headers of a request for an event stream.
STREAM_HEADERS = {"Accept": "text/event-stream", "Cache-Control": "no-cache"}
