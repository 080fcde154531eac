"""What the side-by-side bench's peer nodes share (`bench.zc_node`, `bench.zenoh_node`): the
command line, the event log and the churn.

A node runs inside a robot's namespace and does SDfR's job with another system.  From
`--start-at` it publishes `--publishers` services at once; from `--churn-at` to
`--churn-until` they churn exactly as `bench.paper_load` reads the paper (an unpublish every
0-5 s, its publisher publishing again, under a fresh id, 10 s later), drawn from the same
seeded sequence whatever the system, so that every system carries the same load.  SIGUSR1
publishes one more service (``extra-<n>``), SIGUSR2 unpublishes the oldest, SIGTERM leaves
gracefully, SIGKILL is a silent death.  Every publish, unpublish, leave and change of what is
listed is a JSON line in `--events` (the format of `bench.paper_load`), written at once.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import signal
import time
from typing import IO, Any


def arguments(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description,
                                formatter_class=argparse.RawTextHelpFormatter)  # fmt: skip
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
    return p


def attributes(robot: str, index: int) -> dict[str, str]:
    """Publisher `index`'s attributes (what SDfR's bench load publishes with each service)."""
    return {
        "name": f"publisher-{index}",
        "type": f"bench.kind{index % 7}",
        "url": f"http://{robot}.local:{9000 + index}/",
        "index": str(index),
        "rate": str(10 + index % 5),
        "frame": f"{robot}/base_link",
    }


class PeerNode:
    """The churn and the event log; a system's node adds `register`, `unregister`, `leave`
    and what it lists (`seen` / `gone`)."""

    def __init__(self, args: argparse.Namespace, events: IO[str]) -> None:
        self.args = args
        self.robot: str = args.robot
        self.events = events
        # (The same sequence for every system: python-zeroconf's node drew it first.)
        self.rng = random.Random(f"zc:{args.seed}:{self.robot}")
        self.mine: dict[str, Any] = {}  # sid -> the system's handle, in publish order
        self.index_of: dict[str, int] = {}
        self.listed: set[tuple[str, str]] = set()
        self.tasks: set[asyncio.Task[Any]] = set()
        self.extra = 0
        self.done = asyncio.Event()

    # -- what a system provides -------------------------------------------------------------

    async def register(self, index: int, sid: str) -> Any:
        """Publish service `sid` (publisher `index`); its handle for `unregister`."""
        raise NotImplementedError

    async def unregister(self, handle: Any) -> None:
        raise NotImplementedError

    async def leave(self) -> None:
        """Leave gracefully (then `left`)."""
        raise NotImplementedError

    # -- shared ------------------------------------------------------------------------------

    def log(self, **event: object) -> None:
        self.events.write(json.dumps({"t": time.time(), **event}, separators=(",", ":")) + "\n")

    def seen(self, who: tuple[str, str]) -> None:
        if who not in self.listed:
            self.listed.add(who)
            self.log(op="seen", at=self.robot, robot=who[0], sid=who[1])

    def gone(self, who: tuple[str, str]) -> None:
        if who in self.listed:
            self.listed.discard(who)
            self.log(op="gone", at=self.robot, robot=who[0], sid=who[1])

    def left(self, ms: float) -> None:
        self.log(op="leave", robot=self.robot, ms=round(ms, 3))
        self.done.set()

    async def publish(self, index: int) -> None:
        sid = f"p{index}x{self.rng.randrange(16**8):08x}"
        self.index_of[sid] = index
        asked, t0 = time.time(), time.perf_counter()
        self.mine[sid] = await self.register(index, sid)
        ms = round((time.perf_counter() - t0) * 1000, 3)
        self.log(op="publish", robot=self.robot, sid=sid, ms=ms, asked=asked)

    async def unpublish(self, sid: str) -> None:
        handle = self.mine.pop(sid)
        asked, t0 = time.time(), time.perf_counter()
        await self.unregister(handle)
        ms = round((time.perf_counter() - t0) * 1000, 3)
        self.log(op="unpublish", robot=self.robot, sid=sid, ms=ms, asked=asked)

    def spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

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

    async def serve(self) -> None:
        """Signals, then at `--start-at` every publisher at once, then the churn, until a
        graceful leave."""
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGUSR1, lambda: self.spawn(self.add_extra()))
        loop.add_signal_handler(signal.SIGUSR2, lambda: self.spawn(self.drop_oldest()))
        loop.add_signal_handler(signal.SIGTERM, lambda: self.spawn(self.leave()))
        await asyncio.sleep(max(0.0, self.args.start_at - time.time()))
        await asyncio.gather(*(self.publish(i) for i in range(self.args.publishers)))
        self.spawn(self.churn())
        await self.done.wait()
