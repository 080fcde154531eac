"""A fleet of protocol cores joined by an in-memory lossy medium, run in virtual time.

Minutes of protocol time take milliseconds: nothing sleeps; the loop jumps
from one event (a delivery or a core's deadline) to the next.

`SimNet` is the medium and its robots (`Node`: a name, an address, a `Core`); `fleet` and
`services` build a fleet at the short test beacon (`BEACON`); `kind_of` and `sent` say what
the robots sent. The protocol's tests and `bench.auth` run on it.
"""

from __future__ import annotations

import heapq
import itertools
import random
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from sdfr import wire
from sdfr.protocol import Addr, Core, CoreConfig
from sdfr.protocol.auth import OPEN, Keyring
from sdfr.records.model import PeerRecord, Service


@dataclass
class Node:
    """One robot on the medium: its protocol core, whether it is on the air, the deadline its
    timer is armed for, and every datagram it sent (time, bytes, destination; None:
    multicast)."""

    name: str
    addr: Addr
    core: Core
    up: bool = True
    armed: float | None = None
    sent: list[tuple[float, bytes, Addr | None]] = field(default_factory=list)


class SimNet:
    """Robots on one broadcast medium with per-pair reachability and loss."""

    def __init__(
        self,
        seed: int = 1,
        *,
        loss: float = 0.0,
        delay: tuple[float, float] = (0.001, 0.004),
        duplicate: float = 0.0,
    ) -> None:
        self.rng = random.Random(seed)
        self.loss = loss
        self.delay = delay
        self.duplicate = duplicate
        self.now = 0.0
        self.nodes: dict[str, Node] = {}
        self.blocked: set[frozenset[str]] = set()
        self.pair_loss: dict[tuple[str, str], float] = {}
        #: Seconds added to every datagram from one robot to another (a robot too busy to
        #: answer in time, as seen by that peer).
        self.pair_delay: dict[tuple[str, str], float] = {}
        self._queue: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = itertools.count()
        self.delivered = 0
        self.dropped = 0
        #: Optional veto on each (sender, receiver, datagram): False drops it.
        self.filter: Callable[[str, str, bytes], bool] | None = None
        #: Observers (an adversary, an invariant checker): every datagram a node is about to
        #: read, with its source, whether the medium or `inject` brings it; every datagram a
        #: node sends, with its destination (None: multicast); and the end of every event
        #: of the loop (a delivery, a timer, a `call_at` action).
        self.on_receive: Callable[[Node, bytes, Addr], None] | None = None
        self.on_send: Callable[[Node, bytes, Addr | None], None] | None = None
        self.after_event: Callable[[], None] | None = None

    # -- building ------------------------------------------------------------------------

    def add(
        self,
        name: str,
        *,
        boot_id: int = 1,
        services: Sequence[Service] = (),
        version: int | None = None,
        start: bool = True,
        keyring: Keyring = OPEN,
        **cfg: object,
    ) -> Node:
        """A robot `name` at the next address 10.1.0.N, its core configured by `cfg`
        (`CoreConfig` fields) and started now unless `start` is False."""
        index = len(self.nodes) + 1
        addr = (f"10.1.0.{index}", 1900)
        config = CoreConfig(fleet=1, robot_id=name, **cfg)  # type: ignore[arg-type]
        core = Core(
            config,
            boot_id=boot_id,
            rng=random.Random(self.rng.random()),
            location=f"http://{addr[0]}:8701/description.json",
            version=version if version is not None else (1 if services else 0),
            services=services,
            keyring=keyring,
        )
        node = Node(name, addr, core)
        self.nodes[name] = node
        if start:
            core.start(self.now)
            self._pump(node)
        return node

    def restart(
        self,
        name: str,
        *,
        boot_id: int,
        graceful: bool = True,
        history: Iterable[PeerRecord] = (),
        **kw: object,
    ) -> Node:
        """A new daemon for the robot `name` at its address; `history`: the peers it had saved
        (`Core.take_dirty`), restored before it starts as the daemon's store does."""
        old = self.nodes[name]
        if graceful:
            old.core.stop(self.now)
            self._pump(old)
        old.up = False
        config = old.core.config
        core = Core(
            config,
            boot_id=boot_id,
            rng=random.Random(self.rng.random()),
            location=old.core.location,
            version=kw.get("version", old.core.version),  # type: ignore[arg-type]
            services=kw.get("services", old.core.services),  # type: ignore[arg-type]
            keyring=old.core.keyring,
        )
        core.restore(history)
        node = Node(name, old.addr, core)
        self.nodes[name] = node
        core.start(self.now)
        self._pump(node)
        return node

    def move(self, name: str, host: str) -> None:
        """The robot's address changes to `host` (its daemon tells the fleet at once)."""
        node = self.nodes[name]
        node.addr = (host, node.addr[1])
        node.core.set_location(f"http://{host}:8701/description.json", self.now)
        self._pump(node)

    def kill(self, name: str) -> None:
        """Silent death: the node stops sending and receiving."""
        self.nodes[name].up = False

    def stop(self, name: str) -> None:
        """A clean stop: the core says goodbye (Byebye), then the node leaves the air."""
        node = self.nodes[name]
        node.core.stop(self.now)
        self._pump(node)
        node.up = False

    def partition(self, *groups: Sequence[str]) -> None:
        self.blocked.clear()
        side = {n: i for i, g in enumerate(groups) for n in g}
        for a, b in itertools.combinations(self.nodes, 2):
            if side.get(a) != side.get(b):
                self.blocked.add(frozenset((a, b)))

    def merge(self) -> None:
        """Undo `partition`: every robot hears every other again."""
        self.blocked.clear()

    def set_services(self, name: str, version: int, services: Sequence[Service]) -> None:
        """The robot's daemon publishes a new set (`version`) now."""
        node = self.nodes[name]
        node.core.set_services(version, services, self.now)
        self._pump(node)

    def inject(self, name: str, data: bytes, src: Addr) -> None:
        """Deliver raw bytes to one node now (malformed input, foreign traffic)."""
        node = self.nodes[name]
        if self.on_receive is not None:
            self.on_receive(node, data, src)
        node.core.receive(data, src, self.now)
        self._pump(node)

    def inject_all(self, data: bytes, src: Addr) -> None:
        """An outsider on the medium multicasts `data` from `src`: every robot gets it now."""
        for name, node in self.nodes.items():
            if node.up:
                self.inject(name, data, src)

    # -- running -------------------------------------------------------------------------

    def run_for(self, seconds: float) -> None:
        """Run the loop `seconds` of virtual time on."""
        self.run_until(self.now + seconds)

    def run_until(self, t_end: float) -> None:
        """Run every event due until virtual time `t_end`, then set the clock there."""
        while self._queue and self._queue[0][0] <= t_end:
            t, _, action = heapq.heappop(self._queue)
            self.now = max(self.now, t)
            action()
            if self.after_event is not None:
                self.after_event()
        self.now = max(self.now, t_end)

    def wait_until(self, pred: Callable[[], bool], timeout: float, step: float = 0.01) -> float:
        """Run until `pred()` holds; return the virtual time it took, or raise."""
        start = self.now
        while not pred():
            if self.now - start > timeout:
                raise AssertionError(f"condition not met within {timeout} s of virtual time")
            self.run_for(step)
        return self.now - start

    def call_at(self, t: float, action: Callable[[], None]) -> None:
        """Run `action` at virtual time `t` (not before now): an adversary's delayed or
        duplicated datagram, say."""
        self._at(max(t, self.now), action)

    # -- views ---------------------------------------------------------------------------

    def sees(self, a: str, b: str) -> bool:
        """Robot `a` holds robot `b` as reachable."""
        peer = self.nodes[a].core.peers.get(b)
        return peer is not None and peer.reachable

    def all_see_all(self, names: Sequence[str] | None = None, with_services: bool = True) -> bool:
        """Each of `names` (default: every robot) holds every other as reachable, with its
        current set of services unless `with_services` is False."""
        names = list(names if names is not None else self.nodes)
        for a in names:
            for b in names:
                if a == b:
                    continue
                peer = self.nodes[a].core.peers.get(b)
                if peer is None or not peer.reachable:
                    return False
                if with_services and peer.services != self.nodes[b].core.services:
                    return False
        return True

    # -- internals -----------------------------------------------------------------------

    def _at(self, t: float, action: Callable[[], None]) -> None:
        heapq.heappush(self._queue, (t, next(self._seq), action))

    def _pump(self, node: Node) -> None:
        """Ship what the node wants to send and re-arm its timer."""
        core = node.core
        for data, dst in core.datagrams_to_send():
            node.sent.append((self.now, data, dst))
            if self.on_send is not None:
                self.on_send(node, data, dst)
            if not node.up and dst is not None:
                continue
            for target in self._targets(node, dst):
                self._transmit(node, target, data)
        deadline = core.next_deadline()
        if deadline is not None and node.up and (node.armed is None or deadline != node.armed):
            node.armed = deadline

            def fire(node: Node = node, when: float = deadline) -> None:
                if node.armed != when or not node.up or self.nodes.get(node.name) is not node:
                    return
                node.armed = None
                node.core.handle_timer(self.now)
                self._pump(node)

            self._at(max(deadline, self.now), fire)

    def _targets(self, node: Node, dst: Addr | None) -> list[Node]:
        if dst is None:
            return [n for n in self.nodes.values() if n is not node]
        return [n for n in self.nodes.values() if n.addr == dst and n is not node]

    def _transmit(self, src: Node, dst: Node, data: bytes) -> None:
        if frozenset((src.name, dst.name)) in self.blocked:
            return
        if self.filter is not None and not self.filter(src.name, dst.name, data):
            self.dropped += 1
            return
        loss = self.pair_loss.get((src.name, dst.name), self.loss)
        copies = 2 if self.rng.random() < self.duplicate else 1
        for _ in range(copies):
            if self.rng.random() < loss:
                self.dropped += 1
                continue
            t = (
                self.now
                + self.rng.uniform(*self.delay)
                + self.pair_delay.get((src.name, dst.name), 0)
            )

            def deliver(dst: Node = dst, data: bytes = data, addr: Addr = src.addr) -> None:
                if not dst.up or self.nodes.get(dst.name) is not dst:
                    return
                self.delivered += 1
                if self.on_receive is not None:
                    self.on_receive(dst, data, addr)
                dst.core.receive(data, addr, self.now)
                self._pump(dst)

            self._at(t, deliver)


