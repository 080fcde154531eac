"""A patient outsider against real daemons (issue 25; needs root).

The outsider is a namespace of the lab without sdfrd (`x9`) running sdfr/testing/outsider.py:
it has no key and knows only the public wire format.  The lab's bridge is a hub (as a radio
is), so it hears everything the robots send, multicast and unicast; it records it, and later
replays or relays it, from its own address or from any address it likes.

Each test makes one attack of issue 25, proves that every forged or replayed datagram reached
the robot attacked (tcpdump on that robot's interface: the exact bytes, from the address they
claim), then checks that the attack changed nothing it must not, and that the robot's reject
counters name it.

- Keyed fleet (`keyed`: r1-r3 with one fleet key; the outsider records ~12 s of their traffic,
  then r3 is killed): replays of dead r3's multicasts to a robot started after it died, and to
  a robot after its restart; r3's unicast replies to r2 replayed at r1; r1's own beacon sent
  back to it from elsewhere; a relay between r1 and r2 when they cannot hear each other.
- Open fleet (`open_fleet`: r1-r3 without a key): amplification toward a victim V (a namespace
  of the lab, so that what is sent to it goes on the wire) whose address the outsider forges:
  beacons claiming V, pings from V, plain SSDP searches from V and from outside the fleet's
  subnet.  The bytes each robot sends to V are counted on its own interface, beside the bytes
  that reached it from V.

Beacons are 1 s here (the findings do not depend on the product's 10 s): a peer's miss window
is MISS_LIMIT beacons.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from netlab import kernel, naming
from netlab.lab import Lab
from sdfr import wire
from sdfr.config import keystore
from sdfr.protocol import MISS_LIMIT
from tests.support.attacks import (
    GROUP,
    PORT,
    Datagram,
    Outsider,
    Sightings,
    Step,
    Tap,
    grown,
    health_of,
    hub,
    listed_at,
    metric,
    rejects,
    wait_until_listed,
)
from tests.support.fleets import _take_down, need_root, unique_lab_name
from tests.support.waiting import poll

pytestmark = pytest.mark.root

BEACON = 1.0
#: A peer not heard for this long is unreachable (the miss window).
DEAD_AFTER = MISS_LIMIT * BEACON
#: How long the lists, /health and /metrics are watched after an attack's last datagram: the
#: discovery layer acts on a datagram at once, and the API shows it within its status pull.
TAIL = 1.0
ROBOTS = ("r1", "r2", "r3")


@dataclass
class Fleet:
    """A lab of ROBOTS and the outsider x9, with sdfrd `options`; what the outsider heard."""

    lab: Lab
    outsider: Outsider
    options: dict[str, Any]
    heard: list[Datagram] = field(default_factory=list)

    def ip(self, robot: str) -> str:
        return self.lab.robot(robot).ip

    def multicasts(self, robot: str, kind: str = "alive") -> list[Datagram]:
        """What the outsider heard `robot` multicast, of one kind, oldest first."""
        return [
            d for d in self.heard if d.src == self.ip(robot) and d.dst == GROUP and d.kind == kind
        ]


def watch(seconds: float) -> None:
    """Let `seconds` pass while the samplers and captures of an attack watch (an observation
    window, not a wait for something to be ready)."""
    time.sleep(seconds)


def listing(lab: Lab, robot: str) -> set[str]:
    return {n["robot_id"] for n in lab.client(robot).neighbors()}


@pytest.fixture(scope="module")
def _labs() -> Iterator[Callable[..., Fleet]]:
    """``make(**sdfrd options) -> Fleet``: labs shared by a module's tests, down at its end."""
    need_root()
    labs: list[Lab] = []

    def make(**options: Any) -> Fleet:
        lab = Lab(unique_lab_name())
        labs.append(lab)
        lab.up()
        lab.add_robots(ROBOTS, {r: (i * 1.0, 0.0) for i, r in enumerate(ROBOTS)})
        outsider = Outsider(lab, lab.add_robot("x9", pos=(1.0, 1.0)).name)
        opts = {"beacon_interval": BEACON, **options}
        lab.start_all(ROBOTS, **opts)
        poll(
            "every robot lists the others",
            lambda: all(listing(lab, r) == set(ROBOTS) - {r} for r in ROBOTS),
            10.0,
        )
        return Fleet(lab, outsider, opts)

    yield make
    problems = [p for lab in reversed(labs) for p in _take_down(lab)]
    if problems:
        pytest.fail("lab teardown: " + "; ".join(problems))


