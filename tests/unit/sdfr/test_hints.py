"""The shared did-you-mean helpers: `sdfr.hints` and the one-line argparse errors."""

from __future__ import annotations

import pytest

from sdfr.argparsing import HintingParser
from sdfr.hints import closest, did_you_mean


def test_closest_spelling_is_offered_and_a_far_word_gets_none() -> None:
    assert closest("radious", ["radius", "robots", "seed"]) == "radius"
    assert did_you_mean("radious", ["radius", "robots"]) == " (did you mean 'radius'?)"
    assert closest("zzz", ["radius", "robots"]) is None
    assert did_you_mean("zzz", ["radius"]) == ""


def _parser() -> HintingParser:
    p = HintingParser(prog="tool")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    up = sub.add_parser("up")
    up.add_argument("name")
    up.add_argument("--robots", type=int, required=True)
    up.add_argument("-t", "--topology")
    up.add_argument("--kind", choices=["namespace", "docker"])
    sub.add_parser("status")
    return p


def _error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    with pytest.raises(SystemExit) as exit_:
        _parser().parse_args(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, f"more than one line: {err!r}"
    return err


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["stauts"], "tool: unknown command 'stauts' (did you mean 'status'?)"),
        (["up", "a", "--robots", "2", "--kind", "dokcer"], "(did you mean 'docker'?)"),
        (["up", "a", "--robts", "2"], "tool up: unknown option --robts (did you mean '--robots'?)"),
        (["up", "a", "--robots", "2", "--topolgy=x"], "unknown option --topolgy (did you mean"),
        (["up"], "tool up: the following arguments are required: name, --robots"),
        (["status", "x"], "tool status: unexpected argument x"),
    ],
)
def test_a_command_line_mistake_is_one_line_naming_the_closest_spelling(
    capsys: pytest.CaptureFixture[str], argv: list[str], expected: str
) -> None:
    err = _error(capsys, argv)
    assert expected in err
    assert "--help` shows usage" in err


def test_a_far_choice_lists_the_choices_and_short_flags_with_values_are_known(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert "(one of namespace, docker)" in _error(
        capsys, ["up", "a", "--robots", "2", "--kind", "zz"]
    )
    args = _parser().parse_args(["up", "a", "--robots", "2", "-tfile"])
    assert args.topology == "file"
