"""An outsider on a SimNet's medium, and the ground truth that judges the robots' views.

The `World` watches a `SimNet` through its hooks (`on_send`, `on_receive`, `after_event`) and
keeps, for every run of every robot's daemon (a `Life`), what the simulator saw: every
datagram it sent (decoded with `sdfr.wire.decode`), every datagram delivered to it and from
where, and the service sets the test gave it.  From that alone, never from a core's private
state, it derives who answered whose ping, and checks each robot's *listed* view (the public
`Core.reachable()` and `Core.view()`) against it:

- I1  a robot is listed reachable by R only if it answered a ping of R (a Response datagram its
      own core sent, carrying a seq R's current run sent in a ping or beacon, reaching R from
      the address that ping went to) within the last miss window: counted from its arrival,
      or, for an answer after R's ping timeout (a busy robot, or one the outsider held
      back), from when R sent the ping;
- I2  a listed robot's boot is that of its run that last answered R (the answer to R's latest
      ping), and its services one of the sets that run was given (or none yet);
- I3  with a fleet key, a datagram the outsider re-sends (a replay, a relay, a copy from a
      forged address, one robot's datagram to another) changes nothing R lists, nor R's
      conflict record; only a datagram's first delivery to its own recipient (a run of the
      robot it was sent to, or any robot for a multicast), from its sender's address, in the
      recipient's current run, may: the medium's own delay, which the outsider may stretch.
      And a listed robot's address is where it really is (a relay cannot move it);
- I4  the bytes a robot's run sent by unicast to an address while that address had not proven
      a round trip (answered one of its pings within `proven_for`) never exceed the bytes that
      run received from that address;
- I5  no robot records a robot-id conflict: no two daemons ever share an id here.

The outsider holds no key.  It captures every datagram any robot sends (multicast and
unicast), and may drop, delay or duplicate datagrams in flight (`Policy`), re-send any
captured one to any robot from any address (`deliver`), and relay what robots send to an
address of its own to a robot and back (`bridge`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from sdfr import wire
from sdfr.protocol import Addr
from sdfr.records.model import PeerRecord, Service
from sdfr.testing.simnet import Node, SimNet
from sdfr.testing.simnet import kind_of_message as kind

OUTSIDER: Addr = ("10.1.0.66", 1900)
VICTIM: Addr = ("10.1.0.77", 1900)
#: Float slack on time comparisons: a deadline equal to the event's time is not yet late.
EPS = 1e-9
INVARIANTS = ("I1", "I2", "I3", "I4", "I5")
#: Narrower forms, for exploring a core that fails the whole ones at once: I1p judges only
#: robots that answered R at least once (not a belief at first sight); I4v only addresses
#: where no robot is (a victim's).
NARROW = ("I1p", "I4v")
#: Findings a core may be known not to meet yet, which `World(known=...)` then lets pass (each
#: should have a test of its own that fails until it is met):
#: - "reused-boot-set": I2 also accepts a set of an earlier run with the same boot id as the
#:   run that answered (a reused boot id: the old set stays listed until the new one arrives);
#: - "keyed-credit": no I4 with a fleet key (the byte credit kept for open fleets only);
#: - "mirror-conflict": the outsider's relay never mirrors a robot's datagrams back to it (an
#:   open robot's challenge of its own id, mirrored, is answered by itself: a false I5).
#: - "late-old-answer": I2 also accepts the run whose answer arrived last (a run's answer to
#:   an older ping, held back past a newer run's answer, is believed: the old boot flaps back).
FINDINGS = ("reused-boot-set", "keyed-credit", "mirror-conflict", "late-old-answer")


class Violation(AssertionError):
    """An invariant does not hold; the message says which, where and when."""


@dataclass
class Capture:
    """A datagram a robot sent, as the outsider recorded it off the air."""

    life: Life
    t: float
    data: bytes
    dst: Addr | None
    src: Addr  # the sender's address when it sent it
    kind: str


@dataclass
class Proof:
    """A robot's answer to one of R's pings, as it reached R."""

    t_recv: float
    t_ping: float
    prover: Life
    src: Addr
    #: When it proves the prover alive: its arrival, or for a late answer, the ping's time.
    alive: float


@dataclass(eq=False)
class Life:
    """One run of one robot's daemon (a restart begins a new one)."""

    name: str
    node: Node
    boot: int
    started: float
    #: Every service set the test gave this run, in order.
    sets: list[tuple[Service, ...]]
    #: seq -> (when, destination or None for a beacon) of every ping this run sent.
    pings: dict[int, list[tuple[float, Addr | None]]] = field(default_factory=dict)
    #: robot -> its latest answer to our pings, by arrival and by our ping's time.
    last_proof: dict[str, Proof] = field(default_factory=dict)
    latest_ping_proof: dict[str, Proof] = field(default_factory=dict)
    #: address -> when a ping of ours was last answered from there.
    proven_at: dict[Addr, float] = field(default_factory=dict)
    bytes_in: Counter[Addr] = field(default_factory=Counter)
    unproven_out: Counter[Addr] = field(default_factory=Counter)
    #: The same by kind of datagram, to say what went there.
    unproven_kinds: dict[Addr, Counter[str]] = field(default_factory=dict)
    received: set[bytes] = field(default_factory=set)

    def __repr__(self) -> str:
        return f"{self.name}(boot {self.boot}, from t={self.started:.3f})"


