"""Python clients of sdfrd's REST API: `Client` (this package's face, on http.client; see
`sdfr.client.sync`) and `sdfr.aio.AsyncClient` (asyncio, the `aio` extra).  Both are
`core.Api`, every call written once in `calls`, carried over their transport."""

from __future__ import annotations

from sdfr.client.sync import (
    RETRY_DELAYS,
    Change,
    Client,
    JsonObject,
    KeptLease,
    UnixHTTPConnection,
    neighbors_path,
    new_service_id,
    owner_token_path,
    search_path,
    service_path,
    split_api,
    user_owner_token,
)

__all__ = [
    "RETRY_DELAYS",
    "Change",
    "Client",
    "JsonObject",
    "KeptLease",
    "UnixHTTPConnection",
    "neighbors_path",
    "new_service_id",
    "owner_token_path",
    "search_path",
    "service_path",
    "split_api",
    "user_owner_token",
]
