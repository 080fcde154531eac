"""`sdfr`: the command line of sdfrd's REST API, for humans (tables) and scripts (--json)."""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import stat
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

from sdfr import keystore, netif, version_text, wifi
from sdfr.auth import MODES
from sdfr.calls import OWNER_HEADER
from sdfr.client import (
    Change,
    Client,
    neighbors_path,
    owner_token_path,
    search_path,
    service_path,
    split_api,
    user_owner_token,
)
from sdfr.config import DEFAULT_API, default_state_dir, from_args, option_help
from sdfr.errors import ApiError, ConfigError, SdfrError
from sdfr.events import FAMILIES, KINDS, kind_filter
from sdfr.model import AttrValue, attr_text

Row = Sequence[object]


# -- argument parsing --------------------------------------------------------------------------


def _attr(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key, value


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


#: Longest --timeout (seconds): longer, and a dead daemon looks like a hung command.
TIMEOUT_MAX = 3600.0


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


_KINDS_HELP = ", ".join([*sorted(FAMILIES), *KINDS])


def build_parser() -> argparse.ArgumentParser:
    # --json is accepted before and after the command; SUPPRESS keeps the later from
    # resetting the earlier.
    json_flag = argparse.ArgumentParser(add_help=False)
    json_flag.add_argument(
        "--json",
        action="store_true",
        default=argparse.SUPPRESS,
        help="print the JSON answer (default: a table)",
    )
    p = argparse.ArgumentParser(
        prog="sdfr",
        description="Ask the local sdfrd which robots are reachable and what they offer; "
        "publish this robot's services.",
        parents=[json_flag],
    )
    p.add_argument("--version", action="version", version=version_text("sdfr"))
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--api",
        type=_api,
        default=DEFAULT_API,
        metavar="HOST:PORT",
        help=f"sdfrd's REST API (default {DEFAULT_API})",
    )
    where.add_argument(
        "--socket",
        metavar="PATH",
        help="sdfrd's unix socket instead, STATE_DIR/api.sock (default: none, --api is used)",
    )
    p.add_argument(
        "--timeout",
        type=_seconds,
        default=5.0,
        metavar="SECONDS",
        help=f"how long to wait for sdfrd's answer, above 0 and at most {TIMEOUT_MAX:.0f} "
        "(default 5)",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, text: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=text, description=text, parents=[json_flag])

    c = command("neighbors", "robots reachable now and their services")
    c.add_argument("--all", action="store_true", help="also robots out of reach (history)")
    c.add_argument(
        "--watch",
        action="store_true",
        help="then print each change of the robots as it happens, until Ctrl-C",
    )
    c = command("publish", "publish a service of this robot; prints its id")
    c.add_argument("name", help="what people call it, e.g. 'front camera'")
    c.add_argument("type", help="what it is, searched by equality, e.g. camera/rgb")
    c.add_argument("--url", help="where to reach it (default: none)")
    c.add_argument(
        "--attr",
        type=_attr,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an attribute (repeatable); true/false and numbers are typed (default: none)",
    )
    c.add_argument(
        "--ttl",
        type=_seconds,
        metavar="SECONDS",
        help="a lease: withdrawn from the fleet SECONDS after its last renewal "
        "(`sdfr renew ID`) (default: none, it lives until unpublished)",
    )
    c.add_argument(
        "--hold",
        action="store_true",
        help="with --ttl: stay running and renew it until Ctrl-C, then unpublish it",
    )
    c = command("unpublish", "withdraw a service of this robot")
    c.add_argument("id", help="its id (as publish printed it)")
    c = command("renew", "renew the lease of a service of this robot")
    c.add_argument("id", help="its id")
    c.add_argument(
        "--ttl", type=_seconds, metavar="SECONDS", help="a new ttl (default: the lease's own)"
    )
    c = command("search", "reachable robots offering matching services")
    c.add_argument("--type", help="the service type (default: any)")
    c.add_argument(
        "--attr",
        type=_attr,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an attribute the service must have (repeatable; numbers match by value, "
        "true/false booleans) (default: none)",
    )
    c = command(
        "events",
        "changes as they happen (robots appearing, leaving, unreachable, their services, "
        "indicator thresholds; this robot's registrations), until Ctrl-C",
    )
    c.add_argument(
        "--since",
        type=_event_id,
        metavar="ID",
        help="first the changes kept after this event id, 0 for all (default: only new ones)",
    )
    c.add_argument(
        "--event",
        type=_kind,
        action="append",
        metavar="KIND",
        help=f"only this kind or family (repeatable): {_KINDS_HELP} (default: all)",
    )
    command("history", "every robot ever seen, reachable or not")
    command("self", "this robot")
    command("services", "this robot's services")
    command("health", "whether both layers are up (exit status 1 when degraded)")
    c = command(
        "wifi-config",
        "the fleet's ad-hoc WiFi set-up sdfrd applies at start (from sdfrd's config; does not "
        "talk to sdfrd): prints it, and applies it unless --dry-run (needs root)",
    )
    c.add_argument(
        "--config", type=Path, metavar="FILE", help="sdfrd's TOML config file (default: none)"
    )
    for name in WIFI_CONFIG_OPTIONS:
        c.add_argument(
            "--" + name.replace("_", "-"), dest=name, metavar=name.upper(), help=option_help(name)
        )
    c.add_argument("--dry-run", action="store_true", help="print what would be done, do nothing")
    c.add_argument("--show-key", action="store_true", help="print the WiFi key instead of ****")
    c = command(
        "example",
        "print a file installed with sdfr (does not talk to sdfrd): robot.toml, a robot's "
        "configuration; sdfrd.service, the systemd unit (docs/deploy.md)",
    )
    c.add_argument("name", choices=EXAMPLES, help=f"one of {', '.join(EXAMPLES)}")
    _keys_parser(command)
    return p


#: The files of sdfr/deploy that `sdfr example` prints.
EXAMPLES = ("robot.toml", "sdfrd.service")


def example_text(name: str) -> str:
    """A file installed with the package (sdfr/deploy/NAME)."""
    return (resources.files("sdfr") / "deploy" / name).read_text()


def _keys_parser(command: Callable[[str, str], argparse.ArgumentParser]) -> None:
    k = command(
        "keys",
        "the fleet keyring: keys that sign and check every datagram (talks to sdfrd over its "
        "unix socket STATE_DIR/api.sock, or --socket; `generate` only writes a file)",
    )
    where = k.add_mutually_exclusive_group()
    where.add_argument(
        "--state-dir",
        type=Path,
        default=None,
        metavar="DIR",
        help=f"sdfrd's state directory, for its api.sock (default {default_state_dir()})",
    )
    # SUPPRESS: when not given here, `sdfr --socket PATH keys ...` still counts.
    where.add_argument(
        "--socket",
        default=argparse.SUPPRESS,
        metavar="PATH",
        help="sdfrd's unix socket, instead of --state-dir (default: STATE_DIR/api.sock)",
    )
    ks = k.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    g = ks.add_parser("generate", help="write a new random fleet key to FILE (mode 0600)")
    g.add_argument("file", type=Path, metavar="FILE", help="where to write the key")
    g.add_argument("--force", action="store_true", help="replace FILE if it exists")
    ks.add_parser("list", help="key ids, which one signs, the mode, datagrams received per key")
    i = ks.add_parser("install", help="accept the key in FILE from now on (it signs after `use`)")
    i.add_argument("file", type=Path, metavar="FILE", help="the key file")
    u = ks.add_parser("use", help="sign with key ID from now on")
    u.add_argument("id", metavar="ID", help="the key's id (`sdfr keys list`)")
    r = ks.add_parser("remove", help="stop accepting key ID (not the one in use)")
    r.add_argument("id", metavar="ID", help="the key's id (`sdfr keys list`)")
    m = ks.add_parser(
        "mode",
        help="accept (send unsigned, accept both), sign (send signed, accept both), enforce "
        "(send signed, accept only signed)",
    )
    m.add_argument("mode", choices=MODES, help="accept, sign or enforce")


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


# -- output ------------------------------------------------------------------------------------


def table(headers: Sequence[str], rows: Sequence[Row]) -> str:
    """Columns aligned, two spaces apart."""
    cells = [[str(c) for c in headers], *[[_cell(c) for c in row] for row in rows]]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in cells]
    return "\n".join(lines)


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    return str(value)


