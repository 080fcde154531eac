"""The radio lab's medium: which radio hears which frame, decided by netlab's range model.

Without a medium, mac80211_hwsim hands every frame to every radio on the channel.  Once a
process registers with it (HWSIM_CMD_REGISTER over generic netlink), every frame of the
radios made in that network namespace goes to that process instead (HWSIM_CMD_FRAME),
which delivers it to the radios it chooses (HWSIM_CMD_FRAME back, one per receiver) and
tells the sender how the transmission went (HWSIM_CMD_TX_INFO_FRAME: the attempts used
and whether the destination acknowledged it).  wmediumd is such a medium; this is netlab's
own, so that a radio lab obeys the same `Topology.links()` as a wired one: positions and
radius, partitions and each pair's loss decide every (sender, receiver) pair.

The radios of every lab are made in the initial namespace (then moved into their robots'
namespaces), and the kernel lets only one process per namespace register: a second
medium (wmediumd, or another radio lab's) is refused with EBUSY, said as a NetlabError.
A frame of a radio this lab does not know is delivered to no one and reported unacked.

The channel between the lab and its medium is a JSON file, ``links.json`` in the lab's
``air`` folder, that the lab replaces atomically (write, then rename) whenever its medium
changes; the medium looks at it (one stat) at most every `RELOAD` seconds while frames
flow.  A file, not a socket, because a detached lab is changed by other processes
(`Lab.attach`, `netlab partition`): each of them rewrites the file and needs no
connection to the medium, and the file says what the medium obeys after any of them.
The medium writes its counters (frames, copies delivered, CPU seconds) to ``stats.json``
beside it every second while frames flow, and at exit.

802.11 as modelled: a group frame (address 1 multicast or broadcast) is sent once, and
each linked radio receives it unless its link's loss drops it; nothing acknowledges it.  A
unicast frame goes through the sender's rate table (its (rate, count) stages, as mac80211
asked): each attempt reaches the destination unless the loss drops it, and the ACK comes
back unless the reverse link's loss drops that (or there is no reverse link); the first
acknowledged attempt ends it.  The destination receives the frame once, however many
attempts reached it.  Radios are known by their hwsim address (the radio's permanent
address with the 0x40 bit set, `netlab.hwsim.Radio.address`); a unicast frame's address 1
is an interface's address, learnt from the address 2 of each frame a radio sends (and,
until then, the permanent address, which an interface starts with).

Run by the lab: ``python -m netlab.airmedium --links FILE --stats FILE [--seed N]``; it
prints ``registered`` once it is the medium, then runs until SIGTERM.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import random
import select
import signal
import socket
import struct
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from netlab import hwsim
from netlab.errors import NetlabError
from netlab.naming import mac_text
from netlab.ranges import Links

#: Seconds between two looks at the links file while frames flow.
RELOAD = 0.1
#: Seconds between two writes of the stats file while frames flow.
STATS_EVERY = 1.0
#: The signal strength (dBm) a received frame and an ACK are reported with.
SIGNAL = -50
#: Most frames read in one wake-up before the links file and the stats get a look.
BATCH = 256
#: The real-time priority (SCHED_FIFO) the medium asks for: the air does not wait for the
#: robots' CPU. Under load (robots, tcpdumps, an observer on the emulated VM's one CPU), a
#: medium at normal priority fell seconds behind, and 802.11's handshakes (EAPOL's 100 ms
#: and 1 s retries, mesh peering's 40 ms timers) timed out on frames it still held.
PRIORITY = 10

# hwsim's tx flags (enum hwsim_tx_control_flags)
TX_CTL_REQ_TX_STATUS = 1
TX_CTL_NO_ACK = 2
TX_STAT_ACK = 4

ATTR_TX_INFO_FLAGS = 21
#: struct hwsim_tx_rate: s8 idx, u8 count; IEEE80211_TX_MAX_RATES of them.
_RATE = struct.Struct("=bB")
MAX_RATES = 4

Rates = tuple[tuple[int, int], ...]


# -- addresses and 802.11 headers ----------------------------------------------------------


def mac_bytes(text: str) -> bytes:
    """``aa:bb:cc:dd:ee:ff`` as 6 bytes; ValueError saying what was wrong otherwise."""
    parts = text.split(":")
    try:
        raw = bytes(int(p, 16) for p in parts)
    except ValueError:
        raw = b""
    if len(parts) != 6 or len(raw) != 6 or any(len(p) != 2 for p in parts):
        raise ValueError(f"not a MAC address (aa:bb:cc:dd:ee:ff): {text!r}")
    return raw


def perm_address(hwsim_addr: str) -> str:
    """The permanent address a radio made without one given has, from its hwsim address:
    the address its interface starts with."""
    raw = mac_bytes(hwsim_addr)
    return mac_text(bytes([raw[0] & ~0x40 & 0xFF]) + raw[1:])


def address1(frame: bytes) -> bytes | None:
    """The receiver address of an 802.11 frame (after frame control and duration)."""
    return frame[4:10] if len(frame) >= 10 else None


def address2(frame: bytes) -> bytes | None:
    """The transmitter address of an 802.11 frame that has one (not a control frame)."""
    is_control = (frame[0] >> 2) & 0x3 == 1 if frame else True
    return frame[10:16] if len(frame) >= 16 and not is_control else None


def is_group(addr: bytes) -> bool:
    """Multicast or broadcast: the group bit of the first octet."""
    return bool(addr[0] & 0x01)


# -- hwsim's frame messages ----------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TxFrame:
    """A frame a radio sends (HWSIM_CMD_FRAME from the kernel)."""

    transmitter: bytes  # the sending radio's hwsim address
    frame: bytes
    flags: int
    rates: Rates  # (rate index, count) stages; index -1 ends the table
    cookie: int
    freq: int | None = None
    rate_flags: bytes | None = None  # HWSIM_ATTR_TX_INFO_FLAGS, given back as it came


def parse_rates(raw: bytes) -> Rates:
    return tuple(_RATE.unpack_from(raw, at) for at in range(0, len(raw) - 1, _RATE.size))


def pack_rates(rates: Rates) -> bytes:
    padded = list(rates[:MAX_RATES]) + [(-1, 0)] * (MAX_RATES - len(rates))
    return b"".join(_RATE.pack(idx, count) for idx, count in padded)


def parse_tx(attributes: Mapping[int, bytes]) -> TxFrame:
    """The frame of one HWSIM_CMD_FRAME's attributes; ValueError naming what is missing."""
    need = {
        hwsim.ATTR_ADDR_TRANSMITTER: "transmitter",
        hwsim.ATTR_FRAME: "frame",
        hwsim.ATTR_FLAGS: "flags",
        hwsim.ATTR_TX_INFO: "tx info",
        hwsim.ATTR_COOKIE: "cookie",
    }
    missing = [what for kind, what in need.items() if kind not in attributes]
    if missing:
        raise ValueError(f"hwsim frame without {', '.join(missing)}")
    freq = attributes.get(hwsim.ATTR_FREQ)
    return TxFrame(
        transmitter=attributes[hwsim.ATTR_ADDR_TRANSMITTER][:6],
        frame=attributes[hwsim.ATTR_FRAME],
        flags=int(struct.unpack_from("=I", attributes[hwsim.ATTR_FLAGS])[0]),
        rates=parse_rates(attributes[hwsim.ATTR_TX_INFO]),
        cookie=int(struct.unpack_from("=Q", attributes[hwsim.ATTR_COOKIE])[0]),
        freq=None if freq is None else int(struct.unpack_from("=I", freq)[0]),
        rate_flags=attributes.get(ATTR_TX_INFO_FLAGS),
    )


