"""A synchronous Python client of sdfrd's REST API (standard library only).

    with Client() as sdfr:                      # 127.0.0.1:8700
        sid = sdfr.publish("front camera", "camera/rgb", attributes={"fps": 30})
        for robot in sdfr.search("camera/rgb", fps=30):
            ...

One keep-alive connection per client (TCP, or the daemon's unix socket
STATE_DIR/api.sock); not safe to share between threads.
"""

from __future__ import annotations

import base64
import http.client
import json
import secrets
import socket
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any
from urllib.parse import quote, urlencode

from sdfr.config import DEFAULT_API
from sdfr.errors import ApiError
from sdfr.model import AttrValue, attr_text

JsonObject = dict[str, Any]
#: Pauses before sending a publish again when sdfrd could not be reached (it may restart).
RETRY_DELAYS = (0.2, 1.0)

# What a server closing an idle keep-alive connection looks like; worth one fresh attempt.
_DROPPED = (
    http.client.RemoteDisconnected,
    ConnectionResetError,
    ConnectionAbortedError,
    BrokenPipeError,
)


class UnixHTTPConnection(http.client.HTTPConnection):
    """HTTP over a unix stream socket."""

    def __init__(self, path: str, timeout: float | None = None) -> None:
        super().__init__("localhost", timeout=timeout)
        self.path = path

    def connect(self) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.settimeout(self.timeout)
            sock.connect(self.path)
        except OSError:
            sock.close()
            raise
        self.sock = sock


def neighbors_path(include_unreachable: bool = False) -> str:
    return "/neighbors?all=1" if include_unreachable else "/neighbors"


def search_path(type: str | None = None, attrs: Mapping[str, AttrValue] | None = None) -> str:
    """The search URL; attribute values compare as text (`true`, `30`, `0.5`)."""
    query: list[tuple[str, str]] = []
    if type is not None:
        query.append(("type", type))
    query += [(f"attr.{key}", attr_text(value)) for key, value in (attrs or {}).items()]
    return "/neighbors/search?" + urlencode(query)


def service_path(service_id: str) -> str:
    return "/services/" + quote(service_id, safe="")


def new_service_id() -> str:
    """A fresh service id (12 hex characters), chosen by the client so that a retry of the
    same publish cannot store it twice."""
    return secrets.token_hex(6)


def service_body(
    name: str,
    type: str,
    url: str | None = None,
    attributes: Mapping[str, AttrValue] | None = None,
    service_id: str | None = None,
) -> JsonObject:
    body: JsonObject = {"name": name, "type": type}
    if service_id is not None:
        body["id"] = service_id
    if url is not None:
        body["url"] = url
    if attributes is not None:
        body["attributes"] = dict(attributes)
    return body


def split_api(api: str) -> tuple[str, int]:
    hostport = api.removeprefix("http://").rstrip("/")
    host, sep, port = hostport.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"api: expected HOST:PORT (e.g. {DEFAULT_API}), got {api!r}")
    return host.strip("[]"), int(port)


def _reason(exc: BaseException) -> str:
    if isinstance(exc, TimeoutError):
        return "timed out"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


