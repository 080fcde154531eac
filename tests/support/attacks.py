"""Tools of the attack suite (tests/ns/test_attacks.py): a patient outsider on a lab's medium
that records, relays and replays; taps that prove what reached a robot; samplers of what a robot
lists and says of its health while an attack runs.

- `hub(lab)`: the lab's bridge floods every frame to every port, as a radio does: the outsider
  hears the robots' unicasts to each other, not only their multicasts.
- `Outsider`: sdfr/testing/outsider.py in a namespace of the lab (`send`, `record`, `replay`,
  `relay`), driven from the test.
- `Tap`: tcpdump (netlab's `Capture`) on robots' interfaces; the datagrams each one saw, read
  back with `read_pcap`.
- `Sightings`: a thread sampling one robot's list (or its /health) at 10 Hz.
- `rejects`, `metric`: counters from a robot's /metrics.
"""

from __future__ import annotations

import contextlib
import json
import re
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

from netlab import kernel, naming
from netlab.capture import Capture, start_all, stop_all
from netlab.lab import Lab
from sdfr import wire
from sdfr.client import Client
from sdfr.testing.outsider import udp_of
from tests.support.waiting import poll

ROOT = Path(__file__).resolve().parents[2]
GROUP = wire.DEFAULT_GROUP
PORT = wire.DEFAULT_PORT


def hub(lab: Lab) -> None:
    """Make the lab's bridge forget where every MAC address is (ageing time 0): it then floods
    every frame to every port the medium rules allow, as a radio carries every frame to all in
    range, and the outsider hears what the robots unicast to each other."""
    kernel.run_in_ns(
        lab.medium.ns,
        ["ip", "link", "set", "dev", naming.BRIDGE, "type", "bridge", "ageing_time", "0"],
        f"making the bridge of {lab.name} a hub",
    )


# -- datagrams -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Datagram:
    """One UDP datagram as heard on a wire: when (unix time), from and to where, its bytes."""

    t: float
    src: str
    sport: int
    dst: str
    dport: int
    data: bytes

    @property
    def kind(self) -> str:
        """The message class, lower case (``alive``, ``response``, ...; ``reject`` when the
        codec refuses it)."""
        return type(wire.decode(self.data)).__name__.lower()

    @property
    def robot(self) -> str | None:
        """The robot id the datagram speaks for, if it names one."""
        msg = wire.decode(self.data)
        origin = getattr(msg, "origin", None)
        return None if origin is None else str(origin.robot_id)

    def to_json(self) -> dict[str, Any]:
        return {
            "t": self.t,
            "src": f"{self.src}:{self.sport}",
            "dst": f"{self.dst}:{self.dport}",
            "hex": self.data.hex(),
        }

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> Datagram:
        src, sport = str(obj["src"]).rsplit(":", 1)
        dst, dport = str(obj["dst"]).rsplit(":", 1)
        return cls(float(obj["t"]), src, int(sport), dst, int(dport), bytes.fromhex(obj["hex"]))


_PCAP_MAGIC = {b"\xd4\xc3\xb2\xa1": "<", b"\xa1\xb2\xc3\xd4": ">"}  # microsecond pcaps
_PCAP_NS_MAGIC = {b"\x4d\x3c\xb2\xa1": "<", b"\xa1\xb2\x3c\x4d": ">"}
LINKTYPE_ETHERNET = 1


def read_pcap(path: Path) -> list[Datagram]:
    """The whole IPv4 UDP datagrams of a pcap (Ethernet link type), in file order."""
    raw = Path(path).read_bytes()
    if len(raw) < 24:
        return []  # stopped before tcpdump wrote its header: nothing was captured
    order = _PCAP_MAGIC.get(raw[:4]) or _PCAP_NS_MAGIC.get(raw[:4])
    if order is None:
        raise ValueError(f"{path} is not a pcap file")
    scale = 1e-9 if raw[:4] in _PCAP_NS_MAGIC else 1e-6
    (link,) = struct.unpack(order + "I", raw[20:24])
    if link != LINKTYPE_ETHERNET:
        raise ValueError(f"{path}: link type {link}, not Ethernet")
    out = []
    pos = 24
    while pos + 16 <= len(raw):
        sec, frac, caplen, _ = struct.unpack(order + "IIII", raw[pos : pos + 16])
        frame = raw[pos + 16 : pos + 16 + caplen]
        pos += 16 + caplen
        got = udp_of(frame)
        if got is not None:
            (src, sport), (dst, dport), data = got
            out.append(Datagram(sec + frac * scale, src, sport, dst, dport, data))
    return out


