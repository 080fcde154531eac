"""An argparse parser whose errors are one line with the closest spelling, not the usage:
the one parser of `netlab`, `sdfr` and `sdfrd`.

    p = HintingParser(prog="netlab")   # subparsers inherit the class
    p.parse_args(["stauts"])
    # netlab: unknown command 'stauts' (did you mean 'status'?); `netlab --help` shows usage

Exit status 2, as argparse's own errors.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator, Sequence
from typing import Any, NoReturn

from sdfr.hints import closest, did_you_mean

_CHOICE = re.compile(r"^argument (?P<arg>.+?): invalid choice: (?P<word>'.*?') \(choose from")
_QUOTED = re.compile(r"'((?:[^'\\]|\\.)*)'")


class HintingParser(argparse.ArgumentParser):
    """`error()` names the mistaken word and its closest spelling in one line."""

    _seen: list[str] | None = None

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: Any = None
    ) -> tuple[argparse.Namespace, list[str]]:
        if args is not None:
            self._seen = list(args)
        return super().parse_known_args(args, namespace)

    def parse_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: Any = None
    ) -> argparse.Namespace:
        ns, extras = self.parse_known_args(args, namespace)
        if extras:  # (said by the action's own parser: its options are the ones that apply)
            _chosen(self, ns).error(f"unrecognized arguments: {' '.join(extras)}")
        return ns

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {self.explain(message)}; `{self.prog} --help` shows usage\n")

    def explain(self, message: str) -> str:
        """`message` (argparse's) with the word at fault and its closest spelling."""
        unknown = self._unknown_options(message)
        if unknown:
            word = unknown[0]
            return f"unknown option {word}{did_you_mean(word, self._all_options())}"
        choice = _CHOICE.match(message)
        if choice is not None:
            word = _unquote(choice["word"])
            offered = [_unquote(q) for q in _QUOTED.findall(message[choice.end() :])]
            command = choice["arg"] in self._command_args()
            what = "command" if command else f"value for {choice['arg']}"
            close = closest(word, offered)
            hint = f" (did you mean {close!r}?)" if close else f" (one of {', '.join(offered)})"
            return f"unknown {what} {word!r}{hint}"
        if message.startswith("unrecognized arguments: "):
            return f"unexpected argument {message.split(': ', 1)[1]}"
        return message

    def _unknown_options(self, message: str) -> list[str]:
        """Flags on the line that no parser knows, when `message` may come from one."""
        if message.startswith("unrecognized arguments: "):
            words = message.split(": ", 1)[1].split()
        elif "required" in message or "expected" in message:
            words = self._seen or []
            if "--" in words:
                words = words[: words.index("--")]
        else:
            return []
        known = self._all_options()
        out = []
        for word in words:
            flag = word.split("=", 1)[0]
            if not flag.startswith("-") or flag == "-" or _number(flag):
                continue
            if flag in known or (not flag.startswith("--") and flag[:2] in known):
                continue  # (-t3: a short flag with its value attached)
            if not any(k.startswith(flag) for k in known if flag.startswith("--")):
                out.append(flag)  # (a unique prefix of a long flag is argparse's to judge)
        return out

    def _command_args(self) -> set[str]:
        """How argparse names the command arguments (sub-parsers) of this tree in errors."""
        return {
            str(a.metavar or a.dest)
            for p in self._tree()
            for a in p._actions
            if isinstance(a, argparse._SubParsersAction)
        } | {"COMMAND"}

    def _all_options(self) -> list[str]:
        return sorted({o for p in self._tree() for o in p._option_string_actions})

    def _tree(self) -> Iterator[argparse.ArgumentParser]:
        yield self
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    if isinstance(sub, HintingParser):
                        yield from sub._tree()


def _chosen(parser: argparse.ArgumentParser, ns: argparse.Namespace) -> argparse.ArgumentParser:
    """The innermost (sub)parser of the command given."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            name = getattr(ns, action.dest or "", None)
            if isinstance(name, str) and name in action.choices:
                return _chosen(action.choices[name], ns)
    return parser


def _unquote(text: str) -> str:
    return text[1:-1] if len(text) >= 2 and text[0] == text[-1] == "'" else text


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
