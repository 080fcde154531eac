"""Every option of `sdfr` and `sdfrd` says its allowed values and its default."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys

import pytest

import sdfr
from sdfr import __version__, cli
from sdfr.config import load


def parsers(p: argparse.ArgumentParser, name: str) -> list[tuple[str, argparse.ArgumentParser]]:
    out = [(name, p)]
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, sp in action.choices.items():
                out += parsers(sp, f"{name} {sub}")
    return out


ALL = parsers(cli.build_parser(), "sdfr") + parsers(load.build_parser(), "sdfrd")


@pytest.mark.parametrize("where, parser", ALL, ids=[n for n, _ in ALL])
def test_every_option_says_its_values_and_default(
    where: str, parser: argparse.ArgumentParser
) -> None:
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._VersionAction):
            continue
        if isinstance(action, argparse._SubParsersAction):
            continue
        if action.help == argparse.SUPPRESS:  # an option of every action, in `sdfr --help`
            assert any(action.dest == a.dest for a in ALL[0][1]._actions), action.dest
            continue
        text = action.help or ""
        name = "/".join(action.option_strings) or action.dest
        assert text, f"{where} {name}: no help"
        for choice in action.choices or ():
            assert str(choice) in text, f"{where} {name}: {choice} not named"
        takes_value = action.option_strings and action.nargs != 0
        if takes_value:
            assert re.search(r"\bdefault\b", text), f"{where} {name}: no default in {text!r}"


@pytest.mark.parametrize(
    "argv, error",
    [
        (["--timeout", "0", "health"], "above 0"),
        (["--timeout", "-1", "health"], "above 0"),
        (["--timeout", "nan", "health"], "above 0"),
        (["--timeout", "1e9", "health"], "at most 3600"),
        (["publish", "a", "b", "--hold"], "give --ttl"),
        (["events", "--event", "robots"], "no event kind"),
    ],
)
def test_bad_values_are_usage_errors(
    argv: list[str], error: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(argv) == 2
    assert error in capsys.readouterr().err


def test_a_mistyped_sdfrd_flag_is_one_line_with_the_closest_spelling(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as done:
        load.from_args(["--iface-name", "lo"])
    assert done.value.code == 2
    assert capsys.readouterr().err == (
        "sdfrd: unknown option --iface-name (did you mean '--iface'?); `sdfrd --help` shows usage\n"
    )


@pytest.mark.parametrize("module", ["sdfr.cli", "sdfr.daemon.supervisor", "netlab.cli"])
def test_version_on_every_command(module: str) -> None:
    res = subprocess.run(
        [sys.executable, "-m", module, "--version"], capture_output=True, text=True, timeout=60
    )
    assert res.returncode == 0, res.stderr
    assert f"{__version__} (sdfr-robots, Python " in res.stdout


def test_the_message_of_a_missing_extra_names_the_install_command() -> None:
    # For commands that need an optional extra (netlab's plots and pcap analysis): no sdfr
    # command needs one; netlab's use this message.
    text = sdfr.need_extra("netlab", "netlab report", "matplotlib")
    assert text == (
        "netlab report needs the 'netlab' extra (matplotlib is not installed): "
        "pip install 'sdfr-robots[netlab]'"
    )