# -- the outsider --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Step:
    """One datagram of a replay: `at` seconds after the replay starts, to `to` (an address,
    or ``ip:port``), from `spoof` (None: the outsider's own address)."""

    at: float
    data: bytes
    to: str
    spoof: str | None = None

    def to_json(self) -> dict[str, Any]:
        return {"at": self.at, "hex": self.data.hex(), "to": self.to, "spoof": self.spoof}


@dataclass
class Recording:
    """What the outsider heard (complete once its `record` block has ended)."""

    path: Path
    datagrams: list[Datagram] = field(default_factory=list)

    def read(self) -> list[Datagram]:
        """What was heard so far (the file grows while the recorder runs)."""
        out = []
        with contextlib.suppress(FileNotFoundError), open(self.path) as f:
            for line in f:
                if line.endswith("\n"):
                    out.append(Datagram.from_json(json.loads(line)))
        return out


class Outsider:
    """sdfr/testing/outsider.py run in the lab's namespace `name`: no daemon, no key; it
    knows only the public wire format."""

    def __init__(self, lab: Lab, name: str = "x9") -> None:
        self.lab, self.name = lab, name
        self.dir = Path(tempfile.mkdtemp(prefix=f"outsider-{lab.name}-", dir=lab.workdir))

    @property
    def ip(self) -> str:
        return self.lab.robot(self.name).ip

    def argv(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "sdfr.testing.outsider", *args]

    def run(self, *args: str, timeout: float = 60) -> str:
        done = self.lab.exec(self.name, self.argv(*args), cwd=ROOT, timeout=timeout)
        if done.returncode != 0:
            raise AssertionError(f"outsider {' '.join(args[:3])}: {done.stderr or done.stdout}")
        return str(done.stdout)

    def popen(self, *args: str) -> subprocess.Popen[str]:
        return self.lab.popen(
            self.name, self.argv(*args), cwd=ROOT, stdout=subprocess.PIPE, text=True
        )

    def send(self, data: bytes, to: str = GROUP, spoof: str | None = None) -> None:
        args = ["send", "--to", to, data.hex()]
        if spoof is not None:
            args[1:1] = ["--spoof", spoof]
        self.run(*args)

    def _ready(self, proc: subprocess.Popen[str], what: str) -> None:
        """Wait for a listening command's ``ready`` line (it hears from then on)."""
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if line.strip() != "ready":
            proc.kill()
            raise AssertionError(f"outsider {what} did not start: {line!r}, {proc.wait()}")

    @contextlib.contextmanager
    def record(self, name: str = "heard") -> Iterator[Recording]:
        """Everything the outsider hears while the block runs (`hub` first, for unicasts)."""
        rec = Recording(self.dir / f"{name}.jsonl")
        proc = self.popen("record", "--out", str(rec.path))
        try:
            self._ready(proc, "record")
            yield rec
        finally:
            proc.terminate()
            proc.communicate(timeout=10)
        rec.datagrams = rec.read()

    def replay(self, steps: Sequence[Step]) -> Replay:
        """Start sending `steps` on their timeline; `Replay.wait` for the end."""
        plan = self.dir / f"plan-{time.monotonic_ns()}.jsonl"
        plan.write_text("".join(json.dumps(s.to_json()) + "\n" for s in steps))
        return Replay(self.popen("replay", "--plan", str(plan)), len(steps))

    def relay(
        self, sender: str, to: str, *, spoof: str | None = None, seconds: float
    ) -> subprocess.Popen[str]:
        """Start relaying what `sender` sends on to `to` (from `spoof`), for `seconds`; the
        process prints ``{"relayed": n}`` at its end."""
        args = ["relay", "--sender", sender, "--to", to, "--seconds", str(seconds)]
        if spoof is not None:
            args += ["--spoof", spoof]
        proc = self.popen(*args)
        self._ready(proc, "relay")
        return proc


class Replay:
    """A replay running in the outsider's namespace."""

    def __init__(self, proc: subprocess.Popen[str], steps: int) -> None:
        self.proc, self.steps = proc, steps
        self.started = time.time()
        #: Unix time each step went out.
        self.sent: list[float] = []

    def wait(self, timeout: float) -> Replay:
        out, _ = self.proc.communicate(timeout=timeout)
        self.sent = [json.loads(line)["t"] for line in out.splitlines() if line.startswith("{")]
        if self.proc.returncode != 0 or len(self.sent) != self.steps:
            raise AssertionError(
                f"the replay sent {len(self.sent)} of {self.steps} datagrams "
                f"(exit {self.proc.returncode})"
            )
        return self

    @property
    def first(self) -> float:
        return self.sent[0]

    @property
    def last(self) -> float:
        return self.sent[-1]


