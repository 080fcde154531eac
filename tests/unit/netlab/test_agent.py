"""netlab.agent's protocol, without a lab: one JSON answer per request line, errors that
say what was wrong, and the end at `down` (labs across hosts themselves:
tests/ns/test_lab_across_hosts.py)."""

from __future__ import annotations

import io
import json

import pytest

from netlab import agent


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
        "",
        '{"op": "down"}',
        '{"op": "merge"}',  # after down: not read
    )
    assert [a["ok"] for a in got] == [False, False, False, False, False, True]
    assert str(got[0]["error"]).startswith("not a request: Expecting value")
    assert got[1]["error"] == "not a request: a request is a JSON object"
    assert str(got[2]["error"]).startswith("no operation 'reboot' (one of up, add_robot,")
    assert got[3]["error"] == "no lab here yet: `up` first"
    assert str(got[4]["error"]).startswith("move: bad request: TypeError:")


def test_the_share_goes_down_when_the_session_ends_without_down(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The controller died or the connection dropped: stdin ends, and the agent takes its
    share of the lab down all the same."""
    downs: list[bool] = []
    monkeypatch.setattr(agent.Agent, "down", lambda self: downs.append(True))
    assert [a["ok"] for a in answers('{"op": "merge"}')] == [False]  # no lab yet
    assert downs == [True]
