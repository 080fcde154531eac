"""The local REST API as an aiohttp application."""

from __future__ import annotations

from aiohttp import web

from sdfr.api.doors import allowed_hosts, doors
from sdfr.api.handlers import (
    health,
    history,
    keys_install,
    keys_list,
    keys_mode,
    keys_remove,
    keys_use,
    list_services,
    neighbors,
    publish,
    search,
    self_info,
    unpublish,
)
from sdfr.api.metrics import metrics
from sdfr.api.openapi import openapi_document
from sdfr.api.replies import MAX_BODY, Handler, json_bytes, json_response
from sdfr.api.server import errors_as_json
from sdfr.api.state import STATE, ApiState, StoreView, Writer, measure
from sdfr.config import Config
from sdfr.store import (
    Store,
)


def create_app(cfg: Config, store: Store) -> web.Application:
    """The local REST API."""
    app = web.Application(middlewares=[measure, errors_as_json, doors], client_max_size=MAX_BODY)
    writer = Writer(cfg.state_dir)
    app[STATE] = ApiState(
        cfg=cfg, view=StoreView(store, cfg), writer=writer, hosts=allowed_hosts(cfg)
    )

    async def close_writer(app: web.Application) -> None:
        writer.close()

    app.on_cleanup.append(close_writer)
    openapi_body = json_bytes(openapi_document())

    async def openapi(request: web.Request) -> web.Response:
        return json_response(openapi_body)

    routes: list[tuple[str, str, Handler]] = [
        ("GET", "/services", list_services),
        ("POST", "/services", publish),
        ("DELETE", "/services/{id}", unpublish),
        ("GET", "/neighbors", neighbors),
        ("GET", "/neighbors/search", search),
        ("GET", "/history", history),
        ("GET", "/self", self_info),
        ("GET", "/health", health),
        ("GET", "/openapi.json", openapi),
        ("GET", "/metrics", metrics),
        ("GET", "/keys", keys_list),
        ("POST", "/keys", keys_install),
        ("POST", "/keys/{id}/use", keys_use),
        # Not /keys/mode: that resource is the mode (PUT), not a key to remove.
        ("DELETE", "/keys/{id:(?!mode$)[^{}/]+}", keys_remove),
        ("PUT", "/keys/mode", keys_mode),
    ]
    for method, path, handler in routes:
        app.router.add_route(method, path, handler)
    return app
