"""The OpenAPI 3.1 document of the local REST API (served at /openapi.json)."""

from __future__ import annotations

from typing import Any

from sdfr import __version__
from sdfr.api.events import STREAMS_MAX, STREAMS_PER_CLIENT
from sdfr.api.handlers import FLAG_VALUES, OWNER_TOKEN
from sdfr.api.models import components
from sdfr.endpoints import OWNER_HEADER
from sdfr.records.events import FAMILIES, KINDS

# -- the OpenAPI document ----------------------------------------------------------------------


def _ref(name: str) -> dict[str, str]:
    return {"$ref": f"#/components/schemas/{name}"}


def _json_content(schema: dict[str, Any]) -> dict[str, object]:
    return {"application/json": {"schema": schema}}


def _answer(text: str, schema: str) -> dict[str, object]:
    return {"description": text, "content": _json_content(_ref(schema))}


_ERROR = _answer("An error; `field` names the offending field or parameter.", "Error")
_ERRORS_400 = {"400": _ERROR, "422": _ERROR}
_DOORS = {
    **_ERROR,
    "description": "A web page's cross-site request (Origin, Sec-Fetch-Site) or a Host that "
    "is not one of this API's names (see api_allowed_origins, api_allowed_hosts)",
}
_REMOTE = {
    **_ERROR,
    "description": "A request from another machine without the token of sdfrd's "
    "api_token_file (Authorization: Bearer TOKEN); only with api_allow_remote",
}
_NOT_YOURS = {
    **_ERROR,
    "description": "The service belongs to another program (field X-SDFR-Owner): send its "
    "owner token, or call over the unix socket as the user that published it (or root); "
    "or, as for every call, a web page's cross-site request or a Host not of this API",
}
_OWNER = {
    "name": OWNER_HEADER,
    "in": "header",
    "required": False,
    "schema": {"type": "string", "pattern": f"^{OWNER_TOKEN.pattern}$"},
    "description": "The owner token of the calling program: a publish makes the service "
    "its own (without one, a token is made and answered as owner_token); unpublish, renew, "
    "hold and a publish again need the service's own token (on the unix socket, the "
    "publishing user, or root, need none)",
}


TAGS = [
    {"name": "services", "description": "This robot's registrations"},
    {"name": "discovery", "description": "Which robots are reachable, and what they offer"},
    {"name": "robot", "description": "This robot and its daemon"},
    {"name": "keys", "description": "The fleet keyring (unix socket only)"},
]


