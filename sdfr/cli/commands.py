"""The `sdfr` actions that talk to sdfrd's REST API: each returns (JSON answer, text, exit
status); the streams (`events`, `neighbors --watch`) and `publish --hold` print as they go."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

from sdfr.cli.args import typed_value
from sdfr.cli.show import (
    ChangeLines,
    attrs_text,
    parsable,
    show_health,
    show_history,
    show_neighbors,
    show_self,
    show_services,
    table,
)
from sdfr.client import Change, Client, neighbors_path, search_path, service_path
from sdfr.errors import ApiError

Result = tuple[Any, str, int]
Command = Callable[[Client, argparse.Namespace], Result]

#: How often `search --wait` asks again.
WAIT_POLL = 0.2


def _neighbors(client: Client, args: argparse.Namespace) -> Result:
    answer = client.request("GET", neighbors_path(args.all))
    return answer, show_neighbors(answer), 0


def _publish(client: Client, args: argparse.Namespace) -> Result:
    attrs = {key: typed_value(value) for key, value in args.attr}
    answer = client.publish_service(args.name, args.type, args.url, attrs or None, ttl=args.ttl)
    return answer, str(answer["id"]), 0


def _renew(client: Client, args: argparse.Namespace) -> Result:
    answer = client.renew(args.id, args.ttl)
    until = time.strftime("%H:%M:%S", time.localtime(answer["expires"]))
    return answer, f"{args.id}: lease of {answer['ttl']:g} s, until {until}", 0


def service_id(services: list[dict[str, Any]], text: str) -> str:
    """The id of this robot's service whose id is `text`, else of the one service named `text`;
    ApiError listing the candidates otherwise."""
    if any(s["id"] == text for s in services):
        return text
    named = [s for s in services if s["name"] == text]
    if len(named) == 1:
        return str(named[0]["id"])
    if not named:
        raise ApiError(
            404, f"no service of this robot has the id or name {text!r} (`sdfr services`)"
        )
    ids = ", ".join(f"{s['id']} ({s['type']})" for s in named)
    raise ApiError(
        409, f"{len(named)} services of this robot are named {text!r}: {ids}; give the id"
    )


def _unpublish(client: Client, args: argparse.Namespace) -> Result:
    sid = service_id(client.services(), args.service)
    client.request("DELETE", service_path(sid))
    return None, "", 0


def _matched(answer: dict[str, Any]) -> bool:
    return any(r["services"] for r in answer["neighbors"])


def _search(client: Client, args: argparse.Namespace) -> Result:
    filtered = bool(args.type or args.attr)
    # No filter: every service of every reachable robot (the API's search wants a criterion).
    path = search_path(args.type, dict(args.attr)) if filtered else neighbors_path(False)
    deadline = time.monotonic() + (args.wait or 0)
    while True:
        try:
            answer = client.request("GET", path)
        except ApiError as exc:  # with --wait, sdfrd may be starting still: ask again
            if exc.status != 0 or deadline <= time.monotonic():
                raise
            time.sleep(WAIT_POLL)
            continue
        left = deadline - time.monotonic()
        if _matched(answer) or left <= 0:
            break
        time.sleep(min(WAIT_POLL, left))
    status = 0 if _matched(answer) else 1
    if args.parsable:
        return answer, parsable(answer), status
    return answer, _show_matches(answer, filtered), status


def _show_matches(answer: dict[str, Any], filtered: bool) -> str:
    rows = [
        (
            r["robot_id"],
            r["address"] or "-",
            s["id"],
            s["name"],
            s["type"],
            s["url"],
            attrs_text(s.get("attributes")),
        )
        for r in answer["neighbors"]
        for s in r["services"]
    ]
    if not rows:
        return f"no reachable robot offers {'a matching' if filtered else 'any'} service"
    return table(["ROBOT", "ADDRESS", "ID", "NAME", "TYPE", "URL", "ATTRIBUTES"], rows)


def _get(path: str, show: Callable[[dict[str, Any]], str]) -> Command:
    def run(client: Client, args: argparse.Namespace) -> Result:
        answer = client.request("GET", path)
        return answer, show(answer), 0

    return run


def _health(client: Client, args: argparse.Namespace) -> Result:
    answer = client.health()
    return answer, show_health(answer), 1 if answer.get("status") == "degraded" else 0


COMMANDS: dict[str, Command] = {
    "neighbors": _neighbors,
    "publish": _publish,
    "unpublish": _unpublish,
    "renew": _renew,
    "search": _search,
    "history": _get("/history", show_history),
    "self": _get("/self", show_self),
    "services": _get("/services", show_services),
    "health": _health,
}


def hold(client: Client, args: argparse.Namespace) -> int:
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


def _known_names(client: Client) -> ChangeLines:
    """Change lines that know the names of the services in the history map and of this
    robot's, for the changes that name only ids (a service removed)."""
    lines = ChangeLines()
    lines.learn_robots(client.request("GET", "/history")["robots"])
    lines.learn(None, client.request("GET", "/services")["services"])
    return lines


def stream(client: Client, args: argparse.Namespace) -> int:
    """`sdfr events` and `sdfr neighbors --watch`: print changes until interrupted;
    `sdfr events --once`: the changes kept, then exit."""
    as_json = args.json
    if args.command == "neighbors":
        kinds: list[str] = ["robot"]
        # The stream first, from the newest id, so that no change falls between the two.
        since: int | None = client.events(since=None)["last_id"]
        lines = _known_names(client)
        answer = client.request("GET", neighbors_path(args.all))
        if as_json:
            print(json.dumps({"event": "snapshot", **answer}, ensure_ascii=False), flush=True)
        else:
            print(show_neighbors(answer), flush=True)
    else:
        kinds = args.event or []
        since = args.since
        lines = _known_names(client)
    if args.command == "events" and args.once:
        after = since or 0
        while page := client.events(after, kinds)["events"]:
            for change in page:
                print(
                    json.dumps(change.data, ensure_ascii=False) if as_json else lines.line(change)
                )
            after = page[-1].id
        return 0
    for change in client.watch(kinds, since):
        _print(change, lines, as_json)
    return 0


def _print(change: Change, lines: ChangeLines, as_json: bool) -> None:
    print(
        json.dumps(change.data, ensure_ascii=False) if as_json else lines.line(change), flush=True
    )