# -- with a fleet key -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def keyed(_labs: Callable[..., Fleet], tmp_path_factory: pytest.TempPathFactory) -> Fleet:
    """A keyed fleet whose traffic the outsider recorded for ~12 s, then r3 killed (no
    Byebye) and dropped by r1 and r2."""
    key = tmp_path_factory.mktemp("keys") / "fleet.key"
    keystore.generate_key_file(key)
    fleet = _labs(key_file=key)
    lab = fleet.lab
    hub(lab)
    r2, r3 = fleet.ip("r2"), fleet.ip("r3")
    with fleet.outsider.record() as rec:

        def enough() -> bool | str:
            heard = rec.read()
            beacons = sum(1 for d in heard if d.src == r3 and d.dst == GROUP)
            replies = sum(1 for d in heard if d.src == r3 and d.dst == r2)
            return (beacons >= 12 and replies >= 12) or f"{beacons} beacons, {replies} replies"

        poll("the outsider heard 12 beacons of r3 and 12 of its unicasts to r2", enough, 30.0)
        lab.kill("r3")
    fleet.heard = rec.datagrams
    poll(
        "r1 and r2 drop the dead r3",
        lambda: all("r3" not in listing(lab, r) for r in ("r1", "r2")),
        DEAD_AFTER + 2.0,
    )
    return fleet


def _listed_message(who: str, seen: Sightings, span: float, what: str, outsider: str) -> str:
    listed = seen.when(lambda a: a is not None)
    where = sorted({a for _, a in listed})
    return (
        f"{who} listed dead r3 for {seen.seconds(lambda a: a is not None):.1f} s of a "
        f"{span:.1f} s replay of {what}, at {where} (the outsider is {outsider})"
    )


def never(achieved: object, message: str) -> None:
    """Fail with `message` alone when the attack `achieved` something (truthy)."""
    if achieved:
        pytest.fail(message, pytrace=False)


def test_a_robot_started_after_r3_died_does_not_list_r3_from_its_replayed_beacons(
    keyed: Fleet,
) -> None:
    lab, x9 = keyed.lab, keyed.outsider
    r3 = keyed.ip("r3")
    beacons = keyed.multicasts("r3")[-8:]
    lab.add_robot("r4", pos=(0.0, 1.0))
    lab.start("r4", **keyed.options)
    r4 = keyed.ip("r4")
    wait_until_listed(lab, "r4", ("r1", "r2"), 10 * BEACON)
    before = rejects(lab, "r4")
    challenged = metric(lab, "r4", "sdfr_challenges_total")
    # One a beacon period, in the order r3 sent them: every other one from the outsider's
    # own address (where r4 would list r3), the others from r3's own address, now free.
    steps = [
        Step(i * BEACON, d.data, GROUP, None if i % 2 == 0 else r3) for i, d in enumerate(beacons)
    ]
    with Tap(lab, ["r4"]) as tap, Sightings(lab, "r4", listed_at("r3")) as seen:
        replay = x9.replay(steps).wait(len(steps) * BEACON + 10)
        watch(TAIL)

    # The replay happened: every datagram reached r4, from where it was sent.
    ours = [s.data for s in steps if s.spoof is None]
    spoofed = [s.data for s in steps if s.spoof is not None]
    assert tap.arrived("r4", ours, x9.ip) == len(ours), "replay from x9 did not reach r4"
    assert tap.arrived("r4", spoofed, r3) == len(spoofed), "replay from r3 did not reach r4"

    span = replay.last - replay.first + TAIL
    listed = seen.when(lambda a: a is not None)
    never(listed, _listed_message("r4", seen, span, f"{len(steps)} of r3's beacons", x9.ip))
    answered = [d for d in tap.between("r4", r4, x9.ip) if d.kind == "response"]
    never(answered, f"r4 answered {len(answered)} of r3's replayed beacon pings at the "
                    f"outsider's address {x9.ip}")  # fmt: skip
    counted = grown(before, rejects(lab, "r4"))
    assert counted["unproven"] >= 1, f"rejects grown on r4: {dict(counted)}"
    assert counted["relayed"] >= 1, f"rejects grown on r4: {dict(counted)}"
    assert metric(lab, "r4", "sdfr_challenges_total") > challenged, "r4 never challenged r3"
    assert "r3" not in listing(lab, "r4")  # the challenges went unanswered