def openapi_document() -> dict[str, object]:
    """The OpenAPI 3.1 description of `create_app`'s routes."""
    schemas = components()
    key_id_param = [{"name": "id", "in": "path", "required": True, "schema": {"type": "string"}}]
    service_id_param = [
        {"name": "id", "in": "path", "required": True, "schema": {"type": "string"}}
    ]
    owned_param = [*service_id_param, _OWNER]
    unix_only = (
        "Only on the unix socket STATE_DIR/api.sock (403 over TCP). Never returns key material."
    )
    paths: dict[str, Any] = {
        "/services": {
            "get": {
                "operationId": "listServices",
                "tags": ["services"],
                "summary": "This robot's registrations",
                "responses": {"200": _answer("The local services", "Services")},
            },
            "post": {
                "operationId": "publishService",
                "tags": ["services"],
                "summary": "Publish a service",
                "description": "It belongs to the calling program: its owner token "
                "(X-SDFR-Owner, or one made for it, answered as owner_token) and, on the unix "
                "socket, its user.",
                "parameters": [_OWNER],
                "requestBody": {"required": True, "content": _json_content(_ref("Registration"))},
                "responses": {
                    "201": {
                        **_answer("Published, on disk", "Published"),
                        "headers": {
                            "Location": {"schema": {"type": "string"}, "description": "Its URL"}
                        },
                    },
                    "200": _answer(
                        "Published already under this id (a retry), on disk", "Published"
                    ),
                    **_ERRORS_400,
                    "403": _NOT_YOURS,
                    "409": {**_ERROR, "description": "The id is another service's"},
                    "413": {
                        **_ERROR,
                        "description": "The body is over 64 KiB, or the service would not fit in "
                        "one discovery datagram as JSON (field `service`)",
                    },
                    "503": {**_ERROR, "description": "The state directory is read-only"},
                    "507": {
                        **_ERROR,
                        "description": "The state directory is full, or the robot's services "
                        "would need more than the 255 Update parts one announcement can carry",
                    },
                },
            },
        },
        "/services/{id}": {
            "get": {
                "operationId": "getService",
                "tags": ["services"],
                "summary": "One of this robot's registrations, with its lease",
                "parameters": service_id_param,
                "responses": {"200": _answer("The registration", "Published"), "404": _ERROR},
            },
            "delete": {
                "operationId": "unpublishService",
                "tags": ["services"],
                "summary": "Unpublish a service (its owner only)",
                "parameters": owned_param,
                "responses": {
                    "204": {"description": "Unpublished, on disk"},
                    "400": _ERROR,
                    "403": _NOT_YOURS,
                    "404": _ERROR,
                },
            },
        },
        "/services/{id}/renew": {
            "post": {
                "operationId": "renewService",
                "tags": ["services"],
                "summary": "Renew a registration's lease: it runs its ttl from now again",
                "description": "Its owner only. The body may give another ttl. Cheap (not "
                "fsynced).",
                "parameters": owned_param,
                "requestBody": {"required": False, "content": _json_content(_ref("Renewal"))},
                "responses": {
                    "200": _answer("Renewed: until when", "Renewed"),
                    "404": {**_ERROR, "description": "No such service (or its lease ran out)"},
                    "409": {**_ERROR, "description": "The service has no lease"},
                    "403": _NOT_YOURS,
                    **_ERRORS_400,
                },
            }
        },
        "/services/{id}/hold": {
            "post": {
                "operationId": "holdService",
                "tags": ["services"],
                "summary": "Renew a lease for as long as this request stays open",
                "description": "With `Accept: text/event-stream`: an event `renewed` (data: "
                "the Renewed object) each third of the ttl, for as long as the connection "
                "stays open; `gone` if the service is unpublished meanwhile. When the "
                "connection closes (its program ended), the lease runs out after its ttl. "
                "Without, it renews once and answers like /renew. Its owner only.",
                "parameters": owned_param,
                "responses": {
                    "200": {
                        "description": "A stream of Server-Sent Events, or one renewal",
                        "content": {
                            "text/event-stream": {"schema": {"type": "string"}},
                            "application/json": {"schema": _ref("Renewed")},
                        },
                    },
                    "400": _ERROR,
                    "403": _NOT_YOURS,
                    "404": _ERROR,
                    "409": {**_ERROR, "description": "The service has no lease"},
                },
            }
        },
        "/events": {
            "get": {
                "operationId": "listEvents",
                "tags": ["discovery"],
                "summary": "Changes: robots appearing, leaving, unreachable, their services, "
                "indicator thresholds; this robot's registrations",
                "description": "With `Accept: text/event-stream`, a stream of Server-Sent "
                "Events (`id`, `event` the kind, `data` a ChangeEvent) that goes on until the "
                "client closes it; without, the events after `since` at once as JSON. Kinds: "
                + "; ".join(f"`{k}`: {v}" for k, v in KINDS.items())
                + ". Ids grow; a stream resumes after the `Last-Event-ID` header (or "
                "`since`); without either it starts with the next change. When the events "
                "after that id are no longer kept (the log holds the last 4,096), the first "
                "event is `resync`: read the state again.",
                "parameters": [
                    {
                        "name": "since",
                        "in": "query",
                        "required": False,
                        "schema": {"type": "integer", "minimum": 0, "maximum": 2**63 - 1},
                        "description": "Events after this id (0: every one kept)",
                    },
                    {
                        "name": "event",
                        "in": "query",
                        "required": False,
                        "style": "form",
                        "explode": True,
                        "schema": {
                            "type": "array",
                            "items": {"enum": sorted([*KINDS, *FAMILIES])},
                        },
                        "description": "Only these kinds (`robot` for every robot.* kind); "
                        "repeatable",
                    },
                    {
                        "name": "Last-Event-ID",
                        "in": "header",
                        "required": False,
                        "schema": {"type": "string", "pattern": "^[0-9]{1,18}$"},
                        "description": "Resume after this id (what an EventSource sends)",
                    },
                ],
                "responses": {
                    "200": {
                        "description": "The events",
                        "content": {
                            "application/json": {"schema": _ref("Events")},
                            "text/event-stream": {"schema": {"type": "string"}},
                        },
                    },
                    "422": _ERROR,
                    "429": {
                        **_ERROR,
                        "description": f"This client (its user) holds {STREAMS_PER_CLIENT} "
                        "streams already, the most one may",
                    },
                    "503": {
                        **_ERROR,
                        "description": f"{STREAMS_MAX} event streams are open already",
                    },
                },
            }
        },
        "/neighbors": {
            "get": {
                "operationId": "listNeighbors",
                "tags": ["discovery"],
                "summary": "Robots reachable now, with their services",
                "parameters": [
                    {
                        "name": "all",
                        "in": "query",
                        "required": False,
                        "schema": {"enum": sorted(FLAG_VALUES)},
                        "allowEmptyValue": True,
                        "description": "Also the unreachable robots of the history map "
                        "(`?all` alone is `?all=true`)",
                    }
                ],
                "responses": {"200": _answer("The neighbours", "Neighbors"), "422": _ERROR},
            }
        },
        "/neighbors/search": {
            "get": {
                "operationId": "searchNeighbors",
                "tags": ["discovery"],
                "summary": "Reachable robots offering matching services (only those services)",
                "description": "At least one criterion. Any number of `attr.KEY=VALUE` "
                "parameters, one per attribute; a service matches when its type and every "
                "given attribute are equal.",
                "parameters": [
                    {
                        "name": "criteria",
                        "in": "query",
                        "required": True,
                        "style": "form",
                        "explode": True,
                        "schema": {
                            "type": "object",
                            "minProperties": 1,
                            "properties": {"type": {"type": "string", "minLength": 1}},
                            "patternProperties": {"^attr\\..+": {"type": "string"}},
                            "additionalProperties": False,
                        },
                        "description": "The criteria, each a query parameter of its own: "
                        "`type=T` and any number of `attr.KEY=VALUE` (a generated client "
                        'passes an object such as {"type": "camera", "attr.fps": '
                        '"30"})',
                    },
                ],
                "responses": {"200": _answer("The matches", "Neighbors"), "422": _ERROR},
            }
        },
        "/history": {
            "get": {
                "operationId": "listHistory",
                "tags": ["discovery"],
                "summary": "Every robot ever seen, reachable or not",
                "responses": {"200": _answer("The history map", "History")},
            }
        },
        "/self": {
            "get": {
                "operationId": "getSelf",
                "tags": ["robot"],
                "summary": "This robot: identity, address, services, discovery state",
                "responses": {"200": _answer("This robot", "Self")},
            }
        },
        "/health": {
            "get": {
                "operationId": "getHealth",
                "tags": ["robot"],
                "summary": "Liveness of the two layers",
                "responses": {
                    "200": _answer("Both layers up", "Health"),
                    "503": _answer("The discovery layer is down; the API answers", "Health"),
                },
            }
        },
        "/openapi.json": {
            "get": {
                "operationId": "getOpenApi",
                "tags": ["robot"],
                "summary": "This document",
                "responses": {"200": {"description": "OpenAPI 3.1", "content": _json_content({})}},
            }
        },
        "/keys": {
            "get": {
                "operationId": "listKeys",
                "tags": ["keys"],
                "summary": "The fleet keyring: key ids, the one that signs, the mode",
                "description": unix_only,
                "responses": {"200": _answer("The keyring", "Keys"), "403": _ERROR},
            },
            "post": {
                "operationId": "installKey",
                "tags": ["keys"],
                "summary": "Install a key (accepted at once, used to sign after `use`)",
                "description": unix_only + " The first key of a robot without any is put to "
                "use in mode accept.",
                "requestBody": {
                    "required": True,
                    "content": _json_content(_ref("KeyInstall")),
                },
                "responses": {
                    "201": _answer("Installed", "Keys"),
                    "200": _answer("Installed already", "Keys"),
                    "403": _ERROR,
                    **_ERRORS_400,
                },
            },
        },
        "/keys/{id}/use": {
            "post": {
                "operationId": "useKey",
                "tags": ["keys"],
                "summary": "Sign with this key from now on",
                "description": unix_only,
                "parameters": key_id_param,
                "responses": {"200": _answer("The keyring", "Keys"), "403": _ERROR, "404": _ERROR},
            }
        },
        "/keys/{id}": {
            "delete": {
                "operationId": "removeKey",
                "tags": ["keys"],
                "summary": "Stop accepting this key (the one in use only with open_fleet)",
                "description": unix_only + " With open_fleet, the last key too, in mode "
                "accept: this robot's fleet is open again.",
                "parameters": [
                    *key_id_param,
                    {
                        "name": "open_fleet",
                        "in": "query",
                        "required": False,
                        "description": "remove the last key (yes/no, default no)",
                        "schema": {"enum": sorted(FLAG_VALUES)},
                    },
                ],
                "responses": {
                    "204": {"description": "Removed"},
                    "403": _ERROR,
                    "404": _ERROR,
                    "409": _ERROR,
                    "422": _ERROR,
                },
            }
        },
        "/keys/mode": {
            "put": {
                "operationId": "setKeyMode",
                "tags": ["keys"],
                "summary": "accept, sign or enforce (the steps of moving a fleet to a key)",
                "description": unix_only,
                "requestBody": {
                    "required": True,
                    "content": _json_content(_ref("KeyMode")),
                },
                "responses": {
                    "200": _answer("The keyring", "Keys"),
                    "403": _ERROR,
                    "409": _ERROR,
                    **_ERRORS_400,
                },
            }
        },
        "/metrics": {
            "get": {
                "operationId": "getMetrics",
                "tags": ["robot"],
                "summary": "Prometheus metrics",
                "responses": {
                    "200": {
                        "description": "Text exposition format 0.0.4",
                        "content": {"text/plain": {"schema": {"type": "string"}}},
                    }
                },
            }
        },
    }
    keyring_errors = {
        "500": {
            **_ERROR,
            "description": "STATE_DIR/keyring.json cannot be read or written (damaged, "
            "unreadable); `field` is keyring and the error names the file",
        },
        "503": {**_ERROR, "description": "The state directory is read-only"},
        "507": {**_ERROR, "description": "The state directory is full"},
    }
    for path, ops in paths.items():
        for method, op in ops.items():
            if path.startswith("/keys"):  # a GET only reads the keyring
                errors = keyring_errors if method != "get" else {"500": keyring_errors["500"]}
                op["responses"].update(errors)
            op["responses"].setdefault("401", _REMOTE)
            op["responses"].setdefault("403", _DOORS)
            op["responses"].setdefault("405", _ERROR)
            op["responses"].setdefault("500", _ERROR)
            if "requestBody" in op:
                op["responses"].setdefault("408", _ERROR)
                op["responses"].setdefault("415", {**_ERROR, "description": "Not a JSON body"})
    return {
        "openapi": "3.1.0",
        "info": {
            "title": "SDfR local API",
            "version": __version__,
            "description": "Publish this robot's services; ask which robots are reachable and "
            "what they offer. Every answer, errors included, is JSON (except /metrics). A "
            "service belongs to the program that published it (X-SDFR-Owner). Only programs "
            "on the robot are answered, unless sdfrd's api_allow_remote lets other machines "
            "in with the token of its api_token_file (Authorization: Bearer TOKEN).",
        },
        "tags": TAGS,
        "paths": paths,
        "components": {"schemas": schemas},
    }