@dataclass
class Policy:
    """What the outsider does to datagrams in flight that match: drop them, deliver them
    `delay` seconds late instead, or deliver a second copy `delay` seconds late."""

    action: str  # "drop" | "delay" | "dup"
    kind: str  # a `kind`, or "*"
    sender: str  # a robot, or "*"
    receiver: str  # a robot, or "*"
    delay: float = 0.0

    def matches(self, sender: str, receiver: str, k: str) -> bool:
        return (
            self.kind in ("*", k)
            and self.sender in ("*", sender)
            and self.receiver in ("*", receiver)
        )


class World:
    """Ground truth of one SimNet, the outsider's capture and tools, and the invariant checks."""

    def __init__(
        self,
        net: SimNet,
        *,
        keyed: bool,
        checks: Sequence[str] = INVARIANTS,
        known: Sequence[str] = (),
    ) -> None:
        self.net = net
        self.keyed = keyed
        self.checks = frozenset(checks)
        if keyed and "keyed-credit" in known:
            self.checks -= {"I4", "I4v"}
        self.known = frozenset(known)
        self.lives: dict[int, Life] = {}  # id(node) -> its life
        self.runs: dict[str, list[Life]] = {}  # robot -> its lives, oldest first
        self.captured: list[Capture] = []
        self.by_bytes: dict[bytes, list[Capture]] = {}
        #: The service set the next life of a robot starts with (set before it starts).
        self.starting: dict[str, tuple[Service, ...]] = {}
        #: Each robot's saved history map (what its daemon's store holds): robot -> record.
        self.saved: dict[str, dict[str, PeerRecord]] = {}
        self.policies: list[Policy] = []
        #: The outsider relays what robots send to `bridge[1]` to robot `bridge[0]`, and what
        #: that robot sends there back to the last other robot that sent there (or, when none
        #: did, to itself: a mirror).
        self.bridge: tuple[str, Addr] | None = None
        self._bridged_from: str | None = None
        self.log: list[str] = []  # what the outsider did, for the failure message
        net.on_send = self._on_send
        net.on_receive = self._on_receive
        net.after_event = self.check
        net.filter = self._filter

    # -- lives -----------------------------------------------------------------------------

    def life(self, node: Node) -> Life:
        life = self.lives.get(id(node))
        if life is None:
            sets = [self.starting.get(node.name, tuple(node.core.services))]
            life = Life(node.name, node, node.core.boot_id, self.net.now, sets)
            self.lives[id(node)] = life
            self.runs.setdefault(node.name, []).append(life)
        return life

    def current(self, name: str) -> Life:
        return self.life(self.net.nodes[name])

    def up(self) -> list[str]:
        return sorted(n for n, node in self.net.nodes.items() if node.up)

    def save(self, name: str) -> None:
        """What the robot's daemon writes to its store: the views its core hands out."""
        core = self.net.nodes[name].core
        store = self.saved.setdefault(name, {})
        for view in core.take_dirty():
            store[view.robot_id] = view
        for robot_id in core.take_removed():
            store.pop(robot_id, None)

    # -- what the simulator saw ------------------------------------------------------------

    def _on_send(self, node: Node, data: bytes, dst: Addr | None) -> None:
        life = self.life(node)
        now = self.net.now
        msg = wire.decode(data)
        cap = Capture(life, now, data, dst, node.addr, kind(msg))
        self.captured.append(cap)
        self.by_bytes.setdefault(data, []).append(cap)
        if isinstance(msg, wire.Discovery | wire.Alive) and msg.seq is not None:
            life.pings.setdefault(msg.seq, []).append((now, dst))
        if isinstance(msg, wire.Response) and msg.ping is not None:
            life.pings.setdefault(msg.ping, []).append((now, dst))
        if dst is not None and not self._proven(life, dst, now):
            life.unproven_out[dst] += len(data)
            life.unproven_kinds.setdefault(dst, Counter())[cap.kind] += len(data)
        if self.bridge is not None and dst == self.bridge[1] and node.up:
            via, addr = self.bridge
            if node.name != via:
                self._bridged_from = node.name
                self._later(0.001, via, data, addr, "bridge")
            elif self._bridged_from is not None or "mirror-conflict" not in self.known:
                # back to whoever sent there last; with nobody else, to itself (a mirror)
                self._later(0.001, self._bridged_from or via, data, addr, "bridge")

    def _proven(self, life: Life, addr: Addr, now: float) -> bool:
        t = life.proven_at.get(addr)
        return t is not None and now - t <= life.node.core.config.proven_for + EPS

    def _on_receive(self, node: Node, data: bytes, src: Addr) -> None:
        life = self.life(node)
        now = self.net.now
        life.bytes_in[src] += len(data)
        life.received.add(data)
        msg = wire.decode(data)
        if not isinstance(msg, wire.Response) or msg.seq is None:
            return
        timeout = node.core.config.ping_timeout
        window = node.core.config.dead_after
        for cap in self.by_bytes.get(data, ()):
            if cap.life.name == life.name:
                continue
            for t_ping, pdst in life.pings.get(msg.seq, ()):
                if t_ping > cap.t or now - t_ping > window + EPS:
                    continue
                if src != (cap.src if pdst is None else pdst):
                    continue  # not from where the ping went
                late = now - t_ping > timeout + EPS
                proof = Proof(now, t_ping, cap.life, src, t_ping if late else now)
                name = cap.life.name
                life.last_proof[name] = proof
                best = life.latest_ping_proof.get(name)
                if best is None or t_ping >= best.t_ping:
                    life.latest_ping_proof[name] = proof
                life.proven_at[src] = now

    # -- the outsider ----------------------------------------------------------------------

    def _filter(self, sender: str, receiver: str, data: bytes) -> bool:
        if not self.policies:
            return True
        k = kind(wire.decode(data))
        for p in self.policies:
            if not p.matches(sender, receiver, k):
                continue
            src = self.net.nodes[sender].addr
            if p.action == "drop":
                return False
            self._later(p.delay, receiver, data, src, p.action)
            return p.action == "dup"
        return True

    def _later(self, delay: float, to: str, data: bytes, src: Addr, why: str) -> None:
        self.net.call_at(self.net.now + delay, lambda: self.deliver(to, data, src, why))

    def deliver(self, to: str, data: bytes, src: Addr, why: str = "inject") -> None:
        """The outsider puts `data` in front of robot `to` as if it came from `src`; with a
        key that must change nothing `to` lists unless it is the datagram's first delivery to
        its own recipient from its own sender (I3)."""
        node = self.net.nodes.get(to)
        if node is None or not node.up:
            return
        life = self.life(node)
        legit = self._first_delivery(life, data, src)
        self.log.append(
            f"t={self.net.now:.3f} {why}: {self._describe(data)} -> {to} from {src[0]}"
            + ("" if legit else " (re-sent)")
        )
        del self.log[:-12]
        if not self.keyed or legit or "I3" not in self.checks:
            self.net.inject(to, data, src)
            return
        before = self.snapshot(to)
        self.net.inject(to, data, src)
        after = self.snapshot(to)
        if after != before:
            self._fail(
                "I3",
                f"{to}'s view changed on a datagram the outsider re-sent "
                f"({self._describe(data)} from {src[0]}):\n  before {before}\n  after  {after}",
            )

    def _first_delivery(self, life: Life, data: bytes, src: Addr) -> bool:
        if data in life.received:
            return False
        node = life.node
        return any(
            cap.life.name != life.name
            and cap.src == src
            and cap.t >= life.started
            and (cap.dst is None or cap.dst == node.addr)
            for cap in self.by_bytes.get(data, ())
        )

    def _describe(self, data: bytes) -> str:
        caps = self.by_bytes.get(data)
        if not caps:
            return f"{len(data)} bytes never sent by a robot"
        c = caps[0]
        to = "multicast" if c.dst is None else f"to {c.dst[0]}"
        return f"{c.life}'s {c.kind} of t={c.t:.3f} {to}"

    # -- the views -------------------------------------------------------------------------

    def snapshot(self, name: str) -> tuple[object, ...]:
        """What robot `name` lists (robots, boots, versions, sets, addresses) and its
        conflict record."""
        core = self.net.nodes[name].core
        listed = []
        for r in core.reachable():
            v = core.view(core.peers[r])
            ids = tuple(s.id for s in v.services)  # (the digest stands for their content)
            listed.append((r, v.address, v.boot_id, v.version, v.digest, ids, v.departed))
        c = core.conflict
        return (tuple(listed), None if c is None else (c.address, c.boot_id))

    def check(self) -> None:
        """Every invariant, now."""
        now = self.net.now
        for name in self.up():
            node = self.net.nodes[name]
            life = self.life(node)
            core = node.core
            window = core.config.dead_after
            for r in core.reachable():
                proof = life.last_proof.get(r)
                judged = "I1" in self.checks or ("I1p" in self.checks and proof is not None)
                if judged and (proof is None or proof.alive + window < now - EPS):
                    last = "never" if proof is None else f"last alive at t={proof.alive:.3f}"
                    self._fail(
                        "I1",
                        f"{name} lists {r} reachable, but {r} answered a ping of {life} "
                        f"{last} (miss window {window:g} s)",
                    )
                if proof is None:
                    continue
                view = core.view(core.peers[r])
                latest = life.latest_ping_proof[r].prover
                provers = [latest]
                if "late-old-answer" in self.known:
                    provers.append(proof.prover)
                if "I2" in self.checks and not any(
                    view.boot_id == p.boot and view.services in self._sets(p) for p in provers
                ):
                    held = [s.id for s in view.services]
                    self._fail(
                        "I2",
                        f"{name} lists {r} with boot {view.boot_id} and services {held}; "
                        f"its latest answer to {name} came from {latest}, whose sets were "
                        f"{[[s.id for s in ss] for ss in latest.sets]}",
                    )
                if "I3" in self.checks and self.keyed and view.address != latest.node.addr[0]:
                    self._fail(
                        "I3",
                        f"{name} lists {r} at {view.address}; {r} is at {latest.node.addr[0]}",
                    )
            if "I4" in self.checks or "I4v" in self.checks:
                robots = {n.addr for n in self.net.nodes.values()}
                for addr, out in sorted(life.unproven_out.items()):
                    if "I4" not in self.checks and addr in robots:
                        continue
                    if out > life.bytes_in[addr]:
                        kinds = dict(life.unproven_kinds[addr])
                        self._fail(
                            "I4",
                            f"{life} sent {out} bytes to {addr[0]} ({kinds}), which has not "
                            f"proven a round trip, and received only {life.bytes_in[addr]} "
                            "from it",
                        )
            if "I5" in self.checks and core.conflict is not None:
                c = core.conflict
                self._fail(
                    "I5",
                    f"{name} records a robot-id conflict with {c.address} (boot {c.boot_id}), "
                    "though no other daemon has its id",
                )

    def _sets(self, life: Life) -> list[tuple[Service, ...]]:
        """The sets a robot listed as of run `life` may show: none yet, or one it was given."""
        sets = [(), *life.sets]
        if "reused-boot-set" in self.known:
            for run in self.runs[life.name]:
                if run.boot == life.boot and run.started < life.started:
                    sets += run.sets
        return sets

    def _fail(self, invariant: str, what: str) -> None:
        recent = "\n    ".join(self.log) or "(nothing)"
        raise Violation(
            f"{invariant} at t={self.net.now:.3f}: {what}\n  the outsider's last acts:\n    "
            f"{recent}"
        )


def pick(
    captures: Sequence[Capture], kind_: str, back: int, where: Callable[[Capture], bool]
) -> Capture | None:
    """The `back`-th latest capture of a kind ("any": all) that `where` accepts (the oldest
    when there are fewer)."""
    found = [c for c in captures if (kind_ == "any" or c.kind == kind_) and where(c)]
    if not found:
        return None
    return found[-1 - min(back, len(found) - 1)]


__all__ = [
    "EPS",
    "FINDINGS",
    "INVARIANTS",
    "NARROW",
    "OUTSIDER",
    "VICTIM",
    "Capture",
    "Life",
    "Policy",
    "Proof",
    "Violation",
    "World",
    "kind",
    "pick",
]
