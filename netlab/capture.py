"""Packet capture to pcap with tcpdump, inside a network namespace.

`Capture(netns, iface, path)` runs ``tcpdump -i IFACE -w PATH -U -s 2048 BPF`` in namespace
`netns` (``ip netns exec``; `None` means the current namespace).  `start()` returns once tcpdump
says it is listening, so nothing sent afterwards is missed; `stop()` interrupts it (SIGINT) and
waits, so the pcap ends with whole records.  The process runs in its own process group and is
only ever signalled by its own pid; on any error it is killed before the error propagates.

Next to the pcap, ``PATH.json`` records what was captured: namespace, interface, its MAC and
addresses, whether it is a bridge (the medium) or a robot's interface, and tcpdump's counters.
`netlab.analysis` reads it to tell frames the interface sent from frames it received.

If the process that started a capture is killed, tcpdump keeps running inside its namespace;
whoever removes the namespace must kill what runs in it (the lab's teardown does).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from netlab.errors import NetlabError

__all__ = [
    "DEFAULT_BPF",
    "SNAPLEN",
    "Capture",
    "CaptureError",
    "CaptureInfo",
    "CaptureStats",
    "sidecar_path",
    "start_all",
    "stop_all",
]

#: SDfR datagrams and ARP (address conflict detection), and nothing else.
DEFAULT_BPF = "udp port 1900 or arp"
#: Bytes kept per frame: more than the largest SDfR frame (1,400 bytes of UDP payload + 42).
SNAPLEN = 2048
READY_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 5.0
_LISTENING = "listening on "

log = logging.getLogger(__name__)


class CaptureError(NetlabError):
    """A capture could not be started, or did not end cleanly; the message says why."""


@dataclass(frozen=True, slots=True)
class CaptureStats:
    """tcpdump's own counters, printed when it exits (None when it did not print them)."""

    captured: int | None = None
    received: int | None = None  # "received by filter"
    dropped: int | None = None  # "dropped by kernel": frames lost, the pcap is incomplete


@dataclass(slots=True)
class CaptureInfo:
    """What ``PATH.json`` holds about a capture."""

    netns: str | None
    iface: str
    label: str
    role: str  # "medium" for a bridge, "robot" otherwise
    mac: str | None
    addresses: list[str]
    bpf: str
    snaplen: int
    started: float | None = None  # time.time() once tcpdump listens
    stopped: float | None = None
    stats: CaptureStats = field(default_factory=CaptureStats)

    def to_json(self) -> dict[str, object]:
        return asdict(self)

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> CaptureInfo:
        stats = obj.get("stats") or {}
        return cls(
            netns=obj.get("netns"),
            iface=str(obj.get("iface", "")),
            label=str(obj.get("label", "")),
            role=str(obj.get("role", "robot")),
            mac=obj.get("mac"),
            addresses=[str(a) for a in obj.get("addresses", [])],
            bpf=str(obj.get("bpf", "")),
            snaplen=int(obj.get("snaplen", SNAPLEN)),
            started=obj.get("started"),
            stopped=obj.get("stopped"),
            stats=CaptureStats(
                captured=stats.get("captured"),
                received=stats.get("received"),
                dropped=stats.get("dropped"),
            ),
        )


#: mac80211_hwsim's monitor interface, in the initial namespace: every frame any of its radios
#: sends, with a radiotap header.
AIR_MONITOR = "hwsim0"


def air_monitor() -> str:
    """Bring hwsim's monitor interface up (the radio medium's capture point); its name.
    CaptureError if there is none (mac80211_hwsim is not loaded)."""
    try:
        res = subprocess.run(
            ["ip", "link", "set", AIR_MONITOR, "up"],
            capture_output=True,
            text=True,
            timeout=10,
            stdin=subprocess.DEVNULL,
        )
    except (OSError, subprocess.SubprocessError) as exc:
        raise CaptureError(f"cannot bring {AIR_MONITOR} up: {exc}") from None
    if res.returncode != 0:
        raise CaptureError(
            f"cannot capture on the air: no {AIR_MONITOR} ({res.stderr.strip()}); is "
            "mac80211_hwsim loaded?"
        )
    return AIR_MONITOR


