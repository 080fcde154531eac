"""The records of labs left up across hosts (netlab.spankeep), without hosts: what a damaged
record, a dead keeper and a command that runs on one host say."""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

import pytest

from netlab import spankeep
from netlab.errors import LabNotFoundError, NetlabError


@pytest.fixture(autouse=True)
def run_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("NETLAB_RUN_DIR", str(tmp_path))
    spankeep.span_dir().mkdir()
    return tmp_path


def a_record(pid: int) -> spankeep.SpanRecord:
    return spankeep.SpanRecord("demo", pid, ["h1", "h2"], {"h1": "demo0", "h2": "demo1"},
                               {"r1": "h1", "r2": "h2"}, None, "python3", 0.0)  # fmt: skip


def test_a_record_round_trips_and_a_damaged_one_is_named() -> None:
    spankeep.record_path("demo").write_text(json.dumps(asdict(a_record(1))))
    assert spankeep.load("demo") == a_record(1)
    assert spankeep.names() == ["demo"]
    spankeep.record_path("demo").write_text('{"name": "demo"}')
    with pytest.raises(NetlabError, match=r"lab demo: its record .*demo.json is damaged"):
        spankeep.load("demo")
    spankeep.record_path("demo").write_text("{")
    with pytest.raises(NetlabError, match=r"is unreadable"):
        spankeep.load("demo")
    assert spankeep.load("other") is None


def test_a_dead_keeper_is_said_and_no_lab_is_not_found() -> None:
    with pytest.raises(LabNotFoundError, match="no lab demo is up across hosts"):
        spankeep.call("demo", "status")
    # A pid that is not a keeper (this test's own process is not `netlab.spankeep`).
    record = a_record(os.getpid())
    spankeep.record_path("demo").write_text(json.dumps(asdict(record)))
    assert not record.keeper_alive()
    with pytest.raises(NetlabError, match=r"its keeper \(pid \d+\) is gone.*`netlab down demo`"):
        spankeep.call("demo", "merge")


def test_a_one_host_command_names_the_robots_host_and_share() -> None:
    spankeep.record_path("demo").write_text(json.dumps(asdict(a_record(1))))
    err = spankeep.elsewhere("demo", "r2", "exec")
    assert str(err) == (
        "lab demo runs across hosts: r2 is on h2, in its share demo1 there: "
        "`ssh h2 netlab exec demo1 r2 ...`"
    )
    assert "h1: demo0, h2: demo1" in str(spankeep.elsewhere("demo", None, "pingall"))
