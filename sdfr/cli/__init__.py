"""`sdfr`: the command line of sdfrd's REST API, for humans (tables) and scripts (--json,
search --parsable). docs/sdfr-cli.md is its reference.

- `args`: the parser, one-line usage errors with a did-you-mean, where sdfrd is;
- `commands`: the actions on the REST API; `keys`: the fleet keyring on the unix socket;
- `local`: the actions that do not talk to sdfrd (wifi-config, example);
- `show`: tables, parsable lines, one line per change.
"""

from __future__ import annotations

import json
import os
import sys

from sdfr.cli import commands, keys
from sdfr.cli.args import EXAMPLES, Usage, build_parser, endpoint, typed_value, usage_error
from sdfr.cli.local import example_text, wifi_config
from sdfr.cli.show import describe_change, table
from sdfr.client import Client, owner_token_path, user_owner_token
from sdfr.client.calls import OWNER_HEADER
from sdfr.errors import ApiError

__all__ = ["EXAMPLES", "build_parser", "describe_change", "example_text", "main", "table"]
__all__ += ["typed_value"]

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
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # usage error (2) or --help (0); the parser said why
        return exc.code if isinstance(exc.code, int) else 2
    args.json = getattr(args, "json", False)
    args.timeout = getattr(args, "timeout", 5.0)
    if args.command == "publish" and args.hold and args.ttl is None:
        return usage_error("publish: --hold keeps a lease: give --ttl SECONDS too")
    if args.command in ("wifi-config", "example"):
        given = [f"--{n.replace('_', '-')}" for n in ("api", "socket", "state_dir") if n in args]
        if given:
            return usage_error(
                f"{args.command} does not talk to sdfrd: {', '.join(given)} has no use here"
                + (
                    "; give sdfrd's configuration with --config"
                    if args.command != "example"
                    else ""
                )
            )
    if args.command == "wifi-config":
        return wifi_config(args)
    if args.command == "example":
        sys.stdout.write(example_text(args.name))
        return 0
    if args.command == "keys":
        return keys.run(args)
    try:
        api, sock = endpoint(args)
    except Usage as exc:
        return usage_error(str(exc))
    token = user_owner_token() if args.command in OWNING else None
    status = 0
    try:
        with Client(api, unix_socket=sock, timeout=args.timeout, owner_token=token) as client:
            if args.command == "events" or (args.command == "neighbors" and args.watch):
                return commands.stream(client, args)
            if args.command == "publish" and args.hold:
                return commands.hold(client, args)
            answer, text, status = commands.COMMANDS[args.command](client, args)
        if args.json:
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
    return status
