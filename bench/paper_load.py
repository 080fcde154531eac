"""The paper's per-robot load (its section 6), as `make bench-paper` reads it, against one sdfrd.

Run inside a robot's namespace, one per robot, all started for the same wall-clock instant
(`--start-at`).  Each robot has 100 simulated services: `--publishers` publishers and the
rest consumers.  How the paper's delays are read (its text: new service providers "try to
publish with a delay time of 10 seconds"; "each of the already published service providers
could be unpublished with a random delay between 5 seconds"):

* **publish**: a publisher publishes its service 10 s (`--publish-delay`) after the load
  starts, and again 10 s after each time it was unpublished.  Every publish is a new
  registration with a fresh id (the paper's "new service providers"); the service itself
  (name, type, url, attributes) is the publisher's own, the same each time.
* **unpublish**: on each robot a scheduler waits a random delay drawn uniformly from 0-5 s
  (`--unpublish-max`), then has one of the publishers whose service is published, chosen
  uniformly, unpublish it; and again.  So a robot unpublishes one service every 2.5 s on
  average and, once its publishers are up, publishes one every 2.5 s: 0.8 changes a second,
  whatever the share of publishers, and about 4 of them are waiting their 10 s at any time.
* **consumers**: each is a thread asking for the neighbour list (`GET /neighbors`) as fast
  as it can: the next request the moment the answer is in.

Requests go over plain HTTP/1.1 keep-alive connections to the API's TCP address, one per
thread (`bench.load.Worker`); a latency is the time from sending the request to having the
whole answer.  Besides the paper's threads a *watcher* reads the neighbour list every
`--watch-interval` s (or, with `--watch-events`, follows the robot's own notifications,
`GET /events`) and notes when each (robot, service) appears and goes: with the
publishers' own notes (`--events`, JSON lines, wall-clock times) it tells how long a change
took to be seen on the other robots.  The summary is one JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import IO, Any

from bench.load import Worker, merge, summary
from sdfr.client import Client, calls
from sdfr.client.calls import new_service_id


@dataclass(frozen=True, slots=True)
class Plan:
    """What one robot's load does; the defaults are the paper's."""

    robot: str
    publishers: int = 70
    consumers: int = 30
    duration: float = 300.0
    publish_delay: float = 10.0
    unpublish_max: float = 5.0
    watch_interval: float = 0.05
    #: The watcher follows GET /events (the robot's own notifications) instead of reading the
    #: neighbour list every `watch_interval`.
    watch_events: bool = False
    seed: int = 0
    #: Seconds before a publisher's first publish (None: `publish_delay`, the paper's).
    first_delay: float | None = None
    #: Wall-clock times between which services churn (None: the whole run).  Outside them
    #: every publisher publishes once and keeps its service.
    churn_at: float | None = None
    churn_until: float | None = None

    def churning(self, t: float) -> bool:
        return (self.churn_at is None or t >= self.churn_at) and (
            self.churn_until is None or t < self.churn_until
        )


def publish_call(robot: str, index: int, sid: str) -> calls.Call[calls.PublishedJson]:
    """Publisher `index`'s service on `robot`, under id `sid`: the same every time it
    publishes, apart from the id."""
    return calls.publish_service(
        f"publisher-{index}",
        f"bench.kind{index % 7}",
        f"http://{robot}.local:{9000 + index}/",
        {"index": index, "rate": 10 + index % 5, "frame": f"{robot}/base_link"},
        service_id=sid,
    )


@dataclass
class Board:
    """Which publishers have their service up, shared by them and the unpublish scheduler."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    published: set[int] = field(default_factory=set)
    orders: dict[int, threading.Event] = field(default_factory=dict)

    def pick(self, rng: random.Random) -> int | None:
        """One published publisher, uniformly, told to unpublish (None: none is up)."""
        with self.lock:
            if not self.published:
                return None
            index = rng.choice(sorted(self.published))
            self.published.discard(index)
            self.orders[index].set()
            return index


class Log:
    """Timestamped JSON lines, written by many threads."""

    def __init__(self, out: IO[str] | None) -> None:
        self.out = out
        self.lock = threading.Lock()

    def write(self, **event: object) -> None:
        if self.out is None:
            return
        line = json.dumps(event, separators=(",", ":"))
        with self.lock:
            self.out.write(line + "\n")


