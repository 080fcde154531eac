"""A robot of the side-by-side bench done with python-zeroconf (mDNS / DNS-SD) instead of SDfR.

Run inside a robot's namespace.  It registers the robot's services (one DNS-SD instance
each, type ``_sdfrbench._tcp.local.``, its attributes in TXT) and browses that type: a
service of another robot is *listed* once it is resolved (SRV and TXT known, as SDfR lists
a service with its attributes).  A resolution that timed out is tried again, as a careful user
of python-zeroconf would, for as long as the browser says the service is there: after 1 s, then
twice as long each time up to 30 s, and at once when the browser reports an update of the
service (records of it arrived since).  From `--churn-at` to `--churn-until` the services churn
exactly as `bench.paper_load` reads the paper (publish 10 s after an unpublish, one unpublish
every 0-5 s, fresh names), so both systems carry the same load.

Signals: SIGUSR1 registers one more service (``extra-<n>``); SIGUSR2 unregisters the oldest
of the robot's services; SIGTERM leaves gracefully (goodbye packets, then exit); SIGKILL is a
silent death.  Every publish, unpublish and change of what is listed is a JSON line in
`--events` (the format of `bench.paper_load`), written at once.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import random
import signal
import socket
import sys
import time
from typing import IO, Any

from zeroconf import IPVersion, ServiceStateChange, Zeroconf
from zeroconf.asyncio import AsyncServiceBrowser, AsyncServiceInfo, AsyncZeroconf

TYPE = "_sdfrbench._tcp.local."
RESOLVE_TIMEOUT_MS = 3000
#: After a resolution timed out: the first wait before the next one, and the longest.
RETRY_FIRST_S = 1.0
RETRY_MAX_S = 30.0


def instance(robot: str, sid: str) -> str:
    return f"{robot}--{sid}.{TYPE}"


def owner(name: str) -> tuple[str, str] | None:
    """(robot, service id) of an instance name of this bench, else None."""
    if not name.endswith("." + TYPE):
        return None
    robot, sep, sid = name[: -len(TYPE) - 1].partition("--")
    return (robot, sid) if sep else None


class Node:
    def __init__(self, args: argparse.Namespace, events: IO[str]) -> None:
        self.args = args
        self.robot: str = args.robot
        self.events = events
        self.rng = random.Random(f"zc:{args.seed}:{self.robot}")
        # Made in the running loop (`run`), which python-zeroconf then uses.
        self.aiozc: AsyncZeroconf
        self.mine: dict[str, AsyncServiceInfo] = {}  # sid -> info, in publish order
        self.index_of: dict[str, int] = {}
        self.listed: set[tuple[str, str]] = set()
        #: What the browser says is there now (a resolution must not bring back what it
        #: has since said is gone).
        self.present: set[tuple[str, str]] = set()
        #: The services being resolved, each with what wakes its resolver up early (the
        #: browser reported a change of the service, or its removal).
        self.resolving: dict[tuple[str, str], asyncio.Event] = {}
        #: The resolvers' jitter (apart from `rng`, so that the churn stays the same).
        self.jitter = random.Random(f"zc-retry:{args.seed}:{self.robot}")
        self.tasks: set[asyncio.Task[Any]] = set()
        self.extra = 0
        self.done = asyncio.Event()

    def log(self, **event: object) -> None:
        self.events.write(json.dumps({"t": time.time(), **event}, separators=(",", ":")) + "\n")

    def info(self, index: int, sid: str) -> AsyncServiceInfo:
        return AsyncServiceInfo(
            TYPE,
            instance(self.robot, sid),
            port=9000 + index,
            properties={
                "name": f"publisher-{index}",
                "type": f"bench.kind{index % 7}",
                "url": f"http://{self.robot}.local:{9000 + index}/",
                "index": str(index),
                "rate": str(10 + index % 5),
                "frame": f"{self.robot}/base_link",
            },
            server=f"{self.robot}.local.",
            addresses=[socket.inet_aton(self.args.ip)],
        )

    async def publish(self, index: int) -> None:
        sid = f"p{index}x{self.rng.randrange(16**8):08x}"
        info = self.info(index, sid)
        self.mine[sid] = info
        self.index_of[sid] = index
        asked, t0 = time.time(), time.perf_counter()
        # The defaults a user gets: probe for a conflict first, then announce.
        await (await self.aiozc.async_register_service(info))
        ms = round((time.perf_counter() - t0) * 1000, 3)
        self.log(op="publish", robot=self.robot, sid=sid, ms=ms, asked=asked)

    async def unpublish(self, sid: str) -> None:
        info = self.mine.pop(sid)
        asked, t0 = time.time(), time.perf_counter()
        await (await self.aiozc.async_unregister_service(info))
        ms = round((time.perf_counter() - t0) * 1000, 3)
        self.log(op="unpublish", robot=self.robot, sid=sid, ms=ms, asked=asked)

    def spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    def on_change(
        self, zeroconf: Zeroconf, service_type: str, name: str, state_change: ServiceStateChange
    ) -> None:
        who = owner(name)
        if who is None or who[0] == self.robot:
            return
        poke = self.resolving.get(who)
        if state_change is ServiceStateChange.Removed:
            self.present.discard(who)
            if who in self.listed:
                self.listed.discard(who)
                self.log(op="gone", at=self.robot, robot=who[0], sid=who[1])
            if poke is not None:
                poke.set()  # its resolver stops
            return
        if state_change is ServiceStateChange.Added:
            self.present.add(who)
        if who in self.listed or who not in self.present:
            return
        # Added, or Updated while not resolved yet: resolve it (now, if already trying).
        if poke is not None:
            poke.set()
        else:
            self.resolving[who] = asyncio.Event()
            self.spawn(self.resolve(name, who))

    async def resolve(self, name: str, who: tuple[str, str]) -> None:
        """Resolve `name` until it is resolved or the browser says it is gone."""
        poke = self.resolving[who]
        wait = RETRY_FIRST_S
        tries = 0
        try:
            while who in self.present and who not in self.listed:
                poke.clear()
                tries += 1
                info = AsyncServiceInfo(TYPE, name)
                ok = await info.async_request(self.aiozc.zeroconf, RESOLVE_TIMEOUT_MS)
                if ok and info.properties:
                    if who in self.present and who not in self.listed:
                        self.listed.add(who)
                        self.log(op="seen", at=self.robot, robot=who[0], sid=who[1])
                    return
                pause = wait * self.jitter.uniform(0.8, 1.2)
                print(
                    f"{time.time():.3f} {self.robot}: resolving {name} timed out "
                    f"(try {tries}); again in {pause:.1f} s",
                    file=sys.stderr,
                    flush=True,
                )
                # asyncio.TimeoutError: on 3.10 it is not the builtin TimeoutError
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(poke.wait(), pause)
                wait = min(2 * wait, RETRY_MAX_S)
        finally:
            del self.resolving[who]

    async def churn(self) -> None:
        """Unpublish a published service every 0-5 s; its publisher publishes again 10 s
        later (bench.paper_load's reading of the paper)."""
        a = self.args
        await asyncio.sleep(max(0.0, a.churn_at - time.time()))
        while time.time() < a.churn_until:
            await asyncio.sleep(self.rng.uniform(0.0, a.unpublish_max))
            if time.time() >= a.churn_until or not self.mine:
                continue
            sid = self.rng.choice(sorted(s for s in self.mine if s in self.index_of))
            index = self.index_of.pop(sid)
            await self.unpublish(sid)
            self.spawn(self.again(index))

    async def again(self, index: int) -> None:
        await asyncio.sleep(self.args.publish_delay)
        if time.time() < self.args.churn_until:
            await self.publish(index)

    async def add_extra(self) -> None:
        self.extra += 1
        await self.publish(1000 + self.extra)

    async def drop_oldest(self) -> None:
        if self.mine:
            sid = next(iter(self.mine))
            self.index_of.pop(sid, None)
            await self.unpublish(sid)

    async def leave(self) -> None:
        t0 = time.perf_counter()
        await self.aiozc.async_unregister_all_services()
        self.log(op="leave", robot=self.robot, ms=round((time.perf_counter() - t0) * 1000, 3))
        self.done.set()

    async def run(self) -> None:
        self.aiozc = AsyncZeroconf(interfaces=[self.args.ip], ip_version=IPVersion.V4Only)
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGUSR1, lambda: self.spawn(self.add_extra()))
        loop.add_signal_handler(signal.SIGUSR2, lambda: self.spawn(self.drop_oldest()))
        loop.add_signal_handler(signal.SIGTERM, lambda: self.spawn(self.leave()))
        browser = AsyncServiceBrowser(self.aiozc.zeroconf, TYPE, handlers=[self.on_change])
        await asyncio.sleep(max(0.0, self.args.start_at - time.time()))
        await asyncio.gather(*(self.publish(i) for i in range(self.args.publishers)))
        self.spawn(self.churn())
        await self.done.wait()
        await browser.async_cancel()
        await self.aiozc.async_close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--robot", required=True)
    p.add_argument("--ip", required=True, help="this robot's address (the interface to use)")
    p.add_argument("--publishers", type=int, default=70)
    p.add_argument("--start-at", type=float, default=0.0, help="wall-clock time to publish at")
    p.add_argument("--churn-at", type=float, default=0.0)
    p.add_argument("--churn-until", type=float, default=0.0)
    p.add_argument("--publish-delay", type=float, default=10.0)
    p.add_argument("--unpublish-max", type=float, default=5.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--events", required=True)
    args = p.parse_args(argv)
    with open(args.events, "w", buffering=1) as events:
        asyncio.run(Node(args, events).run())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