def test_after_a_restart_replayed_datagrams_of_dead_r3_do_not_keep_it_listed(
    keyed: Fleet,
) -> None:
    lab, x9 = keyed.lab, keyed.outsider
    r3 = keyed.ip("r3")
    lab.restart("r2")  # its history map (r3 in it, unreachable) is restored
    wait_until_listed(lab, "r2", ("r1",), 10 * BEACON)
    assert "r3" not in listing(lab, "r2")
    before = rejects(lab, "r2")
    # One every 2 s from r3's own address, in the order r3 sent them (its current boot).
    datagrams = keyed.multicasts("r3")[-8:]
    steps = [Step(2 * BEACON * i, d.data, GROUP, r3) for i, d in enumerate(datagrams)]
    with Tap(lab, ["r2"]) as tap, Sightings(lab, "r2", listed_at("r3")) as seen:
        replay = x9.replay(steps).wait(len(steps) * 2 * BEACON + 10)
        watch(TAIL)

    data = [s.data for s in steps]
    assert tap.arrived("r2", data, r3) == len(data), "the replay did not reach r2"
    late = [t - replay.first for t, a in seen.samples if a is not None]
    late = [t for t in late if t > DEAD_AFTER]
    never(late,
        _listed_message(
            "r2 (restarted)", seen, replay.last - replay.first + TAIL,
            f"{len(steps)} of r3's datagrams, one per {2 * BEACON:g} s", x9.ip,
        )
        + f"; still at +{late[-1] if late else 0:.1f} s, beyond its miss window of "
        f"{DEAD_AFTER:g} s"
    )  # fmt: skip
    counted = grown(before, rejects(lab, "r2"))
    assert counted["unproven"] >= 1, f"rejects grown on r2: {dict(counted)}"


def test_unicast_replies_of_r3_to_r2_replayed_at_r1_are_refused(keyed: Fleet) -> None:
    lab, x9 = keyed.lab, keyed.outsider
    r1, r2, r3 = keyed.ip("r1"), keyed.ip("r2"), keyed.ip("r3")
    replies = [d for d in keyed.heard if d.src == r3 and d.dst == r2][-10:]
    assert "r3" not in listing(lab, "r1")
    before = rejects(lab, "r1")
    # One a beacon period, each from r3's address and port, to r1's.
    steps = [
        Step(i * BEACON, d.data, f"{r1}:{d.dport}", f"{r3}:{d.sport}")
        for i, d in enumerate(replies)
    ]
    with Tap(lab, ["r1"]) as tap, Sightings(lab, "r1", listed_at("r3")) as seen:
        replay = x9.replay(steps).wait(len(steps) * BEACON + 10)
        watch(TAIL)

    data = [s.data for s in steps]
    assert tap.arrived("r1", data, r3) == len(data), "the replay did not reach r1"
    listed = seen.when(lambda a: a is not None)
    never(listed, _listed_message(
        "r1", seen, replay.last - replay.first + TAIL,
        f"{len(steps)} of r3's unicast replies to r2", x9.ip,
    ))  # fmt: skip
    counted = grown(before, rejects(lab, "r1"))
    assert counted["not-for-me"] >= len(steps), f"rejects grown on r1: {dict(counted)}"