def publisher(
    w: Worker,
    plan: Plan,
    index: int,
    board: Board,
    stop: threading.Event,
    out: dict[str, list[float]],
    log: Log,
) -> None:
    order = board.orders[index]
    delay = plan.publish_delay if plan.first_delay is None else plan.first_delay

    def timed(op: str, method: str, path: str, body: bytes | None, ok: int, sid: str) -> bool:
        """One request of the load, timed, logged as `op`; False when it failed."""
        asked = time.time()
        status, _, dt = w.call(method, path, body)
        if status != ok:
            out["errors"].append(float(status))
            return False
        out[op].append(dt)
        ms = round(dt * 1e3, 3)
        log.write(t=time.time(), op=op, robot=plan.robot, sid=sid, ms=ms, asked=asked)
        return True

    first = True
    while not stop.wait(delay):
        if not first and not plan.churning(time.time()):
            return  # churn is over: a service unpublished now stays so
        first, delay = False, plan.publish_delay
        sid = new_service_id()
        publish = publish_call(plan.robot, index, sid)
        # The id leads, as in the requests the bench's published figures were measured with.
        body = json.dumps({"id": sid, **(publish.body or {})}).encode()
        if not timed("publish", publish.method, publish.path, body, 201, sid):
            return
        with board.lock:
            order.clear()
            board.published.add(index)
        while not order.wait(0.2):
            if stop.is_set():
                return
        if stop.is_set():
            return
        unpublish = calls.unpublish(sid)
        if not timed("unpublish", unpublish.method, unpublish.path, None, 204, sid):
            return


def unpublisher(plan: Plan, board: Board, stop: threading.Event) -> None:
    rng = random.Random(f"unpublish:{plan.seed}:{plan.robot}")
    if plan.churn_at is not None and stop.wait(max(0.0, plan.churn_at - time.time())):
        return
    while not stop.wait(rng.uniform(0.0, plan.unpublish_max)):
        if plan.churn_until is not None and time.time() >= plan.churn_until:
            return
        board.pick(rng)


def consumer(w: Worker, stop: threading.Event, out: dict[str, list[float]]) -> None:
    while not stop.is_set():
        status, _, dt = w.call("GET", "/neighbors")
        if status != 200:
            out["errors"].append(float(status))
            return
        out["neighbors"].append(dt)


def listed(body: bytes) -> set[tuple[str, str]]:
    """(robot, service id) of every service of every reachable neighbour in an answer."""
    return listed_in(json.loads(body)["neighbors"])


def listed_in(neighbors: Iterable[Mapping[str, Any]]) -> set[tuple[str, str]]:
    """(robot, service id) of every service of every reachable neighbour."""
    return {
        (str(n["robot_id"]), str(s["id"]))
        for n in neighbors
        if n.get("reachable", True)
        for s in n["services"]
    }


def watcher(w: Worker, plan: Plan, stop: threading.Event, log: Log, reads: list[int]) -> None:
    seen: set[tuple[str, str]] = set()
    while not stop.is_set():
        status, body, _ = w.call("GET", "/neighbors")
        t = time.time()
        if status == 200:
            now = listed(body)
            for robot, sid in sorted(now - seen):
                log.write(t=t, op="seen", at=plan.robot, robot=robot, sid=sid)
            for robot, sid in sorted(seen - now):
                log.write(t=t, op="gone", at=plan.robot, robot=robot, sid=sid)
            seen = now
            reads[0] += 1
        stop.wait(plan.watch_interval)


def events_watcher(api: str, plan: Plan, log: Log, reads: list[int]) -> None:
    """The watcher on the robot's own notifications: GET /events (robot changes), a change
    noted when its event arrives.  The whole list is read when the stream (re)opens, on a
    resync, and when an event left a robot's services out (too many to carry: the event says
    `services_truncated`); that read's changes are noted at the read's time."""
    client = Client(api, timeout=30.0)
    reader = Client(api, timeout=30.0)
    seen: set[tuple[str, str]] = set()

    def note(now: set[tuple[str, str]], t: float) -> None:
        for robot, sid in sorted(now - seen):
            log.write(t=t, op="seen", at=plan.robot, robot=robot, sid=sid)
        for robot, sid in sorted(seen - now):
            log.write(t=t, op="gone", at=plan.robot, robot=robot, sid=sid)
        seen.clear()
        seen.update(now)

    def read_all() -> None:
        note(listed_in(reader.neighbors()), time.time())
        reads[0] += 1

    for change in client.watch(["robot", "resync"], on_open=read_all):
        t = time.time()
        now = after(seen, change.event, str(change.robot_id), change.data)
        if now is None:
            read_all()
        else:
            note(now, t)