def _indicator(value: object) -> str:
    return f"{value:.2f}" if isinstance(value, int | float) else "-"


def _rtt(value: object) -> str:
    return f"{value:.1f} ms" if isinstance(value, int | float) else "-"


def _ago(epoch: object, now: float) -> str:
    if not isinstance(epoch, int | float) or epoch <= 0:
        return "-"
    age = max(0.0, now - epoch)
    if age < 120:
        return f"{age:.0f}s ago"
    if age < 7200:
        return f"{age / 60:.0f}m ago"
    return f"{age / 3600:.1f}h ago"


def _names(services: list[dict[str, Any]], limit: int = 4) -> str:
    names = [str(s.get("name")) for s in services]
    if len(names) > limit:
        return ", ".join(names[:limit]) + f", +{len(names) - limit} more"
    return ", ".join(names) or "-"


def _attrs(attributes: object) -> str:
    if not isinstance(attributes, dict) or not attributes:
        return "-"
    return " ".join(f"{k}={attr_text(v)}" for k, v in attributes.items())


def _show_neighbors(answer: dict[str, Any]) -> str:
    robots = answer["neighbors"]
    if not robots:
        return "no reachable robots"
    return table(
        ["ROBOT", "ADDRESS", "REACHABLE", "INDICATOR", "RTT", "SERVICES"],
        [
            (
                r["robot_id"],
                r["address"] or "-",
                r["reachable"],
                _indicator(r.get("indicator")),
                _rtt(r.get("rtt_ms")),
                _names(r["services"]),
            )
            for r in robots
        ],
    )


