"""netlab.agent's protocol, without a lab: one JSON answer per request line, errors that
say what was wrong, and the end at `down` (labs across hosts themselves:
tests/ns/test_lab_across_hosts.py)."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from netlab import agent
from netlab.agentlink import AgentClient, Part
from netlab.hosts import Ssh
from sdfr.errors import ApiError


def answers(*lines: str) -> list[dict[str, object]]:
    out = io.StringIO()
    agent.serve(io.StringIO("".join(line + "\n" for line in lines)), out)
    return [json.loads(line) for line in out.getvalue().splitlines()]


def test_each_request_gets_one_answer_saying_what_was_wrong() -> None:
    got = answers(
        "not json",
        "[1, 2]",
        '{"op": "reboot"}',
        '{"op": "neighbors", "robot": "r1"}',
        '{"op": "move", "nonsense": 1}',
        '{"op": "batch", "ops": [{"op": "move"}, {"op": "down"}]}',
        '{"op": "api", "robot": "r1", "call": "shutdown", "args": {}}',
        "",
        '{"op": "down"}',
        '{"op": "merge"}',  # after down: not read
    )
    assert [a["ok"] for a in got] == [False] * 7 + [True]
    assert str(got[0]["error"]).startswith("not a request: Expecting value")
    assert got[1]["error"] == "not a request: a request is a JSON object"
    assert str(got[2]["error"]).startswith("no operation 'reboot' (one of hello, up, add_robots,")
    assert got[3]["error"] == "no lab here yet: `up` first"
    assert str(got[4]["error"]).startswith("move: bad request: TypeError:")
    assert str(got[5]["error"]).startswith("batch: ['down'] are not medium operations (move,")
    assert str(got[6]["error"]).startswith("api: no call 'shutdown' (one of neighbors, history,")


class _Refusing:
    """A robot's client whose daemon refuses, as sdfr.client.Client raises it."""

    def publish(self, **_: object) -> str:
        raise ApiError(422, "must be 1-63 characters", "name")


class _Lab:
    def client(self, robot: str) -> _Refusing:
        return _Refusing()


def test_a_daemons_refusal_crosses_as_the_api_error_it_was() -> None:
    """An `api` call the robot's daemon refuses answers with its status, message and field,
    and the controller's client raises the same ApiError (the engine's probes count it as a
    robot that cannot be asked, not a lost host); a host lost is an ApiError there too."""
    a = agent.Agent()
    a.lab = _Lab()  # type: ignore[assignment]
    got = a.handle({"op": "api", "robot": "r1", "call": "publish", "args": {"name": ""}})
    assert got == {
        "ok": False,
        "error": "name: must be 1-63 characters",
        "api": {"status": 422, "message": "must be 1-63 characters", "field": "name"},
    }

    # The controller's side, reading that very answer line from its host.
    refusing = answering(json.dumps(got))
    with pytest.raises(ApiError, match="name: must be 1-63") as refused:
        AgentClient(refusing, "r1").publish("", "t")
    assert refused.value.status == 422 and refused.value.field == "name"
    refusing.close()
    lost = answering(None)  # the session ends without a word: the host is gone
    with pytest.raises(ApiError, match="host h3: api: its agent ended") as gone:
        AgentClient(lost, "r1").neighbors()
    assert gone.value.status == 0
    lost.close()


def answering(line: str | None) -> Part:
    """A `Part` whose "host" reads one request and answers `line` (None: ends silently)."""
    part = Part.__new__(Part)
    part.ssh = Ssh("h3", Path("/nonexistent"), sys.executable)
    says = f"print({line!r})" if line is not None else "pass"
    part.proc = subprocess.Popen(
        [sys.executable, "-c", f"import sys; sys.stdin.readline(); {says}"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    part._lock = threading.Lock()
    return part


def test_the_share_goes_down_when_the_session_ends_without_down(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The controller died or the connection dropped: stdin ends, and the agent takes its
    share of the lab down all the same."""
    downs: list[bool] = []
    monkeypatch.setattr(agent.Agent, "down", lambda self: downs.append(True))
    assert [a["ok"] for a in answers('{"op": "merge"}')] == [False]  # no lab yet
    assert downs == [True]
