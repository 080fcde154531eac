"""The OpenAPI view of the API's records (`sdfr.records.schema`): which records the document's
schemas are generated from, under which component names. schemathesis checks in `make test`
that every answer the handlers build keeps to them."""

from __future__ import annotations

import json
from typing import Any

import msgspec

from sdfr.records.model import ServiceInput, ServiceOutput
from sdfr.records.schema import (
    ChangeEvent,
    Error,
    Events,
    Health,
    History,
    KeyInstall,
    KeyMode,
    Keys,
    LocalService,
    Neighbors,
    Published,
    Registration,
    Renewal,
    Renewed,
    Self,
    Services,
)

MODELS = (
    ServiceInput,
    ServiceOutput,
    Registration,
    Error,
    Published,
    Services,
    LocalService,
    Renewal,
    Renewed,
    ChangeEvent,
    ChangeEvent,
    Events,
    Neighbors,
    History,
    Self,
    Health,
    Keys,
    KeyInstall,
    KeyMode,
)
#: Component names other than the class's own.
RENAMED = {"ServiceOutput": "Service", "PeerJson": "PeerRecord"}


def components() -> dict[str, Any]:
    """Every model's JSON Schema, by component name, with references between them."""
    _, schemas = msgspec.json.schema_components(MODELS, ref_template="#/components/schemas/{name}")
    text = json.dumps(schemas)
    for old, new in RENAMED.items():
        text = text.replace(f'"#/components/schemas/{old}"', f'"#/components/schemas/{new}"')
    out: dict[str, Any] = {RENAMED.get(k, k): v for k, v in json.loads(text).items()}
    for schema in out.values():
        schema.pop("title", None)
    return out