def _show_matches(answer: dict[str, Any]) -> str:
    rows = [
        (
            r["robot_id"],
            r["address"] or "-",
            s["id"],
            s["name"],
            s["type"],
            s["url"],
            _attrs(s.get("attributes")),
        )
        for r in answer["neighbors"]
        for s in r["services"]
    ]
    if not rows:
        return "no reachable robot offers a matching service"
    return table(["ROBOT", "ADDRESS", "ID", "NAME", "TYPE", "URL", "ATTRIBUTES"], rows)


def _show_services(answer: dict[str, Any]) -> str:
    services = answer["services"]
    if not services:
        return "no services published"
    return table(
        ["ID", "NAME", "TYPE", "URL", "ATTRIBUTES", "LEASE"],
        [
            (
                s["id"],
                s["name"],
                s["type"],
                s["url"],
                _attrs(s.get("attributes")),
                f"{s['ttl']:g} s" if isinstance(s.get("ttl"), int | float) else "-",
            )
            for s in services
        ],
    )


def _show_history(answer: dict[str, Any]) -> str:
    robots = answer["robots"]
    if not robots:
        return "no robot seen yet"
    now = time.time()
    return table(
        ["ROBOT", "ADDRESS", "REACHABLE", "LAST SEEN", "INDICATOR", "RTT", "SERVICES"],
        [
            (
                r["robot_id"],
                r["address"] or "-",
                r["reachable"],
                _ago(r.get("last_seen"), now),
                _indicator(r.get("indicator")),
                _rtt(r.get("rtt_ms")),
                _names(r["services"]),
            )
            for r in robots
        ],
    )