class Client:
    """sdfrd's REST API; every method raises ApiError (status 0: the daemon was not reached)."""

    def __init__(
        self,
        api: str = DEFAULT_API,
        *,
        unix_socket: str | Path | None = None,
        timeout: float = 5.0,
        retry_delays: Sequence[float] = RETRY_DELAYS,
    ) -> None:
        self.timeout = timeout
        #: Pauses before sending a publish again when sdfrd could not be reached.
        self.retry_delays = tuple(retry_delays)
        self._conn: http.client.HTTPConnection | None = None
        if unix_socket is not None:
            self._unix: str | None = str(unix_socket)
            self.where = self._unix
            self._host, self._port = "localhost", 0
        else:
            self._unix = None
            self._host, self._port = split_api(api)
            self.where = f"{self._host}:{self._port}"

    # -- plumbing ----------------------------------------------------------------------------

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> Client:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _connection(self) -> http.client.HTTPConnection:
        if self._unix is not None:
            return UnixHTTPConnection(self._unix, timeout=self.timeout)
        return http.client.HTTPConnection(self._host, self._port, timeout=self.timeout)

    def _exchange(self, method: str, path: str, body: bytes | None) -> tuple[int, str, bytes]:
        headers = {"Accept": "application/json"}
        if body is not None:
            headers["Content-Type"] = "application/json"
        while True:
            fresh = self._conn is None
            conn = self._conn = self._conn or self._connection()
            try:
                conn.request(method, path, body=body, headers=headers)
                resp = conn.getresponse()
                data = resp.read()
            except _DROPPED as exc:
                self.close()
                if not fresh:
                    continue  # the server closed the idle connection: once more on a new one
                raise ApiError(0, f"cannot reach sdfrd at {self.where}: {_reason(exc)}") from None
            except (OSError, http.client.HTTPException) as exc:
                self.close()
                raise ApiError(0, f"cannot reach sdfrd at {self.where}: {_reason(exc)}") from None
            if resp.will_close:
                self.close()
            return resp.status, resp.getheader("Content-Type", ""), data

    def request(
        self,
        method: str,
        path: str,
        body: Any = None,
        *,
        accept: tuple[int, ...] = (),
    ) -> Any:
        """One call: the decoded JSON answer (None when empty); errors raise ApiError.

        `accept` lists error statuses whose body is returned instead (e.g. 503 of /health).
        """
        payload = None if body is None else json.dumps(body).encode()
        status, ctype, data = self._exchange(method, path, payload)
        decoded: Any = None
        if data and ctype.startswith("application/json"):
            try:
                decoded = json.loads(data)
            except ValueError:
                raise ApiError(status, f"sdfrd sent invalid JSON for {method} {path}") from None
        elif data:
            decoded = data.decode("utf-8", errors="replace")
        if status >= 400 and status not in accept:
            if isinstance(decoded, dict) and isinstance(decoded.get("error"), str):
                field = decoded.get("field")
                raise ApiError(status, decoded["error"], field if isinstance(field, str) else None)
            text = decoded.strip()[:200] if isinstance(decoded, str) else ""
            raise ApiError(status, f"HTTP {status} {text}".strip())
        return decoded

    def _get(self, path: str, key: str) -> Any:
        answer = self.request("GET", path)
        if not isinstance(answer, dict) or key not in answer:
            raise ApiError(0, f"unexpected answer from sdfrd for GET {path}: no {key!r}")
        return answer[key]

    # -- the API -----------------------------------------------------------------------------

    def publish(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, AttrValue] | None = None,
        *,
        service_id: str | None = None,
    ) -> str:
        """Publish a service of this robot; returns its id (see `publish_service`)."""
        answer = self.publish_service(name, type, url, attributes, service_id=service_id)
        return str(answer["id"])

    def publish_service(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, AttrValue] | None = None,
        *,
        service_id: str | None = None,
    ) -> JsonObject:
        """Publish a service of this robot; the daemon's answer (id, service, version).

        The id is chosen here (`service_id`, or a fresh one) and sent with the service, so the
        publish is idempotent: when the daemon cannot be reached or the answer is lost, it is
        sent again, and a daemon that stored it already answers 200 instead of storing it
        twice.
        """
        body = service_body(name, type, url, attributes, service_id or new_service_id())
        for delay in (*self.retry_delays, None):
            try:
                answer: JsonObject = self.request("POST", "/services", body)
                return answer
            except ApiError as exc:
                if exc.status != 0 or delay is None:
                    raise
                time.sleep(delay)
        raise AssertionError("unreachable")

    def unpublish(self, service_id: str) -> None:
        self.request("DELETE", service_path(service_id))

    def services(self) -> list[JsonObject]:
        """This robot's registrations."""
        services: list[JsonObject] = self._get("/services", "services")
        return services

    def neighbors(self, include_unreachable: bool = False) -> list[JsonObject]:
        """The robots reachable now (with `include_unreachable`, all of the history map)."""
        found: list[JsonObject] = self._get(neighbors_path(include_unreachable), "neighbors")
        return found

    def search(
        self,
        type: str | None = None,
        attrs: Mapping[str, AttrValue] | None = None,
        **more_attrs: AttrValue,
    ) -> list[JsonObject]:
        """Reachable robots with a service of `type` whose attributes equal the given ones.

        Each robot lists only its matching services. Attributes as keywords
        (`search("camera", fps=30)`) or, for any key, as `attrs={"frame-rate": 30}`.
        """
        found: list[JsonObject] = self._get(
            search_path(type, {**(attrs or {}), **more_attrs}), "neighbors"
        )
        return found

    def history(self) -> list[JsonObject]:
        """Every robot ever seen, reachable or not."""
        robots: list[JsonObject] = self._get("/history", "robots")
        return robots

    def self_info(self) -> JsonObject:
        info: JsonObject = self.request("GET", "/self")
        return info

    def health(self) -> JsonObject:
        """`status` is "ok", or "degraded" (HTTP 503) while the discovery layer is down."""
        info: JsonObject = self.request("GET", "/health", accept=(503,))
        return info

    def metrics(self) -> str:
        return str(self.request("GET", "/metrics"))

    # -- the fleet keyring (over the unix socket only) ---------------------------------------

    def keys(self) -> JsonObject:
        """The keyring: mode, the key that signs, and per key its id (never the key)."""
        ring: JsonObject = self.request("GET", "/keys")
        return ring

    def install_key(self, key: bytes) -> JsonObject:
        """Accept `key` from now on (and, for a robot that had no key, sign with it in mode
        accept); the answer has its `id`."""
        ring: JsonObject = self.request("POST", "/keys", {"key": base64.b64encode(key).decode()})
        return ring

    def use_key(self, key_id: str) -> JsonObject:
        ring: JsonObject = self.request("POST", f"/keys/{quote(key_id, safe='')}/use")
        return ring

    def remove_key(self, key_id: str) -> None:
        self.request("DELETE", f"/keys/{quote(key_id, safe='')}")

    def set_key_mode(self, mode: str) -> JsonObject:
        ring: JsonObject = self.request("PUT", "/keys/mode", {"mode": mode})
        return ring
