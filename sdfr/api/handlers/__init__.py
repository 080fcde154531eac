"""The REST handlers, one module a part of the API: `services` (local registrations),
`fleet` (what discovery found), `health` (this robot), `keys` (the fleet keyring) and
`request` (what a request carries: its owner token, its query parameters)."""

from sdfr.api.handlers.fleet import history, neighbors, search
from sdfr.api.handlers.health import health, self_info
from sdfr.api.handlers.keys import keys_install, keys_list, keys_mode, keys_remove, keys_use
from sdfr.api.handlers.request import FLAG_VALUES, OWNER_TOKEN
from sdfr.api.handlers.services import get_service, hold, list_services, publish, renew, unpublish

__all__ = [
    "FLAG_VALUES",
    "OWNER_TOKEN",
    "get_service",
    "health",
    "history",
    "hold",
    "keys_install",
    "keys_list",
    "keys_mode",
    "keys_remove",
    "keys_use",
    "list_services",
    "neighbors",
    "publish",
    "renew",
    "search",
    "self_info",
    "unpublish",
]