def _show_self(answer: dict[str, Any]) -> str:
    disc = answer.get("discovery") or {}
    state = "up" if disc.get("up") else "down"
    age = disc.get("heartbeat_age")
    if isinstance(age, int | float):
        state += f" (last heartbeat {age:.1f}s ago)"
    pairs = [
        ("robot", answer.get("robot_id")),
        ("fleet", answer.get("fleet")),
        ("address", answer.get("address") or None),
        ("boot id", answer.get("boot_id")),
        ("version", answer.get("version")),
        ("location", answer.get("location")),
        ("discovery", state),
    ]
    lines = [f"{key + ':':<10} {_cell(value)}" for key, value in pairs]
    return "\n".join(lines) + "\n\n" + _show_services(answer)


def _show_health(answer: Mapping[str, Any]) -> str:
    age = answer.get("discovery_heartbeat_age")
    beat = f", last heartbeat {age:.1f}s ago" if isinstance(age, int | float) else ""
    auth = f", fleet key: {answer['auth']}" if answer.get("auth") else ""
    lines = [
        f"{answer['status']}: api {answer['api']}, discovery {answer['discovery']}{beat}{auth}"
    ]
    if answer.get("discovery_error"):
        lines.append(f"error: {answer['discovery_error']}")
    lines += [f"warning: {w}" for w in answer.get("warnings") or []]
    return "\n".join(lines)


def _show_keys(answer: dict[str, Any]) -> str:
    mode = answer["mode"]
    if not answer["keyed"]:
        return "no fleet key: the fleet is open (sdfr keys install FILE)"
    head = f"mode: {mode}, signing with {answer['primary'] if mode != 'accept' else 'no key'}"
    rows = [
        (
            k["id"],
            k["primary"],
            time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(k["installed"]))
            if isinstance(k.get("installed"), int | float)
            else "-",
            k["received"],
        )
        for k in answer["keys"]
    ]
    text = head + "\n" + table(["KEY", "PRIMARY", "INSTALLED", "RECEIVED"], rows)
    unknown = [
        (u["id"], u["address"], u["count"], time.strftime("%X", time.localtime(u["last_seen"])))
        for u in answer.get("unknown") or []
    ]
    if unknown:
        text += (
            "\nkeys not in the keyring, datagrams dropped (a robot left out of a rotation?):\n"
            + table(["KEY", "FROM", "DATAGRAMS", "LAST"], unknown)
        )
    return text


# -- commands ----------------------------------------------------------------------------------

Command = Callable[[Client, argparse.Namespace], tuple[Any, str]]


def _neighbors(client: Client, args: argparse.Namespace) -> tuple[Any, str]:
    answer = client.request("GET", neighbors_path(args.all))
    return answer, _show_neighbors(answer)


def _publish(client: Client, args: argparse.Namespace) -> tuple[Any, str]:
    attrs = {key: typed_value(value) for key, value in args.attr}
    answer = client.publish_service(args.name, args.type, args.url, attrs or None, ttl=args.ttl)
    return answer, str(answer["id"])


def _renew(client: Client, args: argparse.Namespace) -> tuple[Any, str]:
    answer = client.renew(args.id, args.ttl)
    until = time.strftime("%H:%M:%S", time.localtime(answer["expires"]))
    return answer, f"{args.id}: lease of {answer['ttl']:g} s, until {until}"


def _unpublish(client: Client, args: argparse.Namespace) -> tuple[Any, str]:
    client.request("DELETE", service_path(args.id))
    return None, ""


def _search(client: Client, args: argparse.Namespace) -> tuple[Any, str]:
    answer = client.request("GET", search_path(args.type, dict(args.attr)))
    return answer, _show_matches(answer)


def _get(path: str, show: Callable[[dict[str, Any]], str]) -> Command:
    def run(client: Client, args: argparse.Namespace) -> tuple[Any, str]:
        answer = client.request("GET", path)
        return answer, show(answer)

    return run


def _health(client: Client, args: argparse.Namespace) -> tuple[Any, str]:
    answer = client.health()
    return answer, _show_health(answer)


COMMANDS: dict[str, Command] = {
    "neighbors": _neighbors,
    "publish": _publish,
    "unpublish": _unpublish,
    "renew": _renew,
    "search": _search,
    "history": _get("/history", _show_history),
    "self": _get("/self", _show_self),
    "services": _get("/services", _show_services),
    "health": _health,
}