def test_a_robots_own_beacon_sent_back_from_elsewhere_leaves_no_lasting_warning(
    keyed: Fleet,
) -> None:
    lab, x9 = keyed.lab, keyed.outsider
    r1 = keyed.ip("r1")
    own = keyed.multicasts("r1")[-1]
    poll("r1 healthy", lambda: lab.client("r1").health()["status"] == "ok", 5.0)
    before = rejects(lab, "r1")
    with Tap(lab, ["r1"]) as tap, Sightings(lab, "r1", health_of) as health:
        x9.send(own.data, GROUP)  # once, from the outsider's own address
        watch(DEAD_AFTER + TAIL)
    assert tap.arrived("r1", [own.data], x9.ip) == 1, "r1's beacon did not come back to it"
    warned = health.when(lambda h: h[0] == "warning")
    never(warned,
        f"r1's own beacon sent back once from {x9.ip} put its /health in warning for "
        f"{health.seconds(lambda h: h[0] == 'warning'):.1f} s of {DEAD_AFTER + TAIL:g} s: "
        f"{warned[-1][1] if warned else ''}"
    )  # fmt: skip
    counted = grown(before, rejects(lab, "r1"))
    assert counted["relayed"] >= 1, f"rejects grown on r1: {dict(counted)}"

    # Whatever comes back, and from wherever: everything r1 sends, relayed back to it for a
    # few seconds from the outsider's address (by multicast) and from an address nobody has
    # (by unicast).  No warning outlives a miss window without a live second daemon.
    nobody = str(lab.robot("r1").address.network.network_address + 200)
    relays = [
        x9.relay(r1, GROUP, seconds=3 * BEACON),
        x9.relay(r1, r1, spoof=nobody, seconds=3 * BEACON),
    ]
    for proc in relays:
        out, _ = proc.communicate(timeout=10 * BEACON)
        assert '"relayed": 0' not in out, f"nothing was relayed: {out}"
    took = poll(
        "r1's /health back to ok after the relays",
        lambda: health_of(lab.client("r1"))[0] == "ok" or str(health_of(lab.client("r1"))),
        DEAD_AFTER + 2 * TAIL,
    )
    assert took <= DEAD_AFTER + 2 * TAIL


def test_a_relay_between_robots_that_cannot_hear_each_other_moves_neither(keyed: Fleet) -> None:
    """A wormhole: r1 and r2 out of each other's range, the outsider relays all each sends to
    the other, from its own address.  A robot's address is the one it signs: r1 must not list
    r2 at the outsider's address (before: r1 challenged it there, the outsider relayed the
    challenge to r2, which answers any ping, and its answer back)."""
    lab, x9 = keyed.lab, keyed.outsider
    r1, r2 = keyed.ip("r1"), keyed.ip("r2")
    lab.set_pair_quality("r1", "r2", loss=100.0)
    try:
        poll("r1 drops r2", lambda: "r2" not in listing(lab, "r1"), DEAD_AFTER + 2.0)
        before = rejects(lab, "r1")
        seconds = 6 * BEACON
        with Tap(lab, ["r1"]) as tap, Sightings(lab, "r1", listed_at("r2")) as seen:
            relays = [x9.relay(r2, r1, seconds=seconds), x9.relay(r1, r2, seconds=seconds)]
            outs = [proc.communicate(timeout=seconds + 10)[0] for proc in relays]
            watch(TAIL)
    finally:
        lab.set_pair_quality("r1", "r2", loss=None)
    relayed = json.loads(outs[0].strip().splitlines()[-1])["relayed"]
    arrived = len(tap.between("r1", x9.ip, r1))
    assert relayed > 0 and arrived >= relayed, f"{arrived} of {relayed} relayed reached r1"
    at_x9 = seen.when(lambda a: a == x9.ip)
    never(at_x9, f"r1 listed r2 at the outsider's address {x9.ip} for "
                 f"{seen.seconds(lambda a: a == x9.ip):.1f} s of a {seconds + TAIL:g} s relay "
                 f"of {relayed} of r2's datagrams (r1 and r2 cannot hear each other)")  # fmt: skip
    counted = grown(before, rejects(lab, "r1"))
    assert counted["relayed"] >= 1, f"rejects grown on r1: {dict(counted)}"


# -- without a key: amplification -------------------------------------------------------------


