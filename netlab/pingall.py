"""`netlab pingall`: every robot pings every other over the medium (as Mininet's pingall).

Each robot's pings run in its own network namespace with the host's ``ping``, all robots at
once; a pair is judged against the medium's links: a pair the medium links both ways must
answer, one it does not link should not.
"""

from __future__ import annotations

import re
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from netlab import kernel

PARALLEL = 64  # pings running at once (a 100-robot lab has 9,900 pairs)
_SUMMARY = re.compile(r"(\d+) packets transmitted, (\d+) (?:packets )?received")


@dataclass(frozen=True, slots=True)
class Ping:
    sent: int
    received: int

    @property
    def loss(self) -> float:
        return 100.0 * (1 - self.received / self.sent) if self.sent else 100.0


def parse_ping(output: str) -> Ping:
    """The transmitted/received counts of ping's summary; none sent when it has none."""
    found = _SUMMARY.search(output)
    return Ping(int(found[1]), int(found[2])) if found else Ping(0, 0)


def ping_argv(address: str, count: int, timeout: float) -> list[str]:
    """ping `count` times, 0.2 s apart, waiting `timeout` s for the last reply."""
    return ["ping", "-n", "-q", "-c", str(count), "-i", "0.2", "-W", f"{timeout:g}", address]


def ping_all(
    namespaces: Mapping[str, str],
    addresses: Mapping[str, str],
    count: int = 3,
    timeout: float = 1.0,
    parallel: int = PARALLEL,
) -> dict[tuple[str, str], Ping]:
    """(source, target) -> its pings, for every ordered pair of robots, `parallel` at once."""
    pairs = [(a, b) for a in namespaces for b in addresses if a != b]
    out: dict[tuple[str, str], Ping] = {}
    for start in range(0, len(pairs), parallel):
        procs: dict[tuple[str, str], subprocess.Popen[str]] = {}
        try:
            for a, b in pairs[start : start + parallel]:
                target = addresses[b].split("/")[0]
                procs[(a, b)] = subprocess.Popen(
                    kernel.ns_argv(namespaces[a], ping_argv(target, count, timeout)),
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.STDOUT,
                    text=True,
                )
            limit = count * 0.2 + timeout + 30
            for pair, proc in procs.items():
                out[pair] = parse_ping(proc.communicate(timeout=limit)[0])
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
    return out


@dataclass(frozen=True, slots=True)
class Verdict:
    failed: list[tuple[str, str]]  # linked both ways, no reply
    unexpected: list[tuple[str, str]]  # not linked, and yet replies
    sent: int
    received: int  # over the linked pairs

    @property
    def ok(self) -> bool:
        return not self.failed


def judge(
    results: Mapping[tuple[str, str], Ping], linked: Mapping[tuple[str, str], float] | None
) -> Verdict:
    """Pairs judged against the medium's `linked` (ordered) pairs; None: every pair linked."""

    def expected(a: str, b: str) -> bool:
        return linked is None or ((a, b) in linked and (b, a) in linked)

    failed = [p for p, r in results.items() if expected(*p) and r.received == 0]
    unexpected = [p for p, r in results.items() if not expected(*p) and r.received > 0]
    judged = [r for p, r in results.items() if expected(*p)]
    return Verdict(
        sorted(failed),
        sorted(unexpected),
        sum(r.sent for r in judged),
        sum(r.received for r in judged),
    )


def matrix(
    robots: Sequence[str],
    results: Mapping[tuple[str, str], Ping],
    linked: Mapping[tuple[str, str], float] | None,
) -> list[str]:
    """Rows of loss in %: one per source robot, one column per target; ``cut`` for a pair the
    medium does not link that stayed silent, FAIL/ANSWERS for a surprise."""
    cells = [["from\\to", *robots]]
    for a in robots:
        row = [a]
        for b in robots:
            if a == b:
                row.append("-")
                continue
            r = results[(a, b)]
            linked_both = linked is None or ((a, b) in linked and (b, a) in linked)
            if linked_both:
                row.append(f"{r.loss:.0f}%" if r.received else "FAIL")
            else:
                row.append(f"ANSWERS {r.loss:.0f}%" if r.received else "cut")
        cells.append(row)
    widths = [max(len(row[i]) for row in cells) for i in range(len(cells[0]))]
    return ["  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in cells]


def summary(verdict: Verdict) -> str:
    """Mininet's results line, over the pairs the medium links, and the surprises."""
    lost = verdict.sent - verdict.received
    loss = 100.0 * lost / verdict.sent if verdict.sent else 0.0
    text = (
        f"{loss:.1f}% dropped ({verdict.received}/{verdict.sent} received over the linked pairs); "
        f"{len(verdict.failed)} linked pairs without a reply"
    )
    if verdict.unexpected:
        text += f"; {len(verdict.unexpected)} pairs answer that the medium does not link"
    return text
