"""`sdfr keys ...`: the fleet keyring, on sdfrd's unix socket (`generate` only writes a file)."""

from __future__ import annotations

import argparse
import json
import os
import stat
import sys
import time
from typing import Any

from sdfr.cli.args import Usage, endpoint, usage_error
from sdfr.cli.show import table
from sdfr.client import Client
from sdfr.config import keystore
from sdfr.errors import ApiError, ConfigError

_CHECK_SOCKET = "is it running, and is --state-dir (or --socket) right?"
_NEED_ACCESS = "key management needs access to the socket (root, or the socket's group)"
#: What `keys remove --open-fleet` adds: the configuration seeds an empty keyring again.
OPEN_FLEET_NOTE = (
    "the fleet is open on this robot: it sends and accepts unsigned datagrams only. If "
    "sdfrd's configuration has key_file (or wifi_secret_file and no key_file), remove it: "
    "at its next start sdfrd seeds an empty keyring from it again"
)

_MODE_TEXT = {
    "accept": "accepting signed and unsigned datagrams",
    "sign": "accepting signed and unsigned datagrams",
    "enforce": "accepting signed datagrams only",
}


def show_keys(answer: dict[str, Any]) -> str:
    mode = answer["mode"]
    if not answer["keyed"]:
        return "no fleet key: the fleet is open (sdfr keys install FILE)"
    primary = answer["primary"]
    if mode == "accept":
        signs = f"not signing yet (key {primary} signs after `sdfr keys mode sign`)"
    else:
        signs = f"signing with {primary}"
    head = f"mode: {mode}, {signs}, {_MODE_TEXT[mode]}"
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


def _checked_socket(path: str) -> str:
    """`path`, or ApiError saying what is wrong when there is no socket there."""
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


def run(args: argparse.Namespace) -> int:
    """`sdfr keys ...`: on the daemon's unix socket (or, for generate, on a file)."""
    as_json = getattr(args, "json", False)
    try:
        if args.keys_command == "generate":
            kid = keystore.generate_key_file(args.file, force=args.force)
            answer: Any = {"id": kid, "file": str(args.file)}
            text = (
                f"wrote key {kid} to {args.file} (mode 0600); copy it to each robot and set "
                "key_file, or `sdfr keys install` it on running robots"
            )
        else:
            try:
                _, sock = endpoint(args, unix_only=True)
            except Usage as exc:
                return usage_error(str(exc))
            assert sock is not None
            with Client(unix_socket=_checked_socket(sock), timeout=args.timeout) as client:
                try:
                    answer, text = _call(client, args)
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


def _call(client: Client, args: argparse.Namespace) -> tuple[Any, str]:
    action = args.keys_command
    if action == "list":
        answer = client.keys()
        return answer, show_keys(answer)
    if action == "install":
        had_keys = client.keys()["keyed"]
        answer = client.install_key(keystore.read_key_file(args.file))
        text = f"key {answer['id']} installed\n" + show_keys(answer)
        if not had_keys:
            text += (
                "\nthis robot had no key: it signs nothing yet and accepts both. When every "
                "robot has the key: `sdfr keys mode sign` on each, then `sdfr keys mode "
                "enforce` on each"
            )
        return answer, text
    if action == "use":
        answer = client.use_key(args.id)
        return answer, show_keys(answer)
    if action == "remove":
        client.remove_key(args.id, open_fleet=args.open_fleet)
        answer = client.keys()
        text = f"key {args.id} removed\n" + show_keys(answer)
        if not answer["keyed"]:
            text += "\n" + OPEN_FLEET_NOTE
        return answer, text
    answer = client.set_key_mode(args.mode)
    return answer, show_keys(answer)