def tx_payload(tx: TxFrame) -> bytes:
    """The attributes of the HWSIM_CMD_FRAME the kernel sends for `tx` (what `parse_tx`
    reads): to test the codec, and for a medium's own frames."""
    out = (
        hwsim.attr(hwsim.ATTR_ADDR_TRANSMITTER, tx.transmitter)
        + hwsim.attr(hwsim.ATTR_FRAME, tx.frame)
        + hwsim.attr_u32(hwsim.ATTR_FLAGS, tx.flags)
        + hwsim.attr(hwsim.ATTR_TX_INFO, pack_rates(tx.rates))
        + hwsim.attr(hwsim.ATTR_COOKIE, struct.pack("=Q", tx.cookie))
    )
    if tx.freq is not None:
        out += hwsim.attr_u32(hwsim.ATTR_FREQ, tx.freq)
    if tx.rate_flags is not None:
        out += hwsim.attr(ATTR_TX_INFO_FLAGS, tx.rate_flags)
    return out


def _s32(value: int) -> bytes:
    return struct.pack("=i", value)


#: Legacy rates every band has (5 GHz has 8, 2.4 GHz 12): hwsim reports a received frame's
#: rate to mac80211 as a legacy rate index, and mac80211 drops a frame whose index is past
#: its band's table (with a warning), as an HT rate's MCS index would often be.
LEGACY_RATES = 8