@pytest.fixture(scope="module")
def open_fleet(_labs: Callable[..., Fleet]) -> Fleet:
    return _labs()


def _amplification(
    fleet: Fleet, victim: str, steps: list[Step], robots: tuple[str, ...] = ROBOTS
) -> tuple[Tap, dict[str, tuple[int, int]]]:
    """Send `steps` (forged from the victim's address) and watch until the robots are done
    with them: per robot, (bytes from the victim that reached it, bytes it sent the victim)."""
    lab = fleet.lab
    with Tap(lab, robots) as tap:
        fleet.outsider.replay(steps).wait(steps[-1].at + 10)
        # Whatever a forged datagram starts (challenges of an unknown robot) ends within a
        # miss window: watch that long after the last one.
        watch(DEAD_AFTER + TAIL)
    out = {}
    for r in robots:
        ip = fleet.ip(r)
        brought = sum(len(d.data) for d in tap.got[r] if d.src == victim and d.dst in (ip, GROUP))
        drawn = sum(len(d.data) for d in tap.between(r, ip, victim))
        out[r] = (brought, drawn)
    return tap, out


def _ratios(bytes_: dict[str, tuple[int, int]]) -> str:
    return ", ".join(
        f"{r}: {drawn} B to V for {brought} B from V ({drawn / max(1, brought):.1f}x)"
        for r, (brought, drawn) in bytes_.items()
    )


def test_forged_beacons_claiming_a_victims_address_draw_no_more_than_they_bring(
    open_fleet: Fleet,
) -> None:
    lab = open_fleet.lab
    victim = lab.add_robot("v1", pos=(2.0, 1.0)).ip
    fakes = [
        wire.encode(
            wire.Alive(
                wire.Origin(lab.fleet, f"ghost{i}", 1, 1, "0" * 16, wire.WIRE_COMPACT),
                f"http://{victim}/",
                30,
            ),
            compact=True,
        )
        for i in range(10)
    ]
    before = {r: rejects(lab, r) for r in ROBOTS}
    steps = [Step(0.2 * i, data, GROUP, victim) for i, data in enumerate(fakes)]
    tap, bytes_ = _amplification(open_fleet, victim, steps)
    for r in ROBOTS:
        assert tap.arrived(r, fakes, victim) == len(fakes), f"the beacons did not reach {r}"
    print(f"forged beacons claiming V: {_ratios(bytes_)}")
    never(any(drawn > brought for brought, drawn in bytes_.values()),
          f"{len(fakes)} forged beacons claiming V={victim}: {_ratios(bytes_)}")  # fmt: skip
    for r in ROBOTS:
        counted = grown(before[r], rejects(lab, r))
        assert counted["unproven"] >= 1, f"rejects grown on {r}: {dict(counted)}"


def test_forged_pings_from_a_victims_address_draw_no_more_than_they_bring(
    open_fleet: Fleet,
) -> None:
    lab = open_fleet.lab
    victim = lab.add_robot("v2", pos=(2.0, 1.0)).ip
    pings = {
        r: [
            wire.encode(
                wire.Discovery(
                    wire.Origin(lab.fleet, f"pinger{i}", 1, 1, "0" * 16, wire.WIRE_COMPACT),
                    f"uuid:{r}",
                    0,
                    seq=1000 + i,
                    multicast=False,
                ),
                group=open_fleet.ip(r),
                port=PORT,
                compact=True,
            )
            for i in range(10)
        ]
        for r in ROBOTS
    }
    before = {r: rejects(lab, r) for r in ROBOTS}
    steps = [
        Step(0.2 * i, data, open_fleet.ip(r), victim)
        for r in ROBOTS
        for i, data in enumerate(pings[r])
    ]
    steps.sort(key=lambda s: s.at)
    tap, bytes_ = _amplification(open_fleet, victim, steps)
    for r in ROBOTS:
        assert tap.arrived(r, pings[r], victim) == len(pings[r]), f"the pings did not reach {r}"
    print(f"forged pings from V: {_ratios(bytes_)}")
    never(any(drawn > brought for brought, drawn in bytes_.values()),
          f"{len(pings['r1'])} forged pings from V={victim} to each robot: "
          f"{_ratios(bytes_)}")  # fmt: skip
    for r in ROBOTS:
        counted = grown(before[r], rejects(lab, r))
        assert counted["unproven"] + counted["amplification"] >= 1, (
            f"rejects grown on {r}: {dict(counted)}"
        )


