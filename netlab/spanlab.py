"""A lab spread over hosts, driven from here: one `netlab.agent` per host over ssh.

`SpanLab` spreads the robots over the hosts (given per host, or in turn), numbers them across
the lab (addresses and MACs never collide between hosts), brings up each host's share with a
`netlab.vxlan.Span` joining the media, tells every host where every other host's robots are,
and sends each change of the medium (moves, partitions, the merge, pair quality) to every
host, so that each host judges the frames it receives by the same map.  Questions about a
robot (its daemon, its API, its log, its shaping) go to its host.  It is a lab the scenario
engine can run (`netlab.scenario.backend.LabLike`): `span_backend` makes one per run.

Each host's share is a lab of its own name (``<lab><i>``... as given by `part_names`): on
hosts simulated on one machine (`netlab.hostsim`) the shares' namespaces share one list.

Clean-up: `down` asks every host to take its share down; a host that cannot be reached is
named in the error after the others are down.  An agent also takes its share down when its
ssh session ends (the controller died, or the connection dropped).
"""

from __future__ import annotations

import base64
import contextlib
import shutil
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

from netlab import naming, procstat
from netlab.agent import FILE_CHUNK
from netlab.agentlink import AgentClient, Part
from netlab.errors import NetlabError
from netlab.hosts import HostError, Ssh
from netlab.observe import ClientLike
from netlab.ranges import Links, Pos, RangeModel, UnitDisc, model_to_json
from netlab.scenario.backend import Backend, LabLike, LabSpec
from netlab.scenario.model import Scenario
from netlab.vxlan import DEFAULT_PORT, vni_for


@dataclass(frozen=True, slots=True)
class SpanRobot:
    """A robot of a lab across hosts, as its host has it (its `log` is a path there)."""

    name: str
    host: str
    ns: str
    mac: str
    iface: str
    log: Path


class SpanMedium:
    """The medium of a lab across hosts is one per host: there is no one namespace to
    capture in (`SpanLab.start_captures` captures on each)."""

    def __init__(self, lab: str) -> None:
        self.lab = lab

    @property
    def ns(self) -> str:
        raise NetlabError(
            f"lab {self.lab} spans hosts: its medium has a namespace on each, none here"
        )