def rx_rate(rate: int) -> int:
    """The rate index a receiver is told: the sender's if it is a legacy one every band
    has, else the lowest (the sender's rate control sees only the tx status)."""
    return rate if 0 <= rate < LEGACY_RATES else 0


def rx_payload(receiver: bytes, tx: TxFrame, rate: int, signal: int = SIGNAL) -> bytes:
    """The attributes of the HWSIM_CMD_FRAME that hands `tx`'s frame, sent at rate index
    `rate`, to radio `receiver`."""
    out = (
        hwsim.attr(hwsim.ATTR_ADDR_RECEIVER, receiver)
        + hwsim.attr(hwsim.ATTR_FRAME, tx.frame)
        + hwsim.attr_u32(hwsim.ATTR_RX_RATE, rx_rate(rate))
        + hwsim.attr(hwsim.ATTR_SIGNAL, _s32(signal))
    )
    if tx.freq is not None:
        out += hwsim.attr_u32(hwsim.ATTR_FREQ, tx.freq)
    return out


def status_payload(tx: TxFrame, acked: bool, used: Rates, signal: int = SIGNAL) -> bytes:
    """The attributes of the HWSIM_CMD_TX_INFO_FRAME that ends `tx`: the attempts `used` per
    stage and, when `acked`, HWSIM_TX_STAT_ACK in its flags."""
    flags = (tx.flags | TX_STAT_ACK) if acked else (tx.flags & ~TX_STAT_ACK)
    out = (
        hwsim.attr(hwsim.ATTR_ADDR_TRANSMITTER, tx.transmitter)
        + hwsim.attr_u32(hwsim.ATTR_FLAGS, flags)
        + hwsim.attr(hwsim.ATTR_COOKIE, struct.pack("=Q", tx.cookie))
        + hwsim.attr(hwsim.ATTR_SIGNAL, _s32(signal if acked else 0))
        + hwsim.attr(hwsim.ATTR_TX_INFO, pack_rates(used))
    )
    if tx.rate_flags is not None:
        out += hwsim.attr(ATTR_TX_INFO_FLAGS, tx.rate_flags)
    return out


# -- the fate of a frame -------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Fate:
    """What became of one frame: who received it (robot, rate index), whether it was
    acknowledged, and the attempts used per stage of the rate table."""

    receivers: tuple[tuple[str, int], ...]
    acked: bool
    used: Rates


def _passes(loss: float, rng: random.Random) -> bool:
    return loss <= 0.0 or rng.random() * 100.0 >= loss


def fate(
    sender: str | None,
    dest: str | None,
    group: bool,
    rates: Rates,
    links: Mapping[tuple[str, str], float],
    robots: Iterable[str],
    rng: random.Random,
) -> Fate:
    """The fate of a frame `sender` sends (None: a radio of no robot here) to `dest` (the
    robot whose interface address 1 names; None when no robot's, or a `group` frame),
    through the rate table `rates`, on `links` ((sender, receiver) -> loss %)."""
    stages = [(idx, count) for idx, count in rates if idx >= 0 and count > 0]
    first = stages[0][0] if stages else 0
    once: Rates = ((first, 1),)
    if sender is None:
        return Fate((), False, once)
    if group:
        heard = tuple(
            (r, first)
            for r in robots
            if r != sender and (sender, r) in links and _passes(links[(sender, r)], rng)
        )
        return Fate(heard, False, once)
    used: list[tuple[int, int]] = []
    received: tuple[tuple[str, int], ...] = ()
    for idx, count in stages:
        for attempt in range(1, count + 1):
            reached = (
                dest is not None
                and dest != sender
                and (sender, dest) in links
                and _passes(links[(sender, dest)], rng)
            )
            if not reached:
                continue
            assert dest is not None
            if not received:
                received = ((dest, idx),)
            if (dest, sender) in links and _passes(links[(dest, sender)], rng):
                return Fate(received, True, (*used, (idx, attempt)))
        used.append((idx, count))
    return Fate(received, False, tuple(used) or once)


# -- the lab's side: the links file and the stats ------------------------------------------


def write_links(path: Path, radios: Mapping[str, str], links: Links) -> None:
    """Replace `path` atomically with the robots' radios (robot -> hwsim address) and the
    `links` among them ((sender, receiver) -> loss %)."""
    data = {
        "radios": dict(sorted(radios.items())),
        "links": [[a, b, loss] for (a, b), loss in sorted(links.items())],
    }
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)