def _wifi_config(args: argparse.Namespace) -> int:
    """`sdfr wifi-config`: plan from sdfrd's configuration; print it; apply unless --dry-run."""
    as_json = getattr(args, "json", False)
    sdfrd_argv: list[str] = [] if args.config is None else ["--config", str(args.config)]
    for name in WIFI_CONFIG_OPTIONS:
        value = getattr(args, name)
        if value is not None:
            sdfrd_argv += ["--" + name.replace("_", "-"), value]
    try:
        cfg = from_args(sdfrd_argv)
        cfg = replace(cfg, iface=cfg.iface or netif.default_iface())
        assert cfg.iface is not None
        secret, warnings = wifi.load_secret(cfg)
        the_plan = wifi.plan(cfg, secret)
    except ConfigError as exc:
        print(f"sdfr: {exc}", file=sys.stderr)
        return 2
    for warning in warnings:
        print(f"sdfr: warning: {warning}", file=sys.stderr)
    wireless = wifi.is_wireless(cfg.iface)
    notes: list[str] = []
    if cfg.wifi == "off":
        notes.append("wifi = off: sdfrd does not touch the radio")
    if not wireless:
        notes.append(
            f"{cfg.iface} is not a wireless interface: sdfrd leaves it alone"
            + ("" if netif.exists(cfg.iface) else f" ({cfg.iface} does not exist here)")
        )
    applied = False
    if not args.dry_run:
        try:
            if cfg.wifi == "off":
                raise SdfrError("wifi: is off in the configuration; pass --wifi auto to apply")
            if not wireless:
                raise SdfrError(f"wifi: {cfg.iface} is not a wireless interface; not touching it")
            wifi.check_root()
            wifi.apply(the_plan)
        except SdfrError as exc:
            print(f"sdfr: {exc}", file=sys.stderr)
            return 1
        applied = True
    if as_json:
        answer = the_plan.to_json(args.show_key)
        answer.update(
            dry_run=args.dry_run,
            applied=applied,
            wireless=wireless,
            sdfrd_applies=cfg.wifi == "auto" and wireless,
            notes=notes,
        )
        print(json.dumps(answer, indent=2))
    else:
        print(the_plan.describe(args.show_key))
        for note in notes:
            print(f"# note: {note}")
        if applied:
            print(f"# done: {cfg.iface} is joining {the_plan.ssid}")
    return 0


def _hold(client: Client, args: argparse.Namespace) -> int:
    """`sdfr publish ... --ttl T --hold`: keep the lease until interrupted, then unpublish."""
    attrs = {key: typed_value(value) for key, value in args.attr}
    stop = {signal.SIGINT, signal.SIGTERM}
    # Blocked before the renewing thread starts (it inherits the mask), so that the signal
    # ends the wait below, and the lease is unpublished, whichever thread it was sent to.
    signal.pthread_sigmask(signal.SIG_BLOCK, stop)
    try:
        with client.lease(args.name, args.type, args.url, attrs or None, ttl=args.ttl) as kept:
            print(kept.id, flush=True)
            signal.sigwait(stop)
            print(f"sdfr: unpublishing {kept.id}", file=sys.stderr)
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, stop)
    return 0


def _clock(epoch: float) -> str:
    return time.strftime("%H:%M:%S", time.localtime(epoch)) + f".{int(epoch % 1 * 1000):03d}"


