"""A robot of the side-by-side bench done with Zenoh (eclipse-zenoh, peer mode) instead of SDfR.

Run inside a robot's namespace, with Zenoh's defaults for a peer: multicast scouting on
224.0.0.224:7446, gossip on, sessions over TCP (accepted on port 7447 of the robot's address,
pinned so that captures can count them; `--scout-port` and `--listen-port` let a second
Zenoh fleet run apart in the same lab).  Each service is a liveliness token,
``sdfrbench/<robot>/<sid>`` (Zenoh's own presence: the token goes when it is undeclared, or
when its session is lost, after the transport's lease, 10 s by default); its attributes are
answered by the robot's queryable ``sdfrbench/<robot>/*/attrs``.  A service of another robot
is *listed* once its token is seen (a liveliness subscriber, with history) and its attributes
are fetched (a get), as SDfR lists a service with its attributes; it is gone when its token
is.  A get that found nothing is tried again as `bench.zc_node` retries a resolution: after
1 s, then twice as long each time up to 30 s, for as long as the token is there.

`--lease-ms` (Zenoh's ``transport/link/tx/lease``, with its ``keep_alive`` of 4 a lease) is
the knob for liveness; the bench labels any run that sets it.  Its command line, churn,
signals and event log are `bench.peer_node`'s.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
import time
from typing import Any

import zenoh

from bench.peer_node import PeerNode, arguments, attributes

ROOT = "sdfrbench"
SCOUT_GROUP = "224.0.0.224"  # Zenoh's multicast scouting group (its port: --scout-port)
GET_TIMEOUT_S = 3.0
RETRY_FIRST_S = 1.0
RETRY_MAX_S = 30.0


def owner(key: str) -> tuple[str, str] | None:
    """(robot, service id) of a token of this bench, else None."""
    parts = key.split("/")
    return (parts[1], parts[2]) if len(parts) == 3 and parts[0] == ROOT else None


class Node(PeerNode):
    def __init__(self, args: Any, events: Any) -> None:
        super().__init__(args, events)
        self.session: zenoh.Session
        self.loop: asyncio.AbstractEventLoop
        self.present: set[tuple[str, str]] = set()
        self.fetching: dict[tuple[str, str], asyncio.Event] = {}
        self.attrs: dict[str, dict[str, str]] = {}  # sid -> its attributes

    def config(self) -> zenoh.Config:
        conf: zenoh.Config = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        # Its port pinned (Zenoh's own default is any free one) so that captures can count it.
        conf.insert_json5(
            "listen/endpoints", json.dumps([f"tcp/{self.args.ip}:{self.args.listen_port}"])
        )
        conf.insert_json5(
            "scouting/multicast/address", json.dumps(f"{SCOUT_GROUP}:{self.args.scout_port}")
        )
        if self.args.lease_ms is not None:
            conf.insert_json5("transport/link/tx/lease", str(self.args.lease_ms))
        return conf

    async def register(self, index: int, sid: str) -> Any:
        self.attrs[sid] = attributes(self.robot, index)  # (answered from now on)
        return sid, self.session.liveliness().declare_token(f"{ROOT}/{self.robot}/{sid}")

    async def unregister(self, handle: Any) -> None:
        sid, token = handle
        token.undeclare()
        self.attrs.pop(sid, None)

    async def leave(self) -> None:
        t0 = time.perf_counter()
        for sid in list(self.mine):
            await self.unregister(self.mine.pop(sid))
        self.left((time.perf_counter() - t0) * 1000)

    # -- what it lists: Zenoh's threads hand over to the loop --------------------------------

    def on_token(self, sample: zenoh.Sample) -> None:
        who = owner(str(sample.key_expr))
        if who is None or who[0] == self.robot:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        self.loop.call_soon_threadsafe(self.token, who, alive)

    def token(self, who: tuple[str, str], alive: bool) -> None:
        poke = self.fetching.get(who)
        if not alive:
            self.present.discard(who)
            self.gone(who)
            if poke is not None:
                poke.set()
            return
        self.present.add(who)
        if who not in self.listed and poke is None:
            self.fetching[who] = asyncio.Event()
            self.spawn(self.fetch(who))

    async def fetch(self, who: tuple[str, str]) -> None:
        """Get `who`'s attributes until they come or its token goes."""
        poke = self.fetching[who]
        wait = RETRY_FIRST_S
        try:
            while who in self.present and who not in self.listed:
                poke.clear()
                got = await self.loop.run_in_executor(None, self.get, who)
                if got and who in self.present:
                    self.seen(who)
                    return
                print(f"{time.time():.3f} {self.robot}: no attributes of {who}; again in "
                      f"{wait:.1f} s", file=sys.stderr, flush=True)  # fmt: skip
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(poke.wait(), wait)
                wait = min(2 * wait, RETRY_MAX_S)
        finally:
            del self.fetching[who]

    def get(self, who: tuple[str, str]) -> dict[str, str] | None:
        robot, sid = who
        for reply in self.session.get(f"{ROOT}/{robot}/{sid}/attrs", timeout=GET_TIMEOUT_S):
            if reply.ok is not None:
                found: dict[str, str] = json.loads(reply.ok.payload.to_string())
                return found
        return None

    def on_query(self, query: zenoh.Query) -> None:
        parts = str(query.key_expr).split("/")
        sid = parts[2] if len(parts) == 4 else ""
        attrs = self.attrs.get(sid)
        if attrs is not None:
            query.reply(f"{ROOT}/{self.robot}/{sid}/attrs", json.dumps(attrs))

    async def run(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.session = zenoh.open(self.config())
        queryable = self.session.declare_queryable(f"{ROOT}/{self.robot}/*/attrs", self.on_query)
        watcher = self.session.liveliness().declare_subscriber(
            f"{ROOT}/**", self.on_token, history=True
        )
        await self.serve()
        # (eclipse-zenoh's stubs leave these untyped)
        watcher.undeclare()  # type: ignore[no-untyped-call]
        queryable.undeclare()  # type: ignore[no-untyped-call]
        self.session.close()  # type: ignore[no-untyped-call]


def main(argv: list[str] | None = None) -> int:
    p = arguments(__doc__ or "")
    p.add_argument(
        "--lease-ms",
        type=int,
        default=None,
        help="Zenoh's transport lease (default: Zenoh's own, 10000)",
    )
    p.add_argument(
        "--scout-port",
        type=int,
        default=7446,
        help="multicast scouting's UDP port (Zenoh's default: 7446)",
    )
    p.add_argument("--listen-port", type=int, default=7447,
                   help="the TCP port its sessions are accepted on (Zenoh's default: any free "
                        "one; pinned so captures count it)")  # fmt: skip
    args = p.parse_args(argv)
    with open(args.events, "w", buffering=1) as events:
        asyncio.run(Node(args, events).run())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
