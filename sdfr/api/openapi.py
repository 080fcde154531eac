"""The OpenAPI 3.1 document of the local REST API (served at /openapi.json)."""

from __future__ import annotations

from typing import Any

from sdfr import __version__
from sdfr.api.handlers import FLAG_VALUES
from sdfr.model import json_schemas

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


#: (method, path) -> (operationId, tag): what a generated client calls each operation.
OPERATIONS = {
    ("get", "/services"): ("listServices", "services"),
    ("post", "/services"): ("publishService", "services"),
    ("delete", "/services/{id}"): ("unpublishService", "services"),
    ("get", "/neighbors"): ("listNeighbors", "discovery"),
    ("get", "/neighbors/search"): ("searchNeighbors", "discovery"),
    ("get", "/history"): ("listHistory", "discovery"),
    ("get", "/self"): ("getSelf", "robot"),
    ("get", "/health"): ("getHealth", "robot"),
    ("get", "/metrics"): ("getMetrics", "robot"),
    ("get", "/openapi.json"): ("getOpenApi", "robot"),
    ("get", "/keys"): ("listKeys", "keys"),
    ("post", "/keys"): ("installKey", "keys"),
    ("post", "/keys/{id}/use"): ("useKey", "keys"),
    ("delete", "/keys/{id}"): ("removeKey", "keys"),
    ("put", "/keys/mode"): ("setKeyMode", "keys"),
}
TAGS = [
    {"name": "services", "description": "This robot's registrations"},
    {"name": "discovery", "description": "Which robots are reachable, and what they offer"},
    {"name": "robot", "description": "This robot and its daemon"},
    {"name": "keys", "description": "The fleet keyring (unix socket only)"},
]


