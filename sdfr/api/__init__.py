"""The API layer's HTTP applications: the local REST API and the read-only description server.

Both answer from the durable store the discovery layer writes (the paper's shared memory),
so they keep answering, from the last known state, while discovery is down. Reads are
cached and revalidated per request with one tiny query: the peers on SQLite's
`data_version` (it changes when another connection, i.e. the discovery layer, commits),
the local registrations on their version (bumped by every publish/unpublish, whichever
connection made it).

The package: `http` (the HTTP/1.1 server: requests, answers, streams, routes), `httpparse`
(reading requests, the limits), `httpserve` (the connection loop, the listeners),
`replies` (JSON answers and errors), `server` (the runner: JSON even for what fails before a
handler), `doors` (who may knock), `state` (status, cached store views, the
writer), `handlers`, `metrics`, `openapi` (the document) and `app` (routes).
"""

from sdfr.api.app import create_app
from sdfr.api.http import App
from sdfr.api.httpserve import TCPSite, UnixSite
from sdfr.api.openapi import openapi_document
from sdfr.api.replies import MAX_BODY
from sdfr.api.server import Runner
from sdfr.api.state import HEARTBEAT_STALE, STATE, ApiState, pid_alive
from sdfr.daemon.channel import notify_discovery

__all__ = [
    "HEARTBEAT_STALE",
    "MAX_BODY",
    "STATE",
    "ApiState",
    "App",
    "Runner",
    "TCPSite",
    "UnixSite",
    "create_app",
    "notify_discovery",
    "openapi_document",
    "pid_alive",
]
