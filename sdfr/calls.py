"""sdfrd's REST API as data, written once for both clients (`sdfr.client`, `sdfr.aio`).

Each API call is a function that returns a `Call`: the method, the path, the JSON body, the
error statuses whose body is an answer, whether it may be sent again when sdfrd could not be
reached, and how its answer becomes the result. The clients only carry calls over their
transport (`http.client` in threads, aiohttp in asyncio), and both read answers, errors and
Server-Sent Events with the functions here. No I/O here.
"""

from __future__ import annotations

import json
import secrets
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypedDict, TypeVar, cast
from urllib.parse import quote, urlencode

from sdfr.config import DEFAULT_API
from sdfr.errors import ApiError
from sdfr.model import AttrValue, attr_text

T = TypeVar("T")
JsonObject = dict[str, Any]

#: Pauses before sending a publish again when sdfrd could not be reached (it may restart).
RETRY_DELAYS = (0.2, 1.0)
#: A kept lease is renewed each time this share of its ttl has passed.
RENEW_EVERY = 1 / 3
#: An event stream is given up as dead after this long without a byte (sdfrd sends a
#: keep-alive comment every 15 s).
STREAM_IDLE = 45.0
#: The header a client sends its owner token in: what it publishes is its own, and only
#: a request with the same token (or, on the unix socket, by the same user) may unpublish,
#: renew, hold or publish it again.
OWNER_HEADER = "X-SDFR-Owner"


# -- the answers, typed -------------------------------------------------------------------------
# (neighbors, search, history and services answer plain dicts, as they always did, so that code
# typed against them keeps checking; these TypedDicts describe them for a `cast`.)


class ServiceJson(TypedDict):
    id: str
    name: str
    type: str
    url: str | None
    attributes: dict[str, AttrValue]


class LocalServiceJson(ServiceJson):
    ttl: float | None
    expires: float | None


class Published(TypedDict):
    id: str
    service: ServiceJson
    version: int
    ttl: float | None
    expires: float | None
    #: The token the service belongs to (the one the client sent; null in GET /services/ID).
    owner_token: str | None


class Renewed(TypedDict):
    id: str
    ttl: float
    expires: float


class Neighbor(TypedDict):
    robot_id: str
    address: str
    reachable: bool
    indicator: float | None
    rtt_ms: float | None
    last_seen: float
    services: list[ServiceJson]


class PeerJson(TypedDict):
    robot_id: str
    address: str
    location: str
    reachable: bool
    indicator: float | None
    rtt_ms: float | None
    boot_id: int
    version: int
    first_seen: float
    last_seen: float
    services: list[ServiceJson]


class Health(TypedDict):
    status: str
    api: str
    discovery: str
    discovery_heartbeat_age: float | None
    discovery_error: str | None
    state: str
    state_error: str | None
    auth: str | None
    warnings: list[str]


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


def service_body(
    name: str,
    type: str,
    url: str | None = None,
    attributes: Mapping[str, AttrValue] | None = None,
    service_id: str | None = None,
    ttl: float | None = None,
) -> JsonObject:
    body: JsonObject = {"name": name, "type": type}
    if service_id is not None:
        body["id"] = service_id
    if url is not None:
        body["url"] = url
    if attributes is not None:
        body["attributes"] = dict(attributes)
    if ttl is not None:
        body["ttl"] = ttl
    return body


def publish(
    name: str,
    type: str,
    url: str | None = None,
    attributes: Mapping[str, AttrValue] | None = None,
    service_id: str | None = None,
    ttl: float | None = None,
) -> Call[Published]:
    """The id is chosen here (or given), so the call is sent again when sdfrd was not reached:
    a daemon that stored it already answers 200 instead of storing it twice."""
    body = service_body(name, type, url, attributes, service_id or new_service_id(), ttl)
    return Call("POST", "/services", _whole, body, retry_unreachable=True)


def unpublish(service_id: str) -> Call[None]:
    return Call("DELETE", service_path(service_id), _nothing)


def service(service_id: str) -> Call[Published]:
    return Call("GET", service_path(service_id), _whole)


def renew(service_id: str, ttl: float | None = None) -> Call[Renewed]:
    body = None if ttl is None else {"ttl": ttl}
    return Call("POST", service_path(service_id) + "/renew", _whole, body)


def services() -> Call[list[JsonObject]]:
    return Call("GET", "/services", _field("services", "GET", "/services"))


def neighbors(include_unreachable: bool = False) -> Call[list[JsonObject]]:
    path = neighbors_path(include_unreachable)
    return Call("GET", path, _field("neighbors", "GET", path))


def search(type: str | None, attrs: Mapping[str, AttrValue]) -> Call[list[JsonObject]]:
    path = search_path(type, attrs)
    return Call("GET", path, _field("neighbors", "GET", path))


def history() -> Call[list[JsonObject]]:
    return Call("GET", "/history", _field("robots", "GET", "/history"))


def self_info() -> Call[JsonObject]:
    return Call("GET", "/self", _whole)


def health() -> Call[Health]:
    return Call("GET", "/health", _whole, accept=(503,))


def metrics() -> Call[str]:
    return Call("GET", "/metrics", str)


def _page(answer: Any) -> EventsPage:
    if not isinstance(answer, dict) or not isinstance(answer.get("events"), list):
        raise ApiError(0, "unexpected answer from sdfrd for GET /events: no 'events'")
    return {
        "events": [Change.from_json(e) for e in answer["events"]],
        "last_id": int(answer["last_id"]),
    }


def events(since: int | None = 0, kinds: Iterable[str] | None = None) -> Call[EventsPage]:
    """The events kept after `since`, at once (a page: ask again from `last_id`); with
    `since` None none, and `last_id` is the newest (where to start watching from)."""
    return Call("GET", events_path(since, kinds), _page)


def keys() -> Call[JsonObject]:
    return Call("GET", "/keys", _whole)


def install_key(key_b64: str) -> Call[JsonObject]:
    return Call("POST", "/keys", _whole, {"key": key_b64})


def use_key(key_id: str) -> Call[JsonObject]:
    return Call("POST", f"/keys/{quote(key_id, safe='')}/use", _whole)


def remove_key(key_id: str, open_fleet: bool = False) -> Call[None]:
    """`open_fleet`: the last key too (in mode accept), leaving an open fleet."""
    query = "?open_fleet=1" if open_fleet else ""
    return Call("DELETE", f"/keys/{quote(key_id, safe='')}{query}", _nothing)


def set_key_mode(mode: str) -> Call[JsonObject]:
    return Call("PUT", "/keys/mode", _whole, {"mode": mode})


# -- answers, errors, event streams ---------------------------------------------------------------


def split_api(api: str) -> tuple[str, int]:
    hostport = api.removeprefix("http://").rstrip("/")
    host, sep, port = hostport.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"api: expected HOST:PORT (e.g. {DEFAULT_API}), got {api!r}")
    return host.strip("[]"), int(port)


def unreachable(where: str, reason: str, unix: bool) -> ApiError:
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
    return ApiError(0, f"cannot reach sdfrd at {where}: {reason}; {hint}")


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