def openapi_document() -> dict[str, object]:
    """The OpenAPI 3.1 description of `create_app`'s routes."""
    nullable_number = {"type": ["number", "null"]}
    neighbor_properties: dict[str, Any] = {
        "robot_id": {"type": "string"},
        "address": {"type": "string", "description": "IPv4 address on the fleet network"},
        "reachable": {"type": "boolean"},
        "indicator": {
            **nullable_number,
            "description": "Connection indicator: success rate 0-1 of recent unicast pings",
        },
        "rtt_ms": {**nullable_number, "description": "Mean round-trip time of recent pings"},
        "last_seen": {"type": "number", "description": "Unix time the robot was last heard"},
        "services": {"type": "array", "items": _ref("Service")},
    }
    neighbor = {
        "type": "object",
        "required": ["robot_id", "address", "reachable", "indicator", "rtt_ms", "services"],
        "properties": neighbor_properties,
    }
    peer_record = {
        "type": "object",
        "required": ["robot_id", "address", "reachable", "boot_id", "version", "services"],
        "properties": {
            **neighbor_properties,
            "location": {"type": "string", "description": "URL of its description"},
            "boot_id": {"type": "integer"},
            "version": {"type": "integer", "description": "Version of its service set"},
            "first_seen": {"type": "number"},
        },
    }
    schemas: dict[str, Any] = {
        **json_schemas(),  # ServiceInput and Service: from the one typed model
        "Error": {
            "type": "object",
            "required": ["error", "field"],
            "properties": {
                "error": {"type": "string"},
                "field": {"type": ["string", "null"]},
            },
        },
        "Published": {
            "type": "object",
            "required": ["id", "service", "version"],
            "properties": {
                "id": {"type": "string"},
                "service": _ref("Service"),
                "version": {"type": "integer"},
            },
        },
        "Services": {
            "type": "object",
            "required": ["services", "version"],
            "properties": {
                "services": {"type": "array", "items": _ref("Service")},
                "version": {
                    "type": "integer",
                    "description": "Bumped by every publish and unpublish",
                },
            },
        },
        "Neighbor": neighbor,
        "Neighbors": {
            "type": "object",
            "required": ["neighbors"],
            "properties": {"neighbors": {"type": "array", "items": _ref("Neighbor")}},
        },
        "PeerRecord": peer_record,
        "History": {
            "type": "object",
            "required": ["robots"],
            "properties": {"robots": {"type": "array", "items": _ref("PeerRecord")}},
        },
        "Self": {
            "type": "object",
            "required": ["robot_id", "fleet", "address", "version", "services", "discovery"],
            "properties": {
                "robot_id": {"type": ["string", "null"]},
                "fleet": {"type": "integer"},
                "iface": {"type": ["string", "null"]},
                "address": {"type": "string"},
                "boot_id": {"type": ["integer", "null"]},
                "version": {"type": "integer"},
                "location": {"type": ["string", "null"]},
                "software": {"type": "string"},
                "services": {"type": "array", "items": _ref("Service")},
                "discovery": {
                    "type": "object",
                    "required": ["up"],
                    "properties": {
                        "up": {"type": "boolean"},
                        "heartbeat_age": nullable_number,
                        "pid": {"type": ["integer", "null"]},
                        "iface": {"type": ["string", "null"]},
                        "started": nullable_number,
                        "announced_version": {"type": ["integer", "null"]},
                        "peers_reachable": {"type": ["integer", "null"]},
                        "peers_known": {"type": ["integer", "null"]},
                    },
                },
            },
        },
        "Health": {
            "type": "object",
            "required": [
                "status",
                "api",
                "discovery",
                "discovery_heartbeat_age",
                "discovery_error",
                "state",
                "state_error",
                "auth",
                "warnings",
            ],
            "properties": {
                "status": {
                    "enum": ["ok", "warning", "degraded"],
                    "description": "degraded: the discovery layer is down or failing, or the "
                    "state directory cannot be written (503); warning: up, with warnings",
                },
                "api": {"const": "up"},
                "discovery": {
                    "enum": ["up", "failing", "down"],
                    "description": "failing: alive, but its work keeps failing or it cannot "
                    "announce this robot's services (see discovery_error)",
                },
                "discovery_heartbeat_age": nullable_number,
                "discovery_error": {"type": ["string", "null"]},
                "state": {
                    "enum": ["ok", "full", "read-only", "error"],
                    "description": "Whether the state directory can be written (publishes "
                    "need it); not ok answers 503 with the discovery layer up",
                },
                "state_error": {"type": ["string", "null"]},
                "auth": {
                    "enum": ["open", "accept", "sign", "enforce", None],
                    "description": "The keyring's mode; open: no fleet key",
                },
                "warnings": {
                    "type": "array",
                    "items": {"type": "string"},
                    "description": "e.g. another daemon claims this robot's id",
                },
            },
        },
        "Keys": {
            "type": "object",
            "required": ["mode", "primary", "keyed", "ssdp_interop", "keys"],
            "properties": {
                "mode": {"enum": ["open", "accept", "sign", "enforce"]},
                "primary": {"type": ["string", "null"], "description": "The key that signs"},
                "keyed": {"type": "boolean"},
                "ssdp_interop": {"type": "boolean"},
                "keys": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "required": ["id", "primary", "installed", "received"],
                        "properties": {
                            "id": {"type": "string", "description": "8 hex characters"},
                            "primary": {"type": "boolean"},
                            "installed": nullable_number,
                            "received": {
                                "type": "integer",
                                "description": "Datagrams verified with it since the "
                                "discovery layer started",
                            },
                        },
                    },
                },
            },
        },
    }
    key_id_param = [{"name": "id", "in": "path", "required": True, "schema": {"type": "string"}}]
    unix_only = (
        "Only on the unix socket STATE_DIR/api.sock (403 over TCP). Never returns key material."
    )
    paths: dict[str, Any] = {
        "/services": {
            "get": {
                "summary": "This robot's registrations",
                "responses": {"200": _answer("The local services", "Services")},
            },
            "post": {
                "summary": "Publish a service",
                "requestBody": {"required": True, "content": _json_content(_ref("ServiceInput"))},
                "responses": {
                    "201": {
                        **_answer("Published, on disk", "Published"),
                        "headers": {
                            "Location": {"schema": {"type": "string"}, "description": "Its URL"}
                        },
                    },
                    "200": _answer("Published already under this id (a retry)", "Published"),
                    **_ERRORS_400,
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
            "delete": {
                "summary": "Unpublish a service",
                "parameters": [
                    {"name": "id", "in": "path", "required": True, "schema": {"type": "string"}}
                ],
                "responses": {"204": {"description": "Unpublished"}, "404": _ERROR},
            }
        },
        "/neighbors": {
            "get": {
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
                "summary": "Every robot ever seen, reachable or not",
                "responses": {"200": _answer("The history map", "History")},
            }
        },
        "/self": {
            "get": {
                "summary": "This robot: identity, address, services, discovery state",
                "responses": {"200": _answer("This robot", "Self")},
            }
        },
        "/health": {
            "get": {
                "summary": "Liveness of the two layers",
                "responses": {
                    "200": _answer("Both layers up", "Health"),
                    "503": _answer("The discovery layer is down; the API answers", "Health"),
                },
            }
        },
        "/openapi.json": {
            "get": {
                "summary": "This document",
                "responses": {"200": {"description": "OpenAPI 3.1", "content": _json_content({})}},
            }
        },
        "/keys": {
            "get": {
                "summary": "The fleet keyring: key ids, the one that signs, the mode",
                "description": unix_only,
                "responses": {"200": _answer("The keyring", "Keys"), "403": _ERROR},
            },
            "post": {
                "summary": "Install a key (accepted at once, used to sign after `use`)",
                "description": unix_only + " The first key of a robot without any is put to "
                "use in mode accept.",
                "requestBody": {
                    "required": True,
                    "content": _json_content(
                        {
                            "type": "object",
                            "required": ["key"],
                            "additionalProperties": False,
                            "properties": {
                                "key": {"type": "string", "description": "base64, 32 bytes"}
                            },
                        }
                    ),
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
                "summary": "Sign with this key from now on",
                "description": unix_only,
                "parameters": key_id_param,
                "responses": {"200": _answer("The keyring", "Keys"), "403": _ERROR, "404": _ERROR},
            }
        },
        "/keys/{id}": {
            "delete": {
                "summary": "Stop accepting this key (never the one in use)",
                "description": unix_only,
                "parameters": key_id_param,
                "responses": {
                    "204": {"description": "Removed"},
                    "403": _ERROR,
                    "404": _ERROR,
                    "409": _ERROR,
                },
            }
        },
        "/keys/mode": {
            "put": {
                "summary": "accept, sign or enforce (the steps of moving a fleet to a key)",
                "description": unix_only,
                "requestBody": {
                    "required": True,
                    "content": _json_content(
                        {
                            "type": "object",
                            "required": ["mode"],
                            "additionalProperties": False,
                            "properties": {"mode": {"enum": ["accept", "sign", "enforce"]}},
                        }
                    ),
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
            op["operationId"], tag = OPERATIONS[(method, path)]
            op["tags"] = [tag]
            if path.startswith("/keys"):  # a GET only reads the keyring
                errors = keyring_errors if method != "get" else {"500": keyring_errors["500"]}
                op["responses"].update(errors)
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
            "what they offer. Every answer, errors included, is JSON (except /metrics).",
        },
        "tags": TAGS,
        "paths": paths,
        "components": {"schemas": schemas},
    }