PLAIN_SEARCH = wire.encode(wire.Discovery(None, "ssdp:all", 1))
#: An address outside every lab's fleet subnet (10.<fleet>.0.0/16): TEST-NET-1.
OFF_SUBNET = "192.0.2.7"


SEARCHES = 10


def _plain_searches(fleet: Fleet, src: str) -> tuple[Tap, dict[str, Counter[str]]]:
    """SEARCHES plain SSDP searches from `src` to the group within 0.1 s, watched until the
    robots have answered them; the reject counters each robot gained."""
    lab = fleet.lab
    before = {r: rejects(lab, r) for r in ROBOTS}
    steps = [Step(0.01 * i, PLAIN_SEARCH, GROUP, src) for i in range(SEARCHES)]
    with Tap(lab, ROBOTS) as tap:
        fleet.outsider.replay(steps).wait(10)
        watch(2 * TAIL)  # a plain search is answered at once (no MX delay)
    for r in ROBOTS:
        arrived = tap.arrived(r, [PLAIN_SEARCH] * SEARCHES, src)
        assert arrived == SEARCHES, f"{arrived} of {SEARCHES} searches from {src} reached {r}"
    return tap, {r: grown(before[r], rejects(lab, r)) for r in ROBOTS}


def test_plain_searches_from_a_victim_get_at_most_one_answer_per_robot(
    open_fleet: Fleet,
) -> None:
    victim = open_fleet.lab.add_robot("v3", pos=(2.0, 1.0)).ip
    tap, counted = _plain_searches(open_fleet, victim)
    answers = {r: tap.between(r, open_fleet.ip(r), victim) for r in ROBOTS}
    bytes_ = {r: (SEARCHES * len(PLAIN_SEARCH), sum(len(d.data) for d in a))
              for r, a in answers.items()}  # fmt: skip
    print(f"plain searches from V: {_ratios(bytes_)}")
    never(
        any(len(a) > 1 for a in answers.values()),
        f"{SEARCHES} plain searches of {len(PLAIN_SEARCH)} B from V={victim} within 0.1 s "
        f"drew { {r: len(a) for r, a in answers.items()} } answers: {_ratios(bytes_)}",
    )
    for r in ROBOTS:
        answered = len(answers[r])
        assert counted[r]["rate-limited"] >= SEARCHES - answered, (
            f"rejects grown on {r}: {dict(counted[r])}"
        )


def test_plain_searches_from_off_the_fleets_subnet_get_no_answer(open_fleet: Fleet) -> None:
    lab = open_fleet.lab
    # The victim has an address off the subnet, and every robot a route to it (as a robot
    # with a default gateway has): an answer could go there.
    v4 = lab.add_robot("v4", pos=(2.0, 1.0))
    kernel.run_in_ns(v4.ns, ["ip", "addr", "add", f"{OFF_SUBNET}/24", "dev", naming.ROBOT_IFACE],
                     "adding an address off the subnet")  # fmt: skip
    for r in ROBOTS:
        kernel.run_in_ns(
            lab.robot(r).ns,
            ["ip", "route", "add", f"{OFF_SUBNET}/32", "dev", naming.ROBOT_IFACE],
            "adding a route off the subnet",
        )
    tap, counted = _plain_searches(open_fleet, OFF_SUBNET)
    answers = {r: len(tap.between(r, open_fleet.ip(r), OFF_SUBNET)) for r in ROBOTS}
    never(any(answers.values()),
          f"{SEARCHES} plain searches from {OFF_SUBNET}, off the fleet's subnet, drew "
          f"{answers} answers")  # fmt: skip
    for r in ROBOTS:
        assert counted[r]["off-subnet"] >= SEARCHES, f"rejects grown on {r}: {dict(counted[r])}"