@dataclass(slots=True)
class LinkTable:
    """What the medium obeys: radios by hwsim address, and the links' losses."""

    radios: dict[bytes, str] = field(default_factory=dict)  # hwsim address -> robot
    links: dict[tuple[str, str], float] = field(default_factory=dict)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> LinkTable:
        """The table of a links file's JSON; ValueError saying what was wrong."""
        try:
            radios = {mac_bytes(str(a)): str(r) for r, a in dict(data["radios"]).items()}
            links = {(str(a), str(b)): float(loss) for a, b, loss in data["links"]}
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"a links file needs radios and links: {exc}") from None
        return cls(radios, links)


def read_links(path: Path) -> LinkTable:
    try:
        return LinkTable.from_json(json.loads(path.read_text()))
    except (OSError, ValueError) as exc:
        raise NetlabError(f"the radio medium's links file {path}: {exc}") from None


def read_stats(path: Path) -> dict[str, Any]:
    """The medium's counters as it last wrote them (see `Medium.stats`)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise NetlabError(f"the radio medium's stats {path}: {exc}") from None
    return dict(data)


# -- the medium process --------------------------------------------------------------------


def register(genl: hwsim.Genl) -> None:
    """Become the medium of this namespace's radios; NetlabError if another is already."""
    try:
        genl.request(genl.family, hwsim.CMD_REGISTER)
    except OSError as exc:
        if exc.errno == errno.EBUSY:
            raise NetlabError(
                "another medium is registered with mac80211_hwsim in this network namespace "
                "(wmediumd, or the medium of another radio lab: only one can be): "
                "the radio medium cannot start"
            ) from None
        raise NetlabError(f"hwsim: cannot register as the medium: {exc.strerror}") from None