def describe_change(change: Change) -> str:
    """One line for a human: when, what, which robot, the details that matter."""
    d = change.data
    who = change.robot_id or "this robot"
    kind = change.event
    if kind == "robot.appeared":
        names = _names(d.get("services") or [])
        what = f"appeared at {d.get('address') or '-'}" + ("" if d.get("new") else " again")
        if d.get("services_truncated"):
            names = f"{d.get('services_count')} services"
        text = f"+ {who} {what} ({names})"
    elif kind in ("robot.left", "robot.unreachable"):
        how = "left (said goodbye)" if kind == "robot.left" else "became unreachable"
        reason = f", {d['reason']}" if d.get("reason") else ""
        text = f"- {who} {how}{reason}"
    elif kind == "robot.services":
        parts = [f"+{s.get('name')}" for s in d.get("added") or []]
        parts += [f"-{sid}" for sid in d.get("removed") or []]
        parts += [f"~{s.get('name')}" for s in d.get("changed") or []]
        text = f"~ {who} services: {' '.join(parts) or 'changed'}"
    elif kind == "robot.address":
        text = f"~ {who} moved from {d.get('previous')} to {d.get('address')}"
    elif kind == "robot.indicator":
        arrow = "rose above" if d.get("direction") == "up" else "fell below"
        text = f"! {who} indicator {_indicator(d.get('indicator'))} {arrow} {d.get('threshold')}"
    elif kind == "robot.forgotten":
        text = f"- {who} forgotten (the history map was full)"
    elif kind.startswith("service."):
        service = d.get("service") or {}
        name = f" {service.get('name')!r}" if service else ""
        verb = kind.split(".")[1]
        lease = f", lease {d['ttl']:g} s" if d.get("ttl") else ""
        text = f"* {verb} {d.get('service_id')}{name}{lease}"
    elif kind == "resync":
        text = "! some changes are no longer kept: read the state again (sdfr neighbors)"
    else:
        text = f"? {kind} {who}"
    return f"{_clock(change.time)}  {text}"


def _stream(client: Client, args: argparse.Namespace, as_json: bool) -> None:
    """`sdfr events` and `sdfr neighbors --watch`: print changes until interrupted."""
    if args.command == "neighbors":
        kinds: list[str] = ["robot"]
        # The stream first, from the newest id, so that no change falls between the two.
        since: int | None = client.events(since=None)["last_id"]
        answer = client.request("GET", neighbors_path(args.all))
        if as_json:
            print(json.dumps({"event": "snapshot", **answer}, ensure_ascii=False), flush=True)
        else:
            print(_show_neighbors(answer), flush=True)
    else:
        kinds = args.event or []
        since = args.since
    for change in client.watch(kinds, since):
        if as_json:
            print(json.dumps(change.data, ensure_ascii=False), flush=True)
        else:
            print(describe_change(change), flush=True)


_CHECK_SOCKET = "is it running, and is --state-dir (or --socket) right?"
_NEED_ACCESS = "key management needs access to the socket (root, or the socket's group)"


def _keys_socket(args: argparse.Namespace) -> str:
    """The unix socket `sdfr keys` talks to: --socket, else --state-dir's api.sock; ApiError
    saying what is wrong when there is no socket there."""
    path = args.socket or str((args.state_dir or default_state_dir()) / "api.sock")
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise ApiError(0, f"no sdfrd answers on {path}: {_CHECK_SOCKET}") from None
    except PermissionError:
        raise ApiError(0, f"cannot look at {path}: permission denied; {_NEED_ACCESS}") from None
    except OSError as exc:
        raise ApiError(0, f"cannot look at {path}: {exc.strerror or exc}") from None
    if not stat.S_ISSOCK(mode):
        raise ApiError(0, f"{path} is not a unix socket: is --state-dir (or --socket) right?")
    return path