# -- what robots saw -----------------------------------------------------------------------


class Tap:
    """tcpdump on the interfaces of `robots` while the block runs; `got[robot]` then holds the
    datagrams each interface carried (both ways)."""

    def __init__(self, lab: Lab, robots: Iterable[str], folder: Path | None = None) -> None:
        self.lab = lab
        self.robots = list(robots)
        self.folder = folder or Path(tempfile.mkdtemp(prefix="tap-", dir=lab.workdir))
        self.got: dict[str, list[Datagram]] = {}
        self._caps = [
            Capture(
                lab.robot(r).ns,
                naming.ROBOT_IFACE,
                self.folder / f"{r}.pcap",
                bpf=f"udp port {PORT}",
                label=r,
            )
            for r in self.robots
        ]

    def __enter__(self) -> Tap:
        start_all(self._caps)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is not None:
            for cap in self._caps:
                cap.kill()
            return
        stop_all(self._caps)
        self.got = {r: read_pcap(self.folder / f"{r}.pcap") for r in self.robots}

    def arrived(self, robot: str, data: Iterable[bytes], src: str) -> int:
        """How many of the datagrams `data` reached `robot` from `src` (each counted once)."""
        wanted = Counter(data)
        found = 0
        for d in self.got[robot]:
            if d.src == src and wanted[d.data] > 0:
                wanted[d.data] -= 1
                found += 1
        return found

    def between(self, robot: str, src: str, dst: str) -> list[Datagram]:
        """The datagrams from `src` to `dst` on `robot`'s interface."""
        return [d for d in self.got[robot] if d.src == src and d.dst == dst]


class Sightings:
    """Samples `probe(client)` on `robot` every `step` seconds in a thread while the block runs:
    `samples` is [(unix time, value)]."""

    def __init__(
        self, lab: Lab, robot: str, probe: Callable[[Client], Any], step: float = 0.1
    ) -> None:
        self.client = Client(unix_socket=lab.robot(robot).api_socket, timeout=2.0)
        self.probe, self.step = probe, step
        self.samples: list[tuple[float, Any]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while True:
            with contextlib.suppress(Exception):
                self.samples.append((time.time(), self.probe(self.client)))
            if self._stop.wait(self.step):
                return

    def __enter__(self) -> Sightings:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        self.client.close()

    def when(self, pred: Callable[[Any], bool]) -> list[tuple[float, Any]]:
        return [(t, v) for t, v in self.samples if pred(v)]

    def seconds(self, pred: Callable[[Any], bool]) -> float:
        """About how long `pred` held: samples where it did times the sampling period."""
        if len(self.samples) < 2:
            return 0.0
        period = (self.samples[-1][0] - self.samples[0][0]) / (len(self.samples) - 1)
        return len(self.when(pred)) * period


def listed_at(robot_id: str) -> Callable[[Client], str | None]:
    """A probe: the address at which a robot lists `robot_id`, None when it does not."""

    def probe(client: Client) -> str | None:
        for n in client.neighbors():
            if n["robot_id"] == robot_id:
                return str(n["address"])
        return None

    return probe


def health_of(client: Client) -> tuple[str, tuple[str, ...]]:
    """A probe: /health's status and warnings."""
    h = client.health()
    return str(h["status"]), tuple(h.get("warnings", ()))


# -- counters ------------------------------------------------------------------------------


def rejects(lab: Lab, robot: str) -> Counter[str]:
    """sdfr_rejects_total by reason."""
    text = lab.client(robot).metrics()
    return Counter(
        {
            m.group(1): int(float(m.group(2)))
            for m in re.finditer(r'^sdfr_rejects_total\{reason="([^"]+)"\} (\S+)$', text, re.M)
        }
    )


def metric(lab: Lab, robot: str, name: str) -> float:
    """One unlabelled sample of /metrics (0 when absent)."""
    m = re.search(rf"^{re.escape(name)} (\S+)$", lab.client(robot).metrics(), re.M)
    return float(m.group(1)) if m else 0.0


def grown(before: Counter[str], after: Counter[str]) -> Counter[str]:
    """What each counter gained."""
    return Counter({k: after[k] - before.get(k, 0) for k in after if after[k] > before.get(k, 0)})


def wait_until_listed(lab: Lab, robot: str, others: Iterable[str], timeout: float) -> None:
    want = set(others)
    poll(
        f"{robot} lists {sorted(want)}",
        lambda: want <= {n["robot_id"] for n in lab.client(robot).neighbors()},
        timeout,
    )