def kind_of(data: bytes) -> str:
    """What a datagram is, in either wire form: "alive", "update" (a whole set's part),
    "delta", "byebye", "search", "ping", "fetch", "reply" (to a ping), "response" or "reject"."""
    return kind_of_message(wire.decode(data))


def kind_of_message(msg: wire.Message | wire.Reject) -> str:
    """`kind_of` of a datagram already decoded."""
    if isinstance(msg, wire.Update):
        return "update" if msg.base is None else "delta"
    if isinstance(msg, wire.Discovery):
        if msg.seq is not None:
            return "ping"
        return "fetch" if msg.want is not None and not msg.multicast else "search"
    if isinstance(msg, wire.Response):
        return "reply" if msg.seq is not None else "response"
    return type(msg).__name__.lower()


def sent(
    net: SimNet, name: str, kind: str, since: float = 0.0
) -> list[tuple[float, bytes, Addr | None]]:
    """(time, datagram, destination) of every datagram of `kind` (see `kind_of`) a robot sent
    since `since`."""
    return [(t, d, dst) for t, d, dst in net.nodes[name].sent if t >= since and kind_of(d) == kind]


BEACON = 1.0  # short beacons keep the virtual clock small; every deadline scales with it


def services(robot: str, n: int = 100, tag: str = "") -> list[Service]:
    """`n` services of robot `robot` (ids `<robot>-s<i><tag>`), of seven types."""
    return [
        Service(
            id=f"{robot}-s{i}{tag}",
            name=f"{robot} service {i}",
            type=f"sensor.kind{i % 7}",
            url=f"http://{robot}.local:9000/s{i}",
            attributes={"fps": 30 + i % 5, "frame": f"{robot}/base_link", "ok": i % 2 == 0},
        )
        for i in range(n)
    ]


def fleet(net: SimNet, n: int, n_services: int = 100, **cfg: Any) -> list[str]:
    """Robots r1..rn on `net`, each with `n_services` services, at the short test beacon
    (pinging twice a beacon, unless `cfg` says otherwise)."""
    names = [f"r{i}" for i in range(1, n + 1)]
    defaults: dict[str, Any] = {"beacon_interval": BEACON, "ping_interval": BEACON / 2}
    for name in names:
        net.add(name, services=services(name, n_services), **{**defaults, **cfg})
    return names
