"""The local REST API as an application of `sdfr.api.http`."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

from sdfr.api.doors import allowed_hosts, doors, load_api_token
from sdfr.api.events import EventHub, events
from sdfr.api.handlers import (
    get_service,
    health,
    history,
    hold,
    keys_install,
    keys_list,
    keys_mode,
    keys_remove,
    keys_use,
    list_services,
    neighbors,
    publish,
    renew,
    search,
    self_info,
    unpublish,
)
from sdfr.api.http import App, Request, Response
from sdfr.api.leases import Leases
from sdfr.api.metrics import metrics
from sdfr.api.openapi import openapi_document
from sdfr.api.replies import MAX_BODY, Handler, json_bytes, json_response
from sdfr.api.server import errors_as_json
from sdfr.api.state import STATE, ApiState, StoreView, Writer, measure
from sdfr.config.load import Config
from sdfr.daemon.channel import notify_discovery
from sdfr.store import Store


def create_app(cfg: Config, store: Store, *, writer_store: Callable[[Path], Store] = Store) -> App:
    """The local REST API; `store` is its connection for reads, `writer_store` opens the
    one its writer commits registrations on. ConfigError when api_token_file cannot serve."""
    remote_token = None if cfg.api_token_file is None else load_api_token(cfg.api_token_file)
    app = App(middlewares=[measure, errors_as_json, doors], max_body=MAX_BODY)
    hub = EventHub(store)
    writer = Writer(cfg.state_dir, committed=hub.wake, open_store=writer_store)
    view = StoreView(store, cfg)

    def withdrawn(ids: list[str]) -> None:
        view.leases_changed()
        notify_discovery(cfg.state_dir)

    leases = Leases(writer, withdrawn)
    app[STATE] = ApiState(
        cfg=cfg,
        view=view,
        writer=writer,
        hosts=allowed_hosts(cfg),
        hub=hub,
        leases=leases,
        remote_token=remote_token,
    )
    poller: list[asyncio.Task[None]] = []

    async def start(app: App) -> None:
        # Leases that ran out while this layer was down end now; the others are timed.
        leases.load(store.leases())
        poller.append(asyncio.get_running_loop().create_task(hub.poll()))

    async def stop_streams(app: App) -> None:
        hub.close()  # event streams and holds end, so a stop does not wait for them

    async def close(app: App) -> None:
        leases.close()
        for task in poller:
            task.cancel()
        writer.close()

    app.on_startup.append(start)
    app.on_shutdown.append(stop_streams)
    app.on_cleanup.append(close)
    openapi_body: list[bytes] = []

    async def openapi(request: Request) -> Response:
        # Made when first asked for: generating the schemas leaves ~0.5 MiB of type caches
        # behind, which a daemon nobody asks for its document need not carry.
        if not openapi_body:
            openapi_body.append(json_bytes(openapi_document()))
        return json_response(openapi_body[0])

    routes: list[tuple[str, str, Handler]] = [
        ("GET", "/services", list_services),
        ("POST", "/services", publish),
        ("DELETE", "/services/{id}", unpublish),
        ("GET", "/services/{id}", get_service),
        ("POST", "/services/{id}/renew", renew),
        ("POST", "/services/{id}/hold", hold),
        ("GET", "/events", events),
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
        app.add_route(method, path, handler)
    return app
