"""`sdfr`'s command line: the parser, the types of its values, one-line usage errors with the
closest valid spelling, and where sdfrd is (--api, --socket, --state-dir, anywhere on the line)."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sdfr import version_text
from sdfr.argparsing import HintingParser as Parser
from sdfr.client import split_api
from sdfr.config.load import DEFAULT_API, default_state_dir, flag, option_help
from sdfr.protocol.auth import MODES
from sdfr.records.events import FAMILIES, KINDS, kind_filter
from sdfr.records.model import AttrValue, attr_text

#: Longest --timeout (seconds): longer, and a dead daemon looks like a hung command.
TIMEOUT_MAX = 3600.0

EXIT_STATUSES = (
    "exit status: 0 done; 1 sdfrd said no, could not be reached, or (search, health) nothing "
    "matched or degraded; 2 a usage error; 130 interrupted"
)

#: The files of sdfr/deploy that `sdfr example` prints.
EXAMPLES = ("robot.toml", "sdfrd.service")

# sdfrd options that `sdfr wifi-config` takes too (wifi_secret is left out on purpose: a flag is
# visible in the process list; put it in the config file or wifi_secret_file).
WIFI_CONFIG_OPTIONS = (
    "iface",
    "fleet",
    "state_dir",
    "wifi",
    "wifi_secret_file",
    "wifi_mode",
    "wifi_freq",
    "wifi_country",
)


# -- value types -------------------------------------------------------------------------------


def _attr(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key, value


def _attr_option(command: argparse.ArgumentParser, text: str) -> None:
    """--attr KEY=VALUE, repeatable, of publish and search."""
    command.add_argument(
        "--attr", type=_attr, action="append", default=[], metavar="KEY=VALUE", help=text
    )


def _api(text: str) -> str:
    try:
        split_api(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def typed_value(text: str) -> AttrValue:
    """`true`/`false` as booleans, numbers as numbers, anything else as text.

    A value becomes a boolean or number only when it reads back as the same text, so that
    searching for the same text finds it (`0.50` and `007` stay strings).
    """
    if text in ("true", "false"):
        return text == "true"
    for kind in (int, float):
        try:
            value = kind(text)
        except ValueError:
            continue
        if math.isfinite(value) and attr_text(value) == text:
            return value
    return text


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value <= TIMEOUT_MAX:  # (NaN fails too)
        raise argparse.ArgumentTypeError(
            f"expected a number of seconds above 0 and at most {TIMEOUT_MAX:.0f}, got {text!r}"
        )
    return value


def _event_id(text: str) -> int:
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"expected an event id (a whole number), got {text!r}")
    return int(text)


def _kind(text: str) -> str:
    try:
        kind_filter([text])
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


#: What --event takes: the families (robot, service), then every kind (resync is both).
KIND_NAMES = (*sorted(FAMILIES - set(KINDS)), *KINDS)


# -- the parser --------------------------------------------------------------------------------


def _common(hidden: bool = False) -> Parser:
    """The options every action takes, before or after its name; `hidden` in an action's help
    (`sdfr --help` shows them). SUPPRESS: an action's parser leaves what the main parser read
    alone when they are not given again after the action."""
    p = _HelpHidden(add_help=False) if hidden else Parser(add_help=False)
    s = argparse.SUPPRESS
    p.add_argument("--json", action="store_true", default=s, help="print JSON (default: a table)")
    p.add_argument(
        "--api",
        type=_api,
        default=s,
        metavar="HOST:PORT",
        help=f"sdfrd's REST API (default {DEFAULT_API})",
    )
    p.add_argument(
        "--socket",
        default=s,
        metavar="PATH",
        help="sdfrd's unix socket instead of --api (default: none; keys: STATE_DIR/api.sock)",
    )
    p.add_argument(
        "--state-dir",
        type=Path,
        default=s,
        metavar="DIR",
        help=f"sdfrd's state directory: the same as --socket DIR/api.sock (default: none; "
        f"keys: {default_state_dir()})",
    )
    p.add_argument(
        "--timeout",
        type=_seconds,
        default=s,
        metavar="SECONDS",
        help=f"wait this long for sdfrd's answer, at most {TIMEOUT_MAX:.0f} (default 5)",
    )
    return p


class _HelpHidden(Parser):
    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        return super().add_argument(*args, **{**kwargs, "help": argparse.SUPPRESS})


#: An action's help ends with this: the options of `sdfr --help` are not repeated there.
COMMON_NOTE = "--json, --api, --socket, --state-dir, --timeout: see sdfr --help"


def build_parser() -> argparse.ArgumentParser:
    common = _common(hidden=True)
    p = Parser(
        prog="sdfr",
        description="Ask the local sdfrd which robots are reachable and what they offer; "
        "publish this robot's services. Every option goes before or after the ACTION.",
        epilog=EXIT_STATUSES,
        parents=[_common()],
    )
    p.add_argument("--version", action="version", version=version_text("sdfr"))
    sub = p.add_subparsers(dest="command", required=True, metavar="ACTION")

    def command(
        name: str, text: str, epilog: str | None = None, more: str = ""
    ) -> argparse.ArgumentParser:
        """An action: `text` in `sdfr --help`, with `more` in its own help."""
        note = COMMON_NOTE if epilog is None else f"{epilog}. {COMMON_NOTE}"
        about = text + more
        return sub.add_parser(name, help=text, description=about, epilog=note, parents=[common])

    c = command("neighbors", "robots reachable now and their services")
    c.add_argument("--all", action="store_true", help="also robots out of reach (history)")
    c.add_argument("--watch", action="store_true", help="then print each change, until Ctrl-C")
    c = command("publish", "publish a service of this robot; prints its id")
    c.add_argument("name", help="what people call it, e.g. 'front camera'")
    c.add_argument("type", help="what it is, searched by equality, e.g. camera/rgb")
    c.add_argument("--url", help="where to reach it (default: none)")
    _attr_option(c, "an attribute (repeatable); true/false and numbers are typed (default: none)")
    c.add_argument(
        "--ttl",
        type=_seconds,
        metavar="SECONDS",
        help="a lease: withdrawn SECONDS after its last renewal (`sdfr renew ID`) "
        "(default: none, it lives until unpublished)",
    )
    c.add_argument(
        "--hold", action="store_true", help="with --ttl: renew it until Ctrl-C, then unpublish"
    )
    c = command("unpublish", "withdraw a service of this robot")
    c.add_argument("service", metavar="ID|NAME", help="its id, or its name if no other has it")
    c = command("renew", "renew the lease of a service of this robot")
    c.add_argument("id", help="its id")
    c.add_argument("--ttl", type=_seconds, metavar="SECONDS", help="new ttl (default: the same)")
    c = command(
        "search",
        "services of reachable robots",
        "exit status: 0 something matched; 1 nothing did (after --wait), or sdfrd said no; "
        "2 a usage error. --parsable: one line per service, '=;ROBOT;ADDRESS;ID;NAME;TYPE;URL' "
        "then one KEY=VALUE field per attribute; ';', '\\' and control characters as \\DDD "
        "(decimal), as avahi-browse -p",
        more=" (all of them, or those matching --type and --attr)",
    )
    c.add_argument("--type", help="the service type (default: any)")
    _attr_option(c, "an attribute to match (repeatable; numbers by value) (default: none)")
    c.add_argument(
        "--wait",
        type=_seconds,
        nargs="?",
        const=TIMEOUT_MAX,
        metavar="SECONDS",
        help=f"until a match appears, at most SECONDS (default: no wait; alone: {TIMEOUT_MAX:.0f})",
    )
    c.add_argument(
        "-p", "--parsable", action="store_true", help="one ';'-separated line per service"
    )
    c = command(
        "events",
        "changes as they happen, until Ctrl-C",
        more=" (robots appearing, leaving, unreachable, their services, indicator "
        "thresholds; this robot's registrations)",
    )
    c.add_argument(
        "--since",
        type=_event_id,
        metavar="ID",
        help="first the changes kept after this id, 0 for all (default: only new ones; --once: 0)",
    )
    c.add_argument(
        "--event",
        type=_kind,
        action="append",
        metavar="KIND",
        help=f"only this kind or family (repeatable): {', '.join(KIND_NAMES)} (default: all)",
    )
    c.add_argument("--once", action="store_true", help="print the changes kept, then exit")
    command("history", "every robot ever seen, reachable or not")
    command("self", "this robot")
    command("services", "this robot's services")
    command("health", "whether both layers are up (exit status 1: degraded)")
    c = sub.add_parser(
        "wifi-config",
        help="the fleet's ad-hoc WiFi set-up, from sdfrd's config",
        description="The fleet's ad-hoc WiFi set-up sdfrd applies at start (from sdfrd's "
        "config; does not talk to sdfrd): prints it, and applies it unless --dry-run (root).",
    )
    c.add_argument("--json", action="store_true", default=argparse.SUPPRESS, help="print JSON")
    c.add_argument(
        "--config", type=Path, metavar="FILE", help="sdfrd's TOML config file (default: none)"
    )
    for name in WIFI_CONFIG_OPTIONS:
        c.add_argument(
            flag(name),
            dest=name,
            default=argparse.SUPPRESS,
            metavar=name.upper(),
            help=option_help(name),
        )
    c.add_argument("--dry-run", action="store_true", help="print what would be done, do nothing")
    c.add_argument("--show-key", action="store_true", help="print the WiFi key instead of ****")
    c = command(
        "example",
        "print robot.toml or sdfrd.service",
        more=" (installed with sdfr): a robot's configuration, the systemd unit (docs/deploy.md)",
    )
    c.add_argument("name", choices=EXAMPLES, help=f"one of {', '.join(EXAMPLES)}")
    _keys_parser(command, common)
    return p


def _keys_parser(
    command: Callable[..., argparse.ArgumentParser], common: argparse.ArgumentParser
) -> None:
    k = command(
        "keys",
        "the fleet keyring (on sdfrd's unix socket)",
        more=": keys that sign and check every datagram (STATE_DIR/api.sock, or --socket; "
        "`generate` only writes a file)",
    )
    ks = k.add_subparsers(dest="keys_command", required=True, metavar="ACTION")

    def action(name: str, text: str) -> argparse.ArgumentParser:
        return ks.add_parser(
            name, help=text, description=text, epilog=COMMON_NOTE, parents=[common]
        )

    g = action("generate", "write a new random fleet key to FILE (mode 0600)")
    g.add_argument("file", type=Path, metavar="FILE", help="where to write the key")
    g.add_argument("--force", action="store_true", help="replace FILE if it exists")
    action("list", "key ids, which one signs, the mode, datagrams received per key")
    i = action("install", "accept the key in FILE from now on (it signs after `use`)")
    i.add_argument("file", type=Path, metavar="FILE", help="the key file")
    u = action("use", "sign with key ID from now on")
    u.add_argument("id", metavar="ID", help="the key's id (`sdfr keys list`)")
    r = action(
        "remove",
        "stop accepting key ID (not the one that signs, unless it is the last one and "
        "--open-fleet is given)",
    )
    r.add_argument("id", metavar="ID", help="the key's id (`sdfr keys list`)")
    r.add_argument(
        "--open-fleet",
        action="store_true",
        help="remove the last key: this robot sends and accepts unsigned datagrams only "
        "(first `sdfr keys mode accept` on every robot; docs/sdfr-cli.md)",
    )
    m = action(
        "mode",
        "accept (send unsigned, accept both), sign (send signed, accept both), enforce "
        "(send signed, accept only signed)",
    )
    m.add_argument("mode", choices=MODES, help="accept, sign or enforce")


# -- where sdfrd is ----------------------------------------------------------------------------


class Usage(Exception):
    """A usage error found after parsing (exit status 2)."""


def endpoint(args: argparse.Namespace, *, unix_only: bool = False) -> tuple[str, str | None]:
    """(api, unix socket or None) from --api, --socket and --state-dir. `unix_only` (keys):
    the socket, by default in the default state directory; --api is a usage error."""
    api: str | None = getattr(args, "api", None)
    sock: str | None = getattr(args, "socket", None)
    state_dir: Path | None = getattr(args, "state_dir", None)
    if sock is not None and state_dir is not None:
        raise Usage("give --socket or --state-dir, not both")
    if state_dir is not None:
        sock = str(state_dir / "api.sock")
    if unix_only:
        if api is not None:
            raise Usage(
                "keys: key management is only available on sdfrd's unix socket; "
                "give --state-dir DIR or --socket PATH, not --api"
            )
        return DEFAULT_API, sock or str(default_state_dir() / "api.sock")
    if api is not None and sock is not None:
        raise Usage("give --api, or --socket/--state-dir, not both")
    return api or DEFAULT_API, sock


def usage_error(message: str) -> int:
    print(f"sdfr: error: {message}; see sdfr --help", file=sys.stderr)
    return 2
