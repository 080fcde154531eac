"""Where SDfR's time goes between a publish and a peer's event, from a side-by-side run.

A change on robot R travels: the publish request to R's API (answered once it is durable),
R's discovery layer announcing it (the Update on R's interface), the medium, the peer P's
challenge of it (a ping to R), R's answer, and P's daemon storing it and telling its event
stream, read by P's watcher. The run's files give every moment: the loader's notes on R
(asked, answered), R's and P's pcaps, and P's watcher's notes (seen). Each change of R
during the churn is followed to each peer; its parts are

* `request`: asked -> the publish answered;
* `announced`: asked -> the Update on R's interface;
* `carried`: the Update on R's interface -> on P's;
* `challenged`: the Update on P's interface -> P's challenge (a ping to R) on it;
* `answered`: the challenge -> R's answer on P's interface;
* `told`: the answer -> P's watcher has the event;
* `total`: asked -> P's watcher has the event.

The Update is the first R sent after the publish was asked; a change whose Update,
challenge or answer cannot be found before the event (the peer's challenge of a change
just before it answered for this one too) counts in `total` only. `side_by_side` writes
it for every run (`sdfr_change_path` in its JSON); `python -m bench.change_path FOLDER`
reads a run folder again.
"""

from __future__ import annotations

import argparse
import bisect
import json
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from bench.paper_measure import percentiles, read_events
from netlab.pcap import Record, capture_infos, read_pcap

PARTS = ("request", "announced", "carried", "challenged", "answered", "told", "total")


class Timeline:
    """One robot's SDfR datagrams in time order, searchable by time."""

    def __init__(self, records: Iterable[Record]) -> None:
        self.records = sorted((r for r in records if r.kind == "sdfr"), key=lambda r: r.time)
        self.times = [r.time for r in self.records]

    def first(self, after: float, ok: Callable[[Record], bool], until: float) -> Record | None:
        """The first record at or after `after` (and not after `until`) that is `ok`."""
        for rec in self.records[bisect.bisect_left(self.times, after) :]:
            if rec.time > until:
                return None
            if ok(rec):
                return rec
        return None


def follow(
    robot: str,
    publishes: Sequence[Mapping[str, Any]],
    seen: Mapping[tuple[str, str], float],
    lines: Mapping[str, Timeline],
    addresses: Mapping[str, str],
) -> dict[str, list[float]]:
    """Each part's durations (seconds) for `robot`'s `publishes` (the loader's notes: asked,
    t, sid), seen by each peer of `lines` at `seen[(peer, sid)]`."""
    parts: dict[str, list[float]] = {p: [] for p in PARTS}
    mine, addr = lines[robot], addresses[robot]

    def sent_update(r: Record) -> bool:
        return r.direction == "tx" and r.msg_type == "Update"

    def got_update(r: Record) -> bool:
        return r.direction == "rx" and r.msg_type == "Update" and r.src == addr

    def challenge(r: Record) -> bool:
        return r.direction == "tx" and r.type_key == "Ping" and r.dst == addr

    def answer_of(r: Record) -> bool:
        return r.direction == "rx" and r.type_key == "Ping reply" and r.src == addr

    for pub in publishes:
        asked, sid = float(pub["asked"]), str(pub["sid"])
        for peer, line in lines.items():
            at = seen.get((peer, sid))
            if peer == robot or at is None:
                continue
            parts["total"].append(at - asked)
            up = mine.first(asked, sent_update, at)
            rx = up and line.first(up.time - 0.001, got_update, at)
            ping = rx and line.first(rx.time, challenge, at)
            answer = ping and line.first(ping.time, answer_of, at)
            if not (up and rx and ping and answer):
                continue
            parts["request"].append(float(pub["t"]) - asked)
            parts["announced"].append(up.time - asked)
            parts["carried"].append(rx.time - up.time)
            parts["challenged"].append(ping.time - rx.time)
            parts["answered"].append(answer.time - ping.time)
            parts["told"].append(at - answer.time)
    return parts


def summary(parts: Mapping[str, Sequence[float]]) -> dict[str, dict[str, float | int]]:
    """Each part's count, p50, p99, max and mean in ms (the parts that have any)."""
    return {n: percentiles(1e3 * v for v in parts[n]) for n in PARTS if parts.get(n)}


def decompose(
    folder: Path, robots: Sequence[str], window: tuple[float, float], robot: str = "r1"
) -> dict[str, dict[str, float | int]]:
    """The parts of `robot`'s changes asked for within `window` (the churn), as each other
    robot of the run in `folder` saw them."""
    infos = capture_infos(folder)
    addresses = {r: infos[r].addresses[0].split("/")[0] for r in robots}
    lines = {r: Timeline(read_pcap(folder / f"{r}.pcap")) for r in robots}
    files = [folder / f"sdfr-{kind}-{r}.jsonl" for kind in ("loader", "watcher") for r in robots]
    seen: dict[tuple[str, str], float] = {}
    publishes = []
    for note in read_events(p for p in files if p.exists()):  # in time order
        if note.get("robot") != robot:
            continue
        if note.get("op") == "seen":
            seen.setdefault((str(note["at"]), str(note["sid"])), float(note["t"]))
        elif note.get("op") == "publish" and window[0] <= float(note["asked"]) <= window[1]:
            publishes.append(note)
    return summary(follow(robot, publishes, seen, lines, addresses))


def sentence(path: Mapping[str, Mapping[str, float | int]]) -> list[str]:
    """The parts as one sentence for the run's Markdown (nothing when there are none)."""
    if not path:
        return []
    said = ", ".join(
        f"{name} {path[name]['p50_ms']} / {path[name]['p99_ms']}" for name in PARTS if name in path
    )
    return [f"SDfR's change path, p50 / p99 ms (`bench/change_path.py`): {said}."]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("folder", type=Path, help="a side-by-side run folder (N-robots-loss-L)")
    p.add_argument("--robot", default="r1", help="whose changes (default r1)")
    args = p.parse_args(argv)
    result = json.loads((args.folder / "side-by-side.json").read_text())
    window = result.get("churn_window")
    if window is None:
        print(f"{args.folder}: its side-by-side.json has no churn_window", file=sys.stderr)
        return 2
    robots = [f"r{i}" for i in range(1, int(result["robots"]) + 1)]
    path = decompose(args.folder, robots, (float(window[0]), float(window[1])), args.robot)
    print(json.dumps(path, indent=2))
    print("\n".join(sentence(path)), file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