def after(
    seen: set[tuple[str, str]], event: str, robot: str, data: Mapping[str, Any]
) -> set[tuple[str, str]] | None:
    """What is listed after this event of GET /events, from what was before; None when the
    event does not say (a resync, or a robot's services left out: the list must be read)."""
    if event == "resync" or any(k.endswith("_truncated") for k in data):
        return None
    if event == "robot.appeared":
        return {x for x in seen if x[0] != robot} | {
            (robot, str(s["id"])) for s in data.get("services", [])
        }
    if event == "robot.services":
        removed = {(robot, str(sid)) for sid in data.get("removed", [])}
        return (seen - removed) | {(robot, str(s["id"])) for s in data.get("added", [])}
    if event in ("robot.left", "robot.unreachable", "robot.forgotten"):
        return {x for x in seen if x[0] != robot}
    return set(seen)


def run(
    plan: Plan, host: str, port: int, log: Log, stop: threading.Event | None = None
) -> dict[str, Any]:
    """Run the load for `plan.duration` seconds (or until `stop` is set); the summary."""
    stop = stop or threading.Event()
    board = Board(orders={i: threading.Event() for i in range(plan.publishers)})
    per_thread: list[dict[str, list[float]]] = []
    threads: list[threading.Thread] = []
    reads = [0]

    def spawn(target: Callable[..., None], *args: Any) -> None:
        threads.append(threading.Thread(target=target, args=args, daemon=True))

    for i in range(plan.publishers):
        out: dict[str, list[float]] = {"publish": [], "unpublish": [], "errors": []}
        per_thread.append(out)
        spawn(publisher, Worker(host, port), plan, i, board, stop, out, log)
    for _ in range(plan.consumers):
        out = {"neighbors": [], "errors": []}
        per_thread.append(out)
        spawn(consumer, Worker(host, port), stop, out)
    spawn(unpublisher, plan, board, stop)
    if plan.watch_interval > 0 and not plan.watch_events:
        spawn(watcher, Worker(host, port), plan, stop, log, reads)
    began = time.time()
    for t in threads:
        t.start()
    if plan.watch_events:  # (blocked on its stream: not joined; ends with the process)
        api = f"{host}:{port}"
        threading.Thread(target=events_watcher, args=(api, plan, log, reads), daemon=True).start()
    stop.wait(plan.duration)
    stop.set()
    ended = time.time()
    for t in threads:
        t.join(timeout=30)
    merged, errors = merge(per_thread)
    result: dict[str, Any] = {k: summary(v) for k, v in merged.items()}
    result.update(
        robot=plan.robot,
        began=began,
        ended=ended,
        errors=len(errors),
        error_statuses=sorted({int(e) for e in errors}),
        requests_per_s=round(sum(len(v) for v in merged.values()) / (ended - began), 1),
        watcher_reads=reads[0],
        still_running=sum(t.is_alive() for t in threads),
    )
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--api", default="127.0.0.1:8700")
    p.add_argument("--robot", required=True, help="this robot's id (names its services)")
    p.add_argument("--publishers", type=int, default=70)
    p.add_argument("--consumers", type=int, default=30)
    p.add_argument("--duration", type=float, default=300.0)
    p.add_argument("--publish-delay", type=float, default=10.0)
    p.add_argument("--unpublish-max", type=float, default=5.0)
    p.add_argument("--watch-interval", type=float, default=0.05, help="0: no watcher")
    p.add_argument(
        "--watch-events",
        action="store_true",
        help="the watcher follows GET /events instead of reading the neighbour list",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--first-delay", type=float, help="before the first publish (default 10 s)")
    p.add_argument("--churn-at", type=float, help="wall-clock time churn starts (default: start)")
    p.add_argument("--churn-until", type=float, help="wall-clock time churn stops")
    p.add_argument("--start-at", type=float, help="wall-clock time (UNIX s) to begin at")
    p.add_argument("--events", help="JSON lines of publishes, unpublishes and what was seen")
    args = p.parse_args(argv)
    plan = Plan(
        robot=args.robot,
        publishers=args.publishers,
        consumers=args.consumers,
        duration=args.duration,
        publish_delay=args.publish_delay,
        unpublish_max=args.unpublish_max,
        watch_interval=args.watch_interval,
        watch_events=args.watch_events,
        seed=args.seed,
        first_delay=args.first_delay,
        churn_at=args.churn_at,
        churn_until=args.churn_until,
    )
    host, _, port = args.api.rpartition(":")
    stop = threading.Event()
    # SIGTERM ends the run early (a watcher that runs for as long as it is needed).
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if args.start_at is not None:
        stop.wait(max(0.0, args.start_at - time.time()))
    # Line-buffered: every event is in the file at once, whatever ends this process.
    with open(args.events, "w", buffering=1) if args.events else nullcontext() as events:
        result = run(plan, host, int(port), Log(events), stop)
    json.dump(result, sys.stdout)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
