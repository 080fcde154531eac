"""The python-zeroconf node of the side-by-side bench: a service the browser reports is resolved
until it is (a resolution that timed out is tried again) or until the browser says it is gone."""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import types
from typing import Any, ClassVar

import pytest
from zeroconf import ServiceStateChange

from bench import zc_node
from bench.zc_node import TYPE, Node, instance

NAME = instance("r2", "p7x0000abcd")
WHO = ("r2", "p7x0000abcd")


class FakeInfo:
    """An AsyncServiceInfo whose resolutions succeed or time out as `answers` says."""

    answers: ClassVar[list[bool]] = []
    calls = 0

    def __init__(self, type_: str, name: str) -> None:
        assert (type_, name) == (TYPE, NAME)
        self.properties: dict[bytes, bytes] = {}

    async def async_request(self, zc: Any, timeout: float) -> bool:
        FakeInfo.calls += 1
        ok = FakeInfo.answers.pop(0) if FakeInfo.answers else False
        await asyncio.sleep(0.001)
        if ok:
            self.properties = {b"name": b"publisher-7"}
        return ok


@pytest.fixture
def node(monkeypatch: pytest.MonkeyPatch) -> tuple[Node, io.StringIO]:
    monkeypatch.setattr(zc_node, "AsyncServiceInfo", FakeInfo)
    monkeypatch.setattr(zc_node, "RETRY_FIRST_S", 0.02)
    FakeInfo.answers, FakeInfo.calls = [], 0
    events = io.StringIO()
    n = Node(argparse.Namespace(robot="r1", seed=0), events)
    n.aiozc = types.SimpleNamespace(zeroconf=None)  # type: ignore[assignment]
    return n, events


def change(n: Node, state: ServiceStateChange) -> None:
    n.on_change(None, TYPE, NAME, state)  # type: ignore[arg-type]


def ops(events: io.StringIO) -> list[str]:
    return [json.loads(line)["op"] for line in events.getvalue().splitlines()]


async def settle(n: Node, seconds: float) -> None:
    await asyncio.sleep(seconds)
    assert not n.tasks and not n.resolving


def test_a_resolution_that_timed_out_is_tried_again_until_it_works(
    node: tuple[Node, io.StringIO],
) -> None:
    n, events = node

    async def go() -> None:
        FakeInfo.answers = [False, False, True]
        change(n, ServiceStateChange.Added)
        change(n, ServiceStateChange.Added)  # said twice: still one resolver
        await settle(n, 0.5)

    asyncio.run(go())
    assert FakeInfo.calls == 3 and ops(events) == ["seen"] and WHO in n.listed


def test_the_retries_stop_once_the_browser_says_the_service_is_gone(
    node: tuple[Node, io.StringIO],
) -> None:
    n, events = node

    async def go() -> None:
        change(n, ServiceStateChange.Added)
        await asyncio.sleep(0.1)
        assert n.resolving
        change(n, ServiceStateChange.Removed)
        await settle(n, 0.2)
        calls = FakeInfo.calls
        await asyncio.sleep(0.2)
        assert FakeInfo.calls == calls

    asyncio.run(go())
    assert ops(events) == [] and not n.listed


def test_an_update_of_the_service_wakes_a_waiting_resolver_at_once(
    node: tuple[Node, io.StringIO], monkeypatch: pytest.MonkeyPatch
) -> None:
    n, events = node
    monkeypatch.setattr(zc_node, "RETRY_FIRST_S", 60.0)

    async def go() -> None:
        FakeInfo.answers = [False, True]
        change(n, ServiceStateChange.Added)
        await asyncio.sleep(0.05)  # the first try timed out: waiting a minute
        assert FakeInfo.calls == 1 and n.resolving
        change(n, ServiceStateChange.Updated)  # its records arrived
        await settle(n, 0.1)

    asyncio.run(go())
    assert FakeInfo.calls == 2 and ops(events) == ["seen"]


def test_an_update_of_a_listed_service_resolves_nothing(node: tuple[Node, io.StringIO]) -> None:
    n, events = node

    async def go() -> None:
        FakeInfo.answers = [True]
        change(n, ServiceStateChange.Added)
        await settle(n, 0.05)
        change(n, ServiceStateChange.Updated)
        await settle(n, 0.05)
        change(n, ServiceStateChange.Removed)

    asyncio.run(go())
    assert FakeInfo.calls == 1 and ops(events) == ["seen", "gone"]