def _keys(args: argparse.Namespace) -> int:
    """`sdfr keys ...`: on the daemon's unix socket (or, for generate, on a file)."""
    as_json = getattr(args, "json", False)
    action = args.keys_command
    try:
        if action == "generate":
            kid = keystore.generate_key_file(args.file, force=args.force)
            answer: Any = {"id": kid, "file": str(args.file)}
            text = (
                f"wrote key {kid} to {args.file} (mode 0600); copy it to each robot and set "
                "key_file, or `sdfr keys install` it on running robots"
            )
        else:
            if args.api != DEFAULT_API:
                print(
                    "sdfr: keys: key management is only available on sdfrd's unix socket; "
                    "give --state-dir DIR or --socket PATH, not --api",
                    file=sys.stderr,
                )
                return 2
            if args.socket is not None and args.state_dir is not None:
                print("sdfr: keys: give --socket or --state-dir, not both", file=sys.stderr)
                return 2
            socket_path = _keys_socket(args)
            with Client(unix_socket=socket_path, timeout=args.timeout) as client:
                try:
                    answer, text = _keys_call(client, args)
                except ApiError as exc:
                    if exc.status != 0 or not exc.message.startswith("cannot reach"):
                        raise
                    hint = _NEED_ACCESS if "Permission denied" in exc.message else _CHECK_SOCKET
                    what = exc.message.partition(";")[0]  # (the client's hint is for the API)
                    raise ApiError(0, f"{what}; {hint}") from None
    except (ConfigError, ApiError) as exc:
        print(f"sdfr: {exc}", file=sys.stderr)
        return 1
    if as_json:
        if answer is not None:
            print(json.dumps(answer, indent=2))
    elif text:
        print(text)
    return 0


def _keys_call(client: Client, args: argparse.Namespace) -> tuple[Any, str]:
    action = args.keys_command
    if action == "list":
        answer = client.keys()
        return answer, _show_keys(answer)
    if action == "install":
        had_keys = client.keys()["keyed"]
        answer = client.install_key(keystore.read_key_file(args.file))
        text = f"key {answer['id']} installed\n" + _show_keys(answer)
        if not had_keys:
            text += (
                "\nthis robot had no key: it signs nothing yet and accepts both. When every "
                "robot has the key: `sdfr keys mode sign` on each, then `sdfr keys mode "
                "enforce` on each"
            )
        return answer, text
    if action == "use":
        answer = client.use_key(args.id)
        return answer, _show_keys(answer)
    if action == "remove":
        client.remove_key(args.id)
        answer = client.keys()
        return answer, f"key {args.id} removed\n" + _show_keys(answer)
    answer = client.set_key_mode(args.mode)
    return answer, _show_keys(answer)


#: The commands that change a registration: they send this user's owner token.
OWNING = frozenset({"publish", "unpublish", "renew"})


def _not_yours_hint(exc: ApiError) -> ApiError:
    """A 403 on a registration: say how sdfr can be its owner."""
    if exc.status != 403 or exc.field != OWNER_HEADER:
        return exc
    return ApiError(
        exc.status,
        f"{exc.message.partition(': only')[0]}; sdfr sends the token kept in "
        f"{owner_token_path()} (the publishing user's), or use --socket as that user or root",
        exc.field,
    )


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.command == "search" and args.type is None and not args.attr:
            parser.error("search: give --type T and/or --attr KEY=VALUE")
        if args.command == "publish" and args.hold and args.ttl is None:
            parser.error("publish: --hold keeps a lease: give --ttl SECONDS too")
    except SystemExit as exc:  # usage error (2) or --help (0); argparse printed why
        return exc.code if isinstance(exc.code, int) else 2
    if args.command == "wifi-config":
        return _wifi_config(args)
    if args.command == "example":
        sys.stdout.write(example_text(args.name))
        return 0
    if args.command == "keys":
        return _keys(args)
    token = user_owner_token() if args.command in OWNING else None
    try:
        with Client(
            args.api, unix_socket=args.socket, timeout=args.timeout, owner_token=token
        ) as client:
            if args.command == "events" or (args.command == "neighbors" and args.watch):
                _stream(client, args, getattr(args, "json", False))
                return 0
            if args.command == "publish" and args.hold:
                return _hold(client, args)
            answer, text = COMMANDS[args.command](client, args)
        if getattr(args, "json", False):
            if answer is not None:
                print(json.dumps(answer, indent=2, ensure_ascii=False))
        elif text:
            print(text)
    except ApiError as exc:
        print(f"sdfr: {_not_yours_hint(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `sdfr history | head`: stop quietly, also at exit's flush
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    if args.command == "health" and answer.get("status") == "degraded":
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
