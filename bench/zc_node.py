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

Its command line, churn, signals and event log are `bench.peer_node`'s.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import random
import socket
import sys
import time
from typing import IO, Any

from zeroconf import IPVersion, ServiceStateChange, Zeroconf
from zeroconf.asyncio import AsyncServiceBrowser, AsyncServiceInfo, AsyncZeroconf

from bench.peer_node import PeerNode, arguments, attributes

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


class Node(PeerNode):
    def __init__(self, args: argparse.Namespace, events: IO[str]) -> None:
        super().__init__(args, events)
        # Made in the running loop (`run`), which python-zeroconf then uses.
        self.aiozc: AsyncZeroconf
        #: What the browser says is there now (a resolution must not bring back what it
        #: has since said is gone).
        self.present: set[tuple[str, str]] = set()
        #: The services being resolved, each with what wakes its resolver up early (the
        #: browser reported a change of the service, or its removal).
        self.resolving: dict[tuple[str, str], asyncio.Event] = {}
        #: The resolvers' jitter (apart from `rng`, so that the churn stays the same).
        self.jitter = random.Random(f"zc-retry:{args.seed}:{self.robot}")

    def info(self, index: int, sid: str) -> AsyncServiceInfo:
        return AsyncServiceInfo(
            TYPE,
            instance(self.robot, sid),
            port=9000 + index,
            properties=attributes(self.robot, index),
            server=f"{self.robot}.local.",
            addresses=[socket.inet_aton(self.args.ip)],
        )

    async def register(self, index: int, sid: str) -> AsyncServiceInfo:
        info = self.info(index, sid)
        # The defaults a user gets: probe for a conflict first, then announce.
        await (await self.aiozc.async_register_service(info))
        return info

    async def unregister(self, handle: Any) -> None:
        await (await self.aiozc.async_unregister_service(handle))

    def on_change(
        self, zeroconf: Zeroconf, service_type: str, name: str, state_change: ServiceStateChange
    ) -> None:
        who = owner(name)
        if who is None or who[0] == self.robot:
            return
        poke = self.resolving.get(who)
        if state_change is ServiceStateChange.Removed:
            self.present.discard(who)
            self.gone(who)
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
                    if who in self.present:
                        self.seen(who)
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

    async def leave(self) -> None:
        t0 = time.perf_counter()
        await self.aiozc.async_unregister_all_services()
        self.left((time.perf_counter() - t0) * 1000)

    async def run(self) -> None:
        self.aiozc = AsyncZeroconf(interfaces=[self.args.ip], ip_version=IPVersion.V4Only)
        browser = AsyncServiceBrowser(self.aiozc.zeroconf, TYPE, handlers=[self.on_change])
        await self.serve()
        await browser.async_cancel()
        await self.aiozc.async_close()


def main(argv: list[str] | None = None) -> int:
    args = arguments(__doc__ or "").parse_args(argv)
    with open(args.events, "w", buffering=1) as events:
        asyncio.run(Node(args, events).run())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