class Medium:
    """The medium's loop: frames in, copies and tx statuses out (see the module doc)."""

    def __init__(self, genl: hwsim.Genl, links_path: Path, stats_path: Path, seed: int) -> None:
        self.genl = genl
        self.links_path = links_path
        self.stats_path = stats_path
        self.rng = random.Random(seed)
        self.table = LinkTable()
        self.iface: dict[bytes, str] = {}  # an interface's address -> its robot
        self.radio_of: dict[str, bytes] = {}  # robot -> its radio's hwsim address
        self._seen: tuple[int, int] | None = None
        self._looked = 0.0
        self._written = 0.0
        self.counts = {
            "frames": 0,
            "group": 0,
            "unicast": 0,
            "acked": 0,
            "delivered": 0,
            "unknown_sender": 0,
            "send_errors": 0,
            "reloads": 0,
            "wakeups": 0,
            "max_batch": 0,
            "behind": 0,
        }
        #: The scheduling the medium runs with (`prioritise`), reported in the stats.
        self.priority = "normal"
        #: Frames each robot's radio sent, and copies each received.
        self.sent: dict[str, int] = {}
        self.received: dict[str, int] = {}
        self.started = time.monotonic()
        self.cpu0 = time.process_time()

    def reload(self, force: bool = False) -> None:
        """Read the links file again if it was replaced (at most every RELOAD seconds)."""
        now = time.monotonic()
        if not force and now - self._looked < RELOAD:
            return
        self._looked = now
        try:
            st = os.stat(self.links_path)
        except FileNotFoundError:
            return
        seen = (st.st_ino, st.st_mtime_ns)
        if seen == self._seen:
            return
        table = read_links(self.links_path)
        self._seen = seen
        self.table = table
        self.radio_of = {r: a for a, r in table.radios.items()}
        for addr, robot in table.radios.items():
            self.iface.setdefault(mac_bytes(perm_address(mac_text(addr))), robot)
        self.counts["reloads"] += 1

    def _send(self, cmd: int, payload: bytes) -> None:
        msg = hwsim.encode(self.genl.family, cmd, payload, 0, hwsim.NLM_F_REQUEST, hwsim.VERSION)
        try:
            self.genl.sock.send(msg)
        except OSError:
            self.counts["send_errors"] += 1

    def handle(self, tx: TxFrame) -> Fate:
        """Decide `tx`'s fate, deliver its copies and end it with its tx status."""
        self.counts["frames"] += 1
        sender = self.table.radios.get(tx.transmitter)
        if sender is None:
            self.counts["unknown_sender"] += 1
        else:
            self.sent[sender] = self.sent.get(sender, 0) + 1
            ta = address2(tx.frame)
            if ta is not None:
                self.iface[ta] = sender
        dest_addr = address1(tx.frame)
        group = dest_addr is not None and is_group(dest_addr)
        self.counts["group" if group else "unicast"] += 1
        dest = None if group or dest_addr is None else self.iface.get(dest_addr)
        robots = self.table.radios.values()
        result = fate(sender, dest, group, tx.rates, self.table.links, robots, self.rng)
        for robot, rate in result.receivers:
            self.received[robot] = self.received.get(robot, 0) + 1
            self._send(hwsim.CMD_FRAME, rx_payload(self.radio_of[robot], tx, rate))
        self.counts["delivered"] += len(result.receivers)
        self.counts["acked"] += result.acked
        self._send(hwsim.CMD_TX_INFO_FRAME, status_payload(tx, result.acked, result.used))
        return result

    def stats(self) -> dict[str, Any]:
        """The counters, with the CPU seconds this process used and per frame."""
        cpu = time.process_time() - self.cpu0
        frames = self.counts["frames"]
        return {
            **self.counts,
            "cpu_seconds": round(cpu, 4),
            "seconds": round(time.monotonic() - self.started, 3),
            "cpu_per_frame": round(cpu / frames, 7) if frames else None,
            "priority": self.priority,
            "sent": dict(sorted(self.sent.items())),
            "received": dict(sorted(self.received.items())),
            "pid": os.getpid(),
        }

    def write_stats(self) -> None:
        self._written = time.monotonic()
        tmp = self.stats_path.with_name(f".{self.stats_path.name}.tmp")
        tmp.write_text(json.dumps(self.stats(), indent=1) + "\n")
        os.replace(tmp, self.stats_path)

    def read(self) -> list[bytes]:
        """The datagrams waiting (at most BATCH), without blocking: one wake-up's work."""
        sock = self.genl.sock
        out: list[bytes] = []
        while len(out) < BATCH:
            try:
                out.append(sock.recv(1 << 16, socket.MSG_DONTWAIT))
            except BlockingIOError:
                break
            except OSError as exc:
                if exc.errno != errno.ENOBUFS:  # frames were dropped: go on
                    raise
                self.counts["send_errors"] += 1
        return out

    def take(self, batch: Sequence[bytes]) -> None:
        """One wake-up's datagrams: answer each frame among them.  `behind` counts wake-ups
        that found more than one waiting (the medium was late), `max_batch` the most."""
        family = self.genl.family
        self.counts["wakeups"] += 1
        self.counts["behind"] += len(batch) > 1
        self.counts["max_batch"] = max(self.counts["max_batch"], len(batch))
        for data in batch:
            for msg in hwsim.decode(data):
                if msg.kind == family and msg.cmd == hwsim.CMD_FRAME:
                    try:
                        tx = parse_tx(msg.attributes)
                    except ValueError:
                        continue
                    self.handle(tx)

    def run(self) -> None:
        """Until SIGTERM (SystemExit): read frames, answer each."""
        sock = self.genl.sock
        while True:
            ready, _, _ = select.select([sock], [], [], 1.0)
            self.reload()
            if ready:
                self.take(self.read())
            if time.monotonic() - self._written >= STATS_EVERY:
                self.write_stats()


def prioritise(priority: int = PRIORITY) -> str:
    """Ask for real-time scheduling (SCHED_FIFO `priority`), else nice -10; what was had."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return f"SCHED_FIFO {priority}"
    with contextlib.suppress(OSError):
        os.nice(-10)
        return "nice -10"
    return "normal"


def _terminate(signum: int, _frame: object) -> None:
    raise SystemExit(0)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m netlab.airmedium", description=__doc__)
    parser.add_argument("--links", type=Path, required=True, help="the lab's links file")
    parser.add_argument("--stats", type=Path, required=True, help="where the counters go")
    parser.add_argument("--seed", type=int, default=0, help="seed of the loss draws")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, _terminate)
    try:
        genl = hwsim.Genl()
        with contextlib.suppress(OSError):  # bursts of frames: room for them (root only)
            genl.sock.setsockopt(socket.SOL_SOCKET, 33, 4 << 20)  # SO_RCVBUFFORCE
        register(genl)
        medium = Medium(genl, args.links, args.stats, args.seed)
        medium.reload(force=True)
        medium.priority = prioritise()
    except NetlabError as exc:
        print(f"netlab airmedium: {exc}", file=sys.stderr)
        return 1
    print("registered", flush=True)
    try:
        medium.run()
    finally:
        medium.write_stats()
        genl.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
