"""An argparse parser whose usage errors are one line: what is wrong, the closest valid
spelling (difflib), and where the help is; for `sdfr` and `sdfrd`."""

from __future__ import annotations

import argparse
import difflib
import re
from collections.abc import Sequence
from typing import NoReturn


class UsageParser(argparse.ArgumentParser):
    """Usage errors in one line: what is wrong, the closest valid spelling, where help is."""

    def error(self, message: str) -> NoReturn:
        choice = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)$", message)
        if choice:
            valid = re.findall(r"'([^']*)'", choice[2]) or choice[2].split(", ")
            close = difflib.get_close_matches(choice[1], valid, n=1)
            where = message[: choice.start()]
            message = f"{where}invalid choice {choice[1]!r} " + (
                f"(did you mean {close[0]}?)" if close else f"(choose from {', '.join(valid)})"
            )
        self.exit(2, f"{self.prog}: error: {message}; see {self.prog} --help\n")

    def parse_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> argparse.Namespace:
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            chosen = _chosen(self, ns)
            valid = [s for a in chosen._actions for s in a.option_strings]
            hints = []
            for extra in extras:
                close = difflib.get_close_matches(extra.partition("=")[0], valid, n=1)
                if extra.startswith("-") and close:
                    hints.append(f"{extra}: did you mean {close[0]}?")
            hint = f" ({'; '.join(hints)})" if hints else ""
            chosen.error(f"unrecognized arguments: {' '.join(extras)}{hint}")
        return ns


def _chosen(parser: argparse.ArgumentParser, ns: argparse.Namespace) -> argparse.ArgumentParser:
    """The innermost (sub)parser of the action given: the one whose options apply."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            name = getattr(ns, action.dest or "", None)
            if name in action.choices:
                return _chosen(action.choices[name], ns)
    return parser