@dataclass(slots=True)
class SpanLab:
    """Robots spread over `hosts` (ssh destinations with their underlay addresses).

    `robots` are added at `up`, each on its host; `place` says where robots added later go.
    A robot neither names goes to the host with the fewest robots, counting those they will
    get (the first such, in the order of `hosts`).
    """

    name: str
    #: (how to reach it, its underlay address: None for the one its ssh session came in on)
    hosts: Sequence[tuple[Ssh, str | None]]
    robots: Mapping[str, str] = field(default_factory=dict)  # robot -> host destination
    place: Mapping[str, str] = field(default_factory=dict)  # robot -> host destination
    seed: int = 7
    fleet: int = 3
    range_model: RangeModel = field(default_factory=lambda: UnitDisc(20.0))
    positions_at_start: Mapping[str, Pos] = field(default_factory=dict)
    workdir: str | None = None  # the shares' parent folder on each host (default: a new one)
    runtime: str = "namespace"
    image: str | None = None
    addressing: str = "manual"  # or "auto": each sdfrd derives, probes and defends its own
    port: int = DEFAULT_PORT
    env: Mapping[str, str] = field(default_factory=dict)
    parts: dict[str, Part] = field(default_factory=dict)
    placed: dict[str, str] = field(default_factory=dict)  # robot -> host, as added
    index: dict[str, int] = field(default_factory=dict)
    macs: dict[str, str] = field(default_factory=dict)
    #: host -> (its clock minus this one's, in s; the bound of that measure: half the round trip)
    clocks: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: (when, each host's VXLAN counters): read with every `usage` reading.
    span_readings: list[tuple[float, dict[str, dict[str, int]]]] = field(default_factory=list)
    _robots: dict[str, SpanRobot] = field(default_factory=dict)
    _captures: dict[str, dict[str, str]] = field(default_factory=dict)  # host -> label -> path
    _pending: list[tuple[str | None, dict[str, Any]]] | None = None

    def part_names(self) -> dict[str, str]:
        """Each host's share's own lab name: the lab's, then the host's number (base 36)."""
        base = self.name[:7]
        return {ssh.destination: f"{base}{naming.b36(i)}" for i, (ssh, _) in enumerate(self.hosts)}

    def host_of(self, robot: str) -> Part:
        try:
            return self.parts[self.placed[robot]]
        except KeyError:
            raise NetlabError(f"lab {self.name} has no robot {robot!r}") from None

    @property
    def where(self) -> str:
        """Where its robots are, and how far apart the hosts' clocks may be from this one's."""
        apart = max((abs(off) + bound for off, bound in self.clocks.values()), default=0.0)
        return (
            f"on one medium across {len(self.hosts)} hosts (clocks within "
            f"{apart * 1e3:.1f} ms of the controller's)"
        )

    @property
    def hosts_meta(self) -> dict[str, dict[str, Any]]:
        """For a run's report: each host's robots, and its clock's offset from this one's
        with the bound of that measure (half the quickest round trip): a latency across two
        hosts is known to within the sum of their offsets' bounds, once their offsets are
        taken off."""
        return {
            ssh.destination: {
                "robots": [r for r, h in self.placed.items() if h == ssh.destination],
                "clock_offset_s": self.clocks.get(ssh.destination, (None, None))[0],
                "clock_bound_s": self.clocks.get(ssh.destination, (None, None))[1],
            }
            for ssh, _ in self.hosts
        }

    @property
    def span_meta(self) -> list[dict[str, Any]]:
        """For a run's report: each host's VXLAN counters at each `usage` reading (what the
        lab's frames cost the underlay over a resources check's window)."""
        return [{"time": t, "hosts": hosts} for t, hosts in self.span_readings]

    @property
    def medium(self) -> SpanMedium:
        return SpanMedium(self.name)

    def __enter__(self) -> SpanLab:
        try:
            self.up()
        except BaseException:
            self.down()
            raise
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.down()

    def up(self) -> None:
        """Every host's share up, joined by the span; then the robots of `robots`.

        First each host is greeted: it must run this netlab version (HostError naming the
        host and both versions otherwise, before anything is made), its underlay address is
        the one given or the one its ssh session came in on, and its clock's offset from
        this one is measured (`clocks`)."""
        naming.check_lab_name(self.name)
        dests = [ssh.destination for ssh, _ in self.hosts]
        if not dests:
            raise NetlabError(f"lab {self.name}: a lab across hosts needs at least one host")
        if len(set(dests)) != len(dests):
            raise NetlabError(f"lab {self.name}: hosts repeat: {', '.join(dests)}")
        unknown = sorted({h for h in [*self.robots.values(), *self.place.values()]
                          if h not in dests})  # fmt: skip
        if unknown:
            raise NetlabError(f"lab {self.name}: robots on unknown hosts {', '.join(unknown)}")
        model = model_to_json(self.range_model)
        if model is None:
            raise NetlabError(
                f"lab {self.name}: a lab across hosts sends its range model to each host; "
                f"{type(self.range_model).__name__} cannot be sent (a unit or lossy disc can)"
            )
        addrs = [self._greet(ssh, addr) for ssh, addr in self.hosts]
        names = self.part_names()
        span = {"lab": self.name, "vni": vni_for(self.name), "hosts": addrs, "port": self.port}
        for (ssh, _), addr in zip(self.hosts, addrs, strict=True):
            name = names[ssh.destination]
            workdir = f"{self.workdir}/{name}" if self.workdir is not None else None
            here = {**span, "local": addr}
            self.parts[ssh.destination].call(
                "up", name=name, seed=self.seed, fleet=self.fleet, range=model, workdir=workdir,
                span=here, runtime=self.runtime, image=self.image, addressing=self.addressing,
            )  # fmt: skip
        at = self.positions_at_start
        self.add_robot_batch([(r, at.get(r, (0.0, 0.0)), None, None) for r in self.robots])

    def _greet(self, ssh: Ssh, given: str | None) -> str:
        """Start the host's agent; its underlay address (see `up`)."""
        from sdfr import __version__

        dest = ssh.destination
        part = self.parts[dest] = Part(ssh, self.env)
        try:
            hi = part.call("hello")  # (its time is late by the agent's start: not used)
        except HostError as exc:
            if "no operation 'hello'" in str(exc):
                raise HostError(
                    f"host {dest}: its netlab is older than {__version__} (no hello): run the "
                    "same version on every host"
                ) from None
            raise
        if hi["version"] != __version__:
            raise HostError(
                f"host {dest}: netlab {hi['version']} there, {__version__} here: run the same "
                "version on every host"
            )
        # The clock: of three exchanges, the quickest bounds the offset best (NTP's way).
        best = (0.0, float("inf"))
        for _ in range(3):
            t0 = time.time()
            there = float(part.call("hello")["time"])
            t1 = time.time()
            if (t1 - t0) / 2 < best[1]:
                best = (there - (t0 + t1) / 2, (t1 - t0) / 2)
        self.clocks[dest] = best
        address = given or hi.get("address")
        if not address:
            raise HostError(
                f"host {dest}: no underlay address was given and its ssh session does not say "
                "which address it came in on (no SSH_CONNECTION): give the host's address"
            )
        return str(address)

    def _place(self, name: str) -> str:
        if name in self.robots or name in self.place:
            return self.robots.get(name) or self.place[name]
        count = {ssh.destination: 0 for ssh, _ in self.hosts}
        planned = {**self.place, **self.robots}  # (those not added yet count where they go)
        for host in {**planned, **self.placed}.values():
            count[host] += 1
        return min(count, key=lambda h: count[h])  # the first of the least loaded

    def add_robot(self, name: str, *, pos: Pos = (0.0, 0.0), mac: str | None = None,
                  runtime: str | None = None) -> SpanRobot:  # fmt: skip
        """A robot on its host (numbered across the lab), known to the other hosts by its MAC
        and position."""
        return self.add_robot_batch([(name, pos, mac, runtime)])[0]

    def add_robot_batch(
        self, specs: Sequence[tuple[str, Pos, str | None, str | None]]
    ) -> list[SpanRobot]:
        """Robots (name, position, MAC or None, runtime or None), each on its host: every
        host adds its own at once, then every host learns the others' (two requests a host,
        the hosts asked in parallel)."""
        if not self.parts:
            raise NetlabError(f"lab {self.name} is not up")
        names = [spec[0] for spec in specs]
        again = sorted({n for n in names if n in self.placed or names.count(n) > 1})
        if again:
            raise NetlabError(f"lab {self.name} already has robots {', '.join(again)}")
        mine: dict[str, list[dict[str, Any]]] = {dest: [] for dest in self.parts}
        for name, pos, mac, runtime in specs:
            host = self._place(name)
            self.placed[name] = host  # (counted by the next one's placement)
            self.index[name] = len(self.index)
            mine[host].append({"name": name, "index": self.index[name], "pos": list(pos),
                               "mac": mac, "runtime": runtime})  # fmt: skip
        got = self._on_hosts({d: ("add_robots", {"robots": rs}) for d, rs in mine.items() if rs})
        for dest, infos in got.items():
            for info, spec in zip(infos, mine[dest], strict=True):
                name = spec["name"]
                self.macs[name] = info["mac"]
                self._robots[name] = SpanRobot(name, dest, info["ns"], info["mac"],
                                               info["iface"], Path(info["log"]))  # fmt: skip
        where = {spec[0]: spec[1] for spec in specs}
        remotes = {
            dest: [{"name": n, "mac": self.macs[n], "pos": list(where[n])}
                   for n in names if self.placed[n] != dest]
            for dest in self.parts
        }  # fmt: skip
        self._on_hosts({d: ("add_remotes", {"remotes": rs}) for d, rs in remotes.items() if rs})
        return [self._robots[n] for n in names]

    def _on_hosts(self, calls: Mapping[str, tuple[str, dict[str, Any]]]) -> dict[str, Any]:
        """One request to each of these hosts, in parallel; their answers (HostError naming
        every host that failed, once all have answered)."""
        with ThreadPoolExecutor(max_workers=max(1, len(calls))) as pool:
            futures = {
                dest: pool.submit(self.parts[dest].call, op, **kw)
                for dest, (op, kw) in calls.items()
            }
        out: dict[str, Any] = {}
        failed = []
        for dest, future in futures.items():
            try:
                out[dest] = future.result()
            except HostError as exc:
                failed.append(str(exc))
        if failed:
            raise HostError("; ".join(failed))
        return out

    def robot(self, ref: str) -> SpanRobot:
        try:
            return self._robots[ref]
        except KeyError:
            raise NetlabError(f"lab {self.name} has no robot {ref!r}") from None

    def client(self, robot: str) -> AgentClient:
        return AgentClient(self.host_of(robot), robot)

    # -- daemons: on their robot's host ---------------------------------------------------------

    def _mine(self, refs: Iterable[str] | None) -> dict[str, list[str]]:
        names = list(self.placed) if refs is None else list(refs)
        for name in names:
            self.host_of(name)
        return {d: [n for n in names if self.placed[n] == d] for d in self.parts}

    def start_all(
        self, refs: Iterable[str] | None = None, *, timeout: float = 60.0, **options: Any
    ) -> None:
        """Start the robots' daemons on every host at once; return when all are healthy
        (HostError naming every host that failed, once all have answered)."""
        self._on_hosts({
            dest: ("start_all", {"robots": mine, "timeout": timeout, "options": options})
            for dest, mine in self._mine(refs).items() if mine
        })  # fmt: skip

    def start(self, ref: str, *, timeout: float = 30.0, **options: Any) -> None:
        self.host_of(ref).call("start", robot=ref, timeout=timeout, options=options)

    def restart(self, ref: str, *, timeout: float = 30.0, **options: Any) -> None:
        self.host_of(ref).call("restart", robot=ref, timeout=timeout, options=options)

    def stop(self, ref: str, timeout: float = 10.0) -> int:
        return int(self.host_of(ref).call("stop", robot=ref, timeout=timeout))

    def kill(self, ref: str) -> None:
        self.host_of(ref).call("kill", robot=ref)

    def daemons_ended(self) -> dict[str, str]:
        ended: dict[str, str] = {}
        for part in self.parts.values():
            with contextlib.suppress(HostError):
                ended.update(part.call("daemons_ended"))
        return ended

    def usage(self, names: Iterable[str]) -> dict[str, procstat.Usage]:
        """A /proc reading of each running daemon's process tree, on its host (a window's
        two readings of a robot come from the same host's clock)."""
        out: dict[str, procstat.Usage] = {}
        span: dict[str, dict[str, int]] = {}
        for dest, mine in self._mine(names).items():
            got = self.parts[dest].call("usage", robots=mine)
            span[dest] = got["span"]
            for name, u in got["robots"].items():
                out[name] = procstat.Usage(float(u[0]), float(u[1]), int(u[2]), int(u[3]),
                                           int(u[4]))  # fmt: skip
        self.span_readings.append((time.time(), span))
        return out

    def fetch_log(self, ref: str) -> str | None:
        """The robot's daemon's log (its last 8 MiB), read on its host; None if it has none."""
        got = self.host_of(ref).call("read_log", robot=ref)
        return None if got is None else str(got)

    # -- captures: tcpdumps on every host, fetched and put on this clock at the end ---------------

    def start_captures(self, mode: str, names: Sequence[str]) -> int:
        """tcpdump on every host: its medium ("all", "medium": only the frames its own robots
        send, so that each frame is captured once) and its robots ("all", "robots"); how
        many.  `stop_captures` fetches them."""
        self._captures = {}
        count = 0
        for dest, part in self.parts.items():
            targets = ["medium"] if mode in ("all", "medium") else []
            if mode in ("all", "robots"):
                targets += [n for n in names if self.placed.get(n) == dest]
            if targets:
                self._captures[dest] = dict(part.call("captures_start", targets=targets))
                count += len(targets)
        return count

    def stop_captures(self, run_dir: Path) -> list[str]:
        """Stop every host's tcpdumps and bring their pcaps into `run_dir`: each robot's as
        ``<robot>.pcap``, the hosts' media merged into ``medium.pcap``, every time put on this
        machine's clock (each host's measured offset taken off); what went wrong, said."""
        from netlab import pcap
        from netlab.capture import sidecar_path

        said: list[str] = []
        media: list[tuple[Path, float]] = []
        fetched = run_dir / ".hosts"
        for dest, paths in self._captures.items():
            part = self.parts[dest]
            try:
                part.call("captures_stop")
            except HostError as exc:
                said.append(str(exc))
            offset = self.clocks.get(dest, (0.0, 0.0))[0]
            for label, path in paths.items():
                local = fetched / dest / f"{label}.pcap"
                try:
                    self._fetch(part, path, local)
                    self._fetch(part, str(sidecar_path(Path(path))), sidecar_path(local))
                except HostError as exc:
                    said.append(f"{label}'s capture on {dest}: {exc}")
                    continue
                if label == "medium":
                    media.append((local, offset))
                else:
                    pcap.merge([(local, offset)], run_dir / f"{label}.pcap")
                    sidecar_path(local).replace(sidecar_path(run_dir / f"{label}.pcap"))
        if media:
            pcap.merge(media, run_dir / "medium.pcap")
            sidecar_path(media[0][0]).replace(sidecar_path(run_dir / "medium.pcap"))
        self._captures = {}
        shutil.rmtree(fetched, ignore_errors=True)
        return said

    @staticmethod
    def _fetch(part: Part, path: str, into: Path) -> None:
        into.parent.mkdir(parents=True, exist_ok=True)
        with into.open("wb") as f:
            while chunk := base64.b64decode(part.call("read_file", path=path, offset=f.tell(),
                                                      size=FILE_CHUNK)):  # fmt: skip
                f.write(chunk)

    # -- the medium: the same map on every host --------------------------------------------------

    def _medium(self, host: str | None, op: str, **kw: Any) -> None:
        if self._pending is not None:
            self._pending.append((host, {"op": op, **kw}))
        elif host is not None:
            self.parts[host].call(op, **kw)
        else:
            self._everywhere(op, **kw)

    @contextlib.contextmanager
    def batch(self) -> Iterator[None]:
        """Every medium change made in the body sent at its end, as one change per host."""
        if self._pending is not None:
            yield
            return
        self._pending = []
        try:
            yield
            pending = self._pending
        finally:
            self._pending = None
        for dest, part in self.parts.items():
            ops = [op for host, op in pending if host in (None, dest)]
            if ops:
                part.call("batch", ops=ops)

    def _everywhere(self, op: str, **kw: Any) -> None:
        for part in self.parts.values():
            part.call(op, **kw)

    def move(self, robot: str, pos: Pos) -> None:
        self.host_of(robot)
        self._medium(None, "move", robot=robot, pos=list(pos))

    def partition(self, groups: Iterable[Iterable[str]]) -> None:
        self._medium(None, "partition", groups=[list(g) for g in groups])

    def merge(self) -> None:
        self._medium(None, "merge")

    def set_pair_quality(self, a: str, b: str, *, loss: float | None, both: bool = True) -> None:
        self.host_of(a), self.host_of(b)
        self._medium(None, "set_pair_quality", a=a, b=b, loss=loss, both=both)

    def shape(self, ref: str, **params: Any) -> str:
        """Shape the robot's link, on its host (what the shaping became there, said)."""
        host = self.placed.get(ref)
        if host is None:
            raise NetlabError(f"lab {self.name} has no robot {ref!r}")
        if self._pending is not None:
            self._medium(host, "shape", robot=ref, params=params)
            return "(applied with the batch)"
        return str(self.parts[host].call("shape", robot=ref, params=params))

    def links(self) -> Links:
        """Ground truth: each linked (sender, receiver) pair with its loss in %, as the
        receiver's host judges it."""
        out: Links = {}
        for part in self.parts.values():
            for a, b, loss in part.call("links"):
                out[(str(a), str(b))] = float(loss)
        return out

    def positions(self) -> dict[str, Pos]:
        if not self.parts:
            return {}
        first = next(iter(self.parts.values()))
        return {n: (float(p[0]), float(p[1])) for n, p in first.call("positions").items()}

    def neighbors(self, robot: str) -> set[str]:
        return set(self.host_of(robot).call("neighbors", robot=robot))

    def down(self, keep_workdir: bool = False) -> dict[str, str]:
        """Every host's share down; the folders kept on each host (`keep_workdir`), or
        HostError naming the hosts that could not be reached."""
        failed = []
        kept: dict[str, str] = {}
        for dest, part in self.parts.items():
            try:
                if part.proc.poll() is not None:
                    raise HostError(f"host {dest}: down: {part._ended()}")
                if folder := part.call("down", keep_workdir=keep_workdir):
                    kept[dest] = str(folder)
            except HostError as exc:
                failed.append(str(exc))
            finally:
                part.close()
                part.ssh.close()
        self.parts.clear()
        if failed:
            raise HostError("; ".join(failed))
        return kept


def check_medium(lab: str, medium: str) -> None:
    """NetlabError unless `medium` can span hosts (the wired one: a radio lives in one VM)."""
    if medium != "wired":
        raise NetlabError(
            f"lab {lab}: a lab across hosts runs the wired medium, not medium = {medium!r} "
            "(radios are one kernel's: mac80211_hwsim)"
        )


def span_backend(
    hosts: Sequence[tuple[Ssh, str | None]],
    *,
    robots: Mapping[str, str] | None = None,
    workdir: str | None = None,
    env: Mapping[str, str] | None = None,
    port: int = DEFAULT_PORT,
) -> Backend:
    """The scenario engine's backend for runs on a lab across `hosts`: each run's lab is a
    `SpanLab` (robots placed by `robots`, else spread), its robots' APIs asked through their
    hosts' agents, its captures made on every host (`SpanLab.start_captures`)."""
    hosts = list(hosts)
    placed = dict(robots or {})

    def make(spec: LabSpec) -> LabLike:
        check_medium(spec.name, spec.medium)
        return SpanLab(spec.name, hosts, place=placed, seed=spec.seed, fleet=spec.fleet,
                       range_model=spec.range_model, workdir=workdir, runtime=spec.runtime,
                       image=spec.image if spec.runtime == "docker" else None,
                       addressing=spec.addressing, port=port, env=dict(env or {}))  # fmt: skip

    def connect(lab: LabLike, robot: str, timeout: float) -> ClientLike:
        # the robot's host agent asks its daemon with its own lab's client and timeout
        assert isinstance(lab, SpanLab)
        return lab.client(robot)

    return Backend(make_lab=make, connect=connect)


def scenario_backend(
    sc: Scenario,
    *,
    hosts: Sequence[str] = (),
    ssh_config: Path | None = None,
    python: str = "python3",
    env: Mapping[str, str] | None = None,
) -> Backend:
    """The backend for a run of `sc` across `hosts` (default: the hosts its [hosts] names),
    reached by ssh with `ssh_config` and running netlab with `python` there; the robots `sc`
    places on one of these hosts stay there, the others are spread."""
    dests = list(hosts) or list(sc.hosts)
    if not dests:
        raise NetlabError(f"scenario {sc.name}: no hosts to run it across")
    placement = {r: h for r, h in sc.placement().items() if h in dests}
    sshs: list[tuple[Ssh, str | None]] = [(Ssh(d, ssh_config, python), None) for d in dests]
    return span_backend(sshs, robots=placement, env=env)
