"""A lab's medium, as its robots hear it: the ranges and partitions of `netlab.ranges`
applied in batches, through `netlab.medium` (a wired lab's bridge) or `netlab.airmedium`
(a radio lab's frames), mobility, per-robot link shaping, and the truth of who hears whom
(`links`).  A part of `Lab` (see `netlab.lab`)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from netlab import airmedium, naming, shaping
from netlab.doctor import capabilities
from netlab.errors import NetlabError
from netlab.medium import Medium
from netlab.mobility import MobilityModel, walk
from netlab.ranges import Links, Pos, Topology, forwarded, with_link_loss
from netlab.robots import Robot, RobotRef
from netlab.shaping import LinkShape


class LabMedium:
    """The medium of a `Lab` (a part of it: it needs the lab's robots and state)."""

    topology: Topology
    medium: Medium
    air: str
    air_medium: str  # a radio lab's: "netlab" (netlab.airmedium) or "hwsim" (the kernel's)
    workdir: Path
    _state: str
    _radio_addrs: dict[str, str]  # a radio lab's robots' hwsim addresses
    _batch: int
    _robots: dict[str, Robot]
    _shapes: dict[str, LinkShape]
    _nft_loss: dict[str, float]
    _daemon_opts: dict[str, dict[str, Any]]  # each robot's sdfrd options, as last started
    #: A lab spanning hosts (`netlab.vxlan`): the other hosts' robots, by name, with their MAC.
    _remote: dict[str, str]

    if TYPE_CHECKING:

        def robot(self, ref: RobotRef) -> Robot: ...

        def _check_up(self) -> None: ...

    @contextlib.contextmanager
    def batch(self) -> Iterator[None]:
        """Apply every medium change made in the body at once, at its end."""
        self._batch += 1
        ok = False
        try:
            yield
            ok = True
        finally:
            self._batch -= 1
            if self._batch == 0 and self._state == "up":
                if ok:
                    self._apply_medium()
                else:
                    with contextlib.suppress(NetlabError):
                        self._apply_medium()

    def _known(self, ref: RobotRef) -> str:
        """A robot of this lab, or of another host of a spanning lab, by name."""
        if isinstance(ref, str) and ref in self._remote:
            return ref
        return self.robot(ref).name

    def _changed(self) -> None:
        if self._batch == 0:
            self._apply_medium()

    def _wired(self, what: str) -> None:
        """NetlabError for `what` on a radio lab, whose links are shaped by no qdisc."""
        if self.air != "wired":
            raise NetlabError(
                f"{what}: not on the radio medium yet, whose links have no qdiscs; "
                "use a wired lab (medium wired)"
            )

    def _ranged(self, what: str) -> None:
        """NetlabError for `what` on a radio lab left to hwsim's own medium, where every
        radio hears every other (no range model between them)."""
        if self.air != "wired" and self.air_medium != "netlab":
            raise NetlabError(
                f"{what}: this radio lab is on hwsim's own medium (air_medium hwsim), where "
                "every radio hears every other; netlab's medium (air_medium netlab) obeys the "
                "range model"
            )

    @property
    def air_links_file(self) -> Path:
        """A radio lab's links, as its medium (`netlab.airmedium`) obeys them."""
        return self.workdir / "air" / "links.json"

    @property
    def air_stats_file(self) -> Path:
        """A radio lab's medium's counters (frames, copies, CPU seconds), every second."""
        return self.workdir / "air" / "stats.json"

    @property
    def radio_macs(self) -> dict[str, str]:
        """A radio lab's robots' interface addresses: who sent which frame on the air."""
        return {r: airmedium.perm_address(a) for r, a in self._radio_addrs.items()}

    def _apply_medium(self) -> None:
        if self.air != "wired" and self.air_medium != "netlab":
            return  # (hwsim's own medium: every radio hears every other)
        if self.air != "wired":  # the radios' frames go through the lab's air medium
            radios = {r: a for r, a in self._radio_addrs.items() if r in self._robots}
            links = {p: loss for p, loss in self.topology.links().items() if set(p) <= set(radios)}
            airmedium.write_links(self.air_links_file, radios, links)
            return
        links = with_link_loss(self.topology.links(), self._nft_loss)
        ports = {r.name: r.port for r in self._robots.values()}
        self.medium.load(links, ports, remote=self._remote)

    def links(self) -> Links:
        """Ground truth: every (sender, receiver) pair that is linked now, with its loss in %.

        Includes each robot's own link loss (`shape(loss=...)`), however it is realised.
        A radio lab's medium delivers frames by the same links; on hwsim's own medium
        every radio hears every other. Radios in an 802.11s mesh (`mesh_radios`) forward
        each other's frames: between them a pair is linked through any chain of them, with
        its best chain's loss (`netlab.ranges.forwarded`).
        """
        if self.air != "wired" and self.air_medium != "netlab":
            return {(a, b): 0.0 for a in self._robots for b in self._robots if a != b}
        link_loss = {name: shape.loss for name, shape in self._shapes.items()}
        links = with_link_loss(self.topology.links(), link_loss)
        return forwarded(links, self.mesh_radios())

    def mesh_radios(self) -> set[str]:
        """A radio lab's robots whose sdfrd was last started in 802.11s mesh (`wifi_mode`):
        their radios stay in the mesh, forwarding, while sdfrd is stopped (its
        wpa_supplicant runs on until the next start or the lab's end)."""
        if self.air == "wired":
            return set()
        return {r for r, opts in self._daemon_opts.items() if opts.get("wifi_mode") == "mesh"}

    def neighbours(self, ref: RobotRef) -> set[str]:
        """The robots `ref` hears now (ground truth)."""
        name = self.robot(ref).name
        return {a for (a, b) in self.links() if b == name}

    def positions(self) -> dict[str, Pos]:
        return dict(self.topology.positions)

    def move(self, ref: RobotRef, pos: Pos) -> None:
        self._check_up()
        self._ranged("moving a robot")
        self.topology.move(self._known(ref), pos)
        self._changed()

    def partition(self, groups: Iterable[Iterable[RobotRef]]) -> None:
        """Cut every link between `groups` (robots in none form one more group)."""
        self._check_up()
        self._ranged("a partition")
        self.topology.partition([[self._known(r) for r in g] for g in groups])
        self._changed()

    def merge(self) -> None:
        """End the partition."""
        self._check_up()
        self._ranged("a merge")
        self.topology.merge()
        self._changed()

    def set_pair_quality(
        self, a: RobotRef, b: RobotRef, *, loss: float | None, both: bool = True
    ) -> None:
        """Loss in % of a→b (and b→a if `both`) while linked; None: back to the range model."""
        self._check_up()
        self._ranged("a pair's loss")
        self.topology.set_pair_quality(self._known(a), self._known(b), loss, both)
        self._changed()

    def run_mobility(
        self,
        model: MobilityModel,
        duration: float,
        step: float = 0.5,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> list[tuple[float, Links]]:
        """Move the model's robots every `step` seconds for `duration`; the links at each step."""
        self._check_up()
        self._ranged("mobility")
        for name in model.robots:
            self.robot(name)
        timeline: list[tuple[float, Links]] = []

        def apply(t: float, positions: dict[str, Pos]) -> None:
            with self.batch():
                for name, pos in positions.items():
                    self.topology.move(name, pos)
            timeline.append((t, self.links()))

        walk(model, duration, step, apply, clock=clock, sleep=sleep)
        return timeline

    # -- shaping -------------------------------------------------------------------------

    def shape(self, ref: RobotRef, **params: Any) -> LinkShape:
        """Shape the robot's link (both directions); no parameters removes all shaping.

        delay/jitter in ms, loss/duplicate/reorder/corrupt in %, rate in bit/s or
        '1mbit'. Raises ShapingUnsupported, before changing anything, for what this
        kernel cannot do.
        """
        self._check_up()
        self._wired("shaping a link")
        robot = self.robot(ref)
        shape = LinkShape.of(**params)
        plan = shaping.plan(shape, capabilities())
        shaping.apply_in_ns(robot.ns, naming.ROBOT_IFACE, plan, f"eth0 of {robot.name}")
        shaping.apply(
            self.medium.ipr, self.medium.ifindex(robot.port), plan, f"the air port of {robot.name}"
        )
        self._shapes[robot.name] = shape
        if plan.nft_loss:
            self._nft_loss[robot.name] = plan.nft_loss
        else:
            self._nft_loss.pop(robot.name, None)
        self._changed()
        return shape

    def shape_of(self, ref: RobotRef) -> LinkShape:
        return self._shapes.get(self.robot(ref).name, LinkShape())