def sidecar_path(pcap: Path) -> Path:
    """Where the metadata of the capture written to `pcap` lives: ``<pcap>.json``."""
    return pcap.with_name(pcap.name + ".json")


class Capture:
    """tcpdump on `iface` in namespace `netns`, writing `path`; a context manager.

    `label` names the capture in analyses and reports (default: the file name without
    extension, e.g. ``r1`` for ``r1.pcap``).
    """

    def __init__(
        self,
        netns: str | None,
        iface: str,
        path: Path,
        *,
        bpf: str = DEFAULT_BPF,
        label: str | None = None,
        snaplen: int = SNAPLEN,
        ready_timeout: float = READY_TIMEOUT_S,
        stop_timeout: float = STOP_TIMEOUT_S,
        tcpdump: str = "tcpdump",
    ) -> None:
        if not iface or "/" in iface or iface != iface.strip():
            raise ValueError(f"not an interface name: {iface!r}")
        self.netns = netns
        self.iface = iface
        self.path = Path(path)
        self.bpf = bpf
        self.label = label if label is not None else self.path.stem
        self.snaplen = snaplen
        self.ready_timeout = ready_timeout
        self.stop_timeout = stop_timeout
        self.tcpdump = tcpdump
        self.info: CaptureInfo | None = None
        self.stats: CaptureStats | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._reader: threading.Thread | None = None
        self._lines: list[str] = []
        self._settled = threading.Event()  # tcpdump listens, or its stderr closed
        self._listening = False

    def __repr__(self) -> str:
        where = f"{self.netns}:" if self.netns else ""
        return f"<Capture {where}{self.iface} -> {self.path} pid={self.pid}>"

    @property
    def where(self) -> str:
        """`iface` in `netns`, for messages."""
        return f"{self.iface} in namespace {self.netns}" if self.netns else self.iface

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    # -- life cycle -----------------------------------------------------------------------
    def __enter__(self) -> Capture:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.stop()
        else:  # do not hide the original error behind a capture error
            with contextlib.suppress(CaptureError):
                self.stop()

    def start(self) -> Capture:
        """Start tcpdump and return once it captures; CaptureError if it cannot."""
        self._launch()
        self._await_ready(time.monotonic() + self.ready_timeout)
        return self

    def stop(self) -> CaptureStats:
        """Interrupt tcpdump and wait for it; its counters.  Idempotent.

        CaptureError if tcpdump had already failed, did not stop within `stop_timeout` (it is
        then killed and the pcap may end in a partial record) or reported dropped frames.
        """
        proc = self._proc
        if proc is None:
            raise CaptureError(f"capture on {self.where} was never started")
        if self.stats is not None:
            return self.stats
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGINT)
        return self._finish(time.monotonic() + self.stop_timeout)

    def kill(self) -> None:
        """Kill tcpdump's process group at once (it is ours: it runs in its own session)."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        if self._reader is not None:
            self._reader.join(timeout=1.0)

    # -- internals ------------------------------------------------------------------------
    def argv(self) -> list[str]:
        """The tcpdump command line (a path of "-" writes the pcap to standard output)."""
        argv = [
            self.tcpdump,
            "-i",
            self.iface,
            "-w",
            str(self.path),
            "-U",  # write each packet as it arrives: the file is always whole records
            "--immediate-mode",  # deliver at once, so a SIGINT loses nothing in kernel buffers
            "-s",
            str(self.snaplen),
            # Keep root: files owned like the rest of the run, and paths tcpdump's own user
            # could not write to still work.
            "-Z",
            "root",
        ]
        if self.bpf:
            argv.append(self.bpf)
        if self.netns is not None:
            argv = ["ip", "netns", "exec", self.netns, *argv]
        return argv

    def _launch(self) -> None:
        if self._proc is not None:
            raise CaptureError(f"capture on {self.where} already started")
        if shutil.which(self.tcpdump) is None:
            raise CaptureError(
                f"{self.tcpdump} not found on PATH; install it (Debian: apt-get install tcpdump)"
            )
        if self.netns is not None and shutil.which("ip") is None:
            raise CaptureError("the ip command (iproute2) is needed to enter a namespace")
        self.info = self._describe_iface()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CaptureError(f"cannot create {self.path.parent}: {exc}") from None
        try:
            self._proc = subprocess.Popen(
                self.argv(),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                start_new_session=True,
            )
        except OSError as exc:
            raise CaptureError(f"cannot run tcpdump on {self.where}: {exc}") from None
        stderr = self._proc.stderr
        assert stderr is not None
        self._reader = threading.Thread(
            target=self._read_stderr, args=(stderr,), name=f"tcpdump-{self.label}", daemon=True
        )
        self._reader.start()

    def _read_stderr(self, stream: IO[bytes]) -> None:
        try:
            for raw in stream:
                line = raw.decode(errors="replace").rstrip()
                self._lines.append(line)
                if not self._listening and _LISTENING in line:
                    self._listening = True
                    self._settled.set()
        finally:
            stream.close()
            self._settled.set()

    def _await_ready(self, deadline: float) -> None:
        try:
            if not self._settled.wait(max(0.0, deadline - time.monotonic())):
                raise CaptureError(
                    f"tcpdump on {self.where} did not start listening within "
                    f"{self.ready_timeout:g} s{self._stderr_tail()}"
                )
            if not self._listening:
                proc = self._proc
                assert proc is not None
                try:
                    code: int | None = proc.wait(timeout=self.stop_timeout)
                except subprocess.TimeoutExpired:
                    code = None
                raise CaptureError(self._explain_failure(code))
        except BaseException:
            self.kill()
            raise
        assert self.info is not None
        self.info.started = time.time()
        self._write_sidecar()

    def _finish(self, deadline: float) -> CaptureStats:
        proc = self._proc
        assert proc is not None
        try:
            code = proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            self.kill()
            self._record_stats()
            raise CaptureError(
                f"tcpdump on {self.where} did not stop within {self.stop_timeout:g} s of SIGINT "
                f"and was killed; {self.path} may end in a partial record"
            ) from None
        if self._reader is not None:
            self._reader.join(timeout=self.stop_timeout)
        stats = self._record_stats()
        if code != 0:
            raise CaptureError(
                f"tcpdump on {self.where} failed (exit status {code}){self._stderr_tail()}"
            )
        if stats.dropped:
            log.warning(
                "tcpdump on %s dropped %d frames: %s is incomplete",
                self.where,
                stats.dropped,
                self.path,
            )
        return stats

    def _record_stats(self) -> CaptureStats:
        self.stats = _parse_stats(self._lines)
        if self.info is not None:
            self.info.stopped = time.time()
            self.info.stats = self.stats
            with contextlib.suppress(OSError):
                self._write_sidecar()
        return self.stats

    def _write_sidecar(self) -> None:
        assert self.info is not None
        target = sidecar_path(self.path)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(json.dumps(self.info.to_json(), indent=2) + "\n")
        tmp.replace(target)

    def _describe_iface(self) -> CaptureInfo:
        """The interface's MAC, addresses and kind; CaptureError if namespace or iface is
        missing (tcpdump's own messages for these are less clear)."""
        if shutil.which("ip") is None:  # no iproute2 and no namespace: tcpdump alone will do
            return CaptureInfo(
                self.netns, self.iface, self.label, "robot", None, [], self.bpf, self.snaplen
            )
        argv = ["ip", "-j", "-d"]
        if self.netns is not None:
            argv += ["-n", self.netns]
        argv += ["addr", "show", "dev", self.iface]
        try:
            res = subprocess.run(
                argv, capture_output=True, text=True, timeout=10, stdin=subprocess.DEVNULL
            )
        except (OSError, subprocess.SubprocessError) as exc:
            raise CaptureError(f"cannot inspect {self.where}: {exc}") from None
        if res.returncode != 0:
            err = res.stderr.strip()
            if "network namespace" in err:
                raise CaptureError(f"network namespace {self.netns!r} does not exist ({err})")
            if "does not exist" in err:
                raise CaptureError(f"no interface {self.where} ({err})")
            raise CaptureError(f"cannot inspect {self.where}: {err or res.returncode}")
        try:
            (link,) = json.loads(res.stdout)
        except ValueError:
            raise CaptureError(f"unexpected output of {' '.join(argv)}: {res.stdout!r}") from None
        kind = (link.get("linkinfo") or {}).get("info_kind")
        return CaptureInfo(
            netns=self.netns,
            iface=self.iface,
            label=self.label,
            # A bridge (the wired medium) or hwsim's monitor (the radio medium, radiotap)
            # sees every frame once; a robot's interface, its own.
            role="medium"
            if kind == "bridge" or "radiotap" in link.get("link_type", "")
            else "robot",
            mac=link.get("address") if link.get("link_type") == "ether" else None,
            addresses=[
                f"{a['local']}/{a['prefixlen']}"
                for a in link.get("addr_info", [])
                if "local" in a and "prefixlen" in a
            ],
            bpf=self.bpf,
            snaplen=self.snaplen,
        )

    def _explain_failure(self, code: int | None) -> str:
        text = "\n".join(self._lines)
        if self.netns is not None and "Cannot open network namespace" in text:
            return f"network namespace {self.netns!r} does not exist"
        if "exec of" in text and "failed" in text:
            return f"tcpdump could not be run in namespace {self.netns}: {text.strip()}"
        if "No such device" in text:
            return f"no interface {self.where}{self._stderr_tail()}"
        if "can't parse filter" in text or "syntax error" in text:
            return f"bad capture filter {self.bpf!r}{self._stderr_tail()}"
        status = "did not exit" if code is None else f"exited with status {code}"
        return f"tcpdump on {self.where} {status} before listening{self._stderr_tail()}"

    def _stderr_tail(self) -> str:
        tail = [line for line in self._lines[-5:] if line.strip()]
        return (": " + " | ".join(tail)) if tail else ""


def _parse_stats(lines: Sequence[str]) -> CaptureStats:
    values: dict[str, int] = {}
    for line in lines:
        words = line.split()
        if len(words) >= 3 and words[0].isdigit() and words[1] in ("packet", "packets"):
            rest = " ".join(words[2:])
            for key, text in (
                ("captured", "captured"),
                ("received", "received by filter"),
                ("dropped", "dropped by kernel"),
            ):
                if rest == text:
                    values[key] = int(words[0])
    return CaptureStats(**values)


def start_all(captures: Iterable[Capture]) -> list[Capture]:
    """Start several captures at once (tcpdumps start in parallel); all or none run after."""
    started: list[Capture] = []
    caps = list(captures)
    try:
        for cap in caps:
            cap._launch()
            started.append(cap)
        deadline = time.monotonic() + max((c.ready_timeout for c in caps), default=0.0)
        for cap in caps:
            cap._await_ready(deadline)
    except BaseException:
        for cap in started:
            cap.kill()
        raise
    return caps


def stop_all(captures: Iterable[Capture]) -> list[CaptureStats]:
    """Stop several captures at once; every one is stopped before the first error is raised."""
    caps = [c for c in captures if c._proc is not None]
    for cap in caps:
        proc = cap._proc
        if cap.stats is None and proc is not None and proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGINT)
    deadline = time.monotonic() + max((c.stop_timeout for c in caps), default=0.0)
    results: list[CaptureStats] = []
    first: CaptureError | None = None
    for cap in caps:
        try:
            results.append(cap.stats if cap.stats is not None else cap._finish(deadline))
        except CaptureError as exc:
            first = first or exc
            results.append(cap.stats or CaptureStats())
    if first is not None:
        raise first
    return results
