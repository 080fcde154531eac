"""A service's JSON is made once and kept (`Service.json_text`, `Service.canonical`): the kept
bytes are exactly what encoding the set whole gave before, so a digest, a delta's dictionary
and a stored row are unchanged on the wire and on disk, and a replaced service is encoded
anew."""

from __future__ import annotations

import dataclasses
import hashlib
import json

from hypothesis import given

from sdfr.records.model import Service, canonical_json, json_array, service_digest
from tests.support.wire_data import service_lists, services


@given(service_lists)
def test_a_set_s_digest_is_the_hash_of_its_sorted_json_as_before(svcs: list[Service]) -> None:
    whole = sorted((s.to_json() for s in svcs), key=lambda d: str(d["id"]))
    before = json.dumps(whole, sort_keys=True, separators=(",", ":")).encode()
    assert canonical_json(svcs) == before
    assert canonical_json(svcs) == before  # (the kept bytes)
    assert service_digest(svcs) == hashlib.sha256(before).hexdigest()[:16]


@given(service_lists)
def test_a_set_s_text_is_its_compact_utf8_json_as_before(svcs: list[Service]) -> None:
    before = json.dumps(
        [s.to_json() for s in svcs], separators=(",", ":"), ensure_ascii=False, allow_nan=False
    ).encode()
    assert json_array(svcs) == before
    assert json_array(svcs) == before


@given(services)
def test_a_replaced_service_is_encoded_anew_and_equality_ignores_the_kept_bytes(
    s: Service,
) -> None:
    s.json_text(), s.canonical()
    renamed = dataclasses.replace(s, name=s.name + "x")
    assert json.loads(renamed.json_text())["name"] == s.name + "x"
    assert json.loads(renamed.canonical())["name"] == s.name + "x"
    fresh = Service(s.id, s.name, s.type, s.url, dict(s.attributes))
    assert fresh == s and repr(fresh) == repr(s)
