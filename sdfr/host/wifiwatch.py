"""Watching the fleet's WiFi once joined: which stations nearby completed the key handshake
with this robot (WPA2's 4-way handshake in IBSS, SAE and AMPE in mesh), and which did not.

A station of the fleet's network that stays unauthorized is a robot that does not share this
robot's WiFi key: its frames are never decrypted, so the discovery layer never hears it, and
without this watch nothing would say why.  When every station nearby refuses this robot, its
own secret is the likely culprit; when one does, that robot's.

`parse_stations` reads `iw dev IFACE station dump`; `Watch` is pure (it is given the stations
and the time) and says what to log and what the status record shows (`sdfr.records.status.Wifi`);
`station_dump` runs `iw` (the discovery layer calls it in a thread, off its event loop).
"""

from __future__ import annotations

import re
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from sdfr.records.status import Wifi, WifiStation

if TYPE_CHECKING:
    from sdfr.config.options import Config

#: A station unauthorized this long is reported (a handshake takes well under a second; an
#: emulated or busy radio a few).
GRACE = 20.0
#: Looking costs a run of `iw`: every PERIOD seconds; every FIRST_PERIOD in the first
#: FIRST_MINUTE after the join, when robots meet, and while a station waits to be reported.
PERIOD = 30.0
FIRST_PERIOD = 5.0
FIRST_MINUTE = 60.0

_STATION = re.compile(r"^Station ([0-9a-f:]{17})", re.M)


@dataclass(frozen=True, slots=True)
class Station:
    mac: str
    authorized: bool
    #: 802.11s peer link state (ESTAB once SAE and AMPE completed); None in IBSS
    plink: str | None = None


def parse_stations(text: str) -> dict[str, Station]:
    """The stations of `iw dev IFACE station dump`'s output, by MAC."""
    out: dict[str, Station] = {}
    starts = list(_STATION.finditer(text))
    for i, match in enumerate(starts):
        body = text[match.end() : starts[i + 1].start() if i + 1 < len(starts) else len(text)]
        fields = {}
        for line in body.splitlines():
            key, sep, value = line.strip().partition(":")
            if sep:
                fields[key.strip()] = value.strip()
        mac = match.group(1)
        out[mac] = Station(mac, fields.get("authorized") == "yes", fields.get("mesh plink"))
    return out


def warning(ssid: str, authorized: int, refused: tuple[WifiStation, ...]) -> str | None:
    """What to tell an operator about stations that refuse this robot, if any."""
    if not refused:
        return None
    macs = ", ".join(s.mac for s in refused)
    if authorized == 0:
        return (
            f"wifi: no station of {ssid} completed the key handshake with this robot ({macs} "
            f"refused for {GRACE:.0f} s or more): this robot's WiFi secret is likely not the "
            "fleet's (check wifi_secret_file)"
        )
    return (
        f"wifi: {len(refused)} station(s) of {ssid} never completed the key handshake with "
        f"this robot ({macs}): they do not share the fleet's WiFi secret"
    )


class Watch:
    """The stations of one interface over time: `observe` gives the status record's `Wifi`
    and the log lines of what changed."""

    def __init__(self, iface: str, ssid: str, mode: str, grace: float = GRACE) -> None:
        self.iface, self.ssid, self.mode = iface, ssid, mode
        self.grace = grace
        self._unauthorized_since: dict[str, float] = {}
        self._reported: set[str] = set()

    @property
    def pending(self) -> bool:
        """A station is unauthorized and not yet reported: worth looking again soon."""
        return any(mac not in self._reported for mac in self._unauthorized_since)

    def observe(self, now: float, stations: Mapping[str, Station]) -> tuple[Wifi, list[str]]:
        lines: list[str] = []
        for mac, station in stations.items():
            if station.authorized:
                self._unauthorized_since.pop(mac, None)
                if mac in self._reported:
                    self._reported.discard(mac)
                    lines.append(f"wifi: station {mac} completed the key handshake after all")
            else:
                self._unauthorized_since.setdefault(mac, now)
        for mac in list(self._unauthorized_since):
            if mac not in stations:  # gone from the air
                del self._unauthorized_since[mac]
                self._reported.discard(mac)
        refused = tuple(
            WifiStation(mac, now - since)
            for mac, since in sorted(self._unauthorized_since.items())
            if now - since >= self.grace
        )
        for late in refused:
            if late.mac not in self._reported:
                self._reported.add(late.mac)
                lines.append(
                    f"wifi: station {late.mac} has not completed the key handshake with this "
                    f"robot in {late.seconds:.0f} s: one of the two has another WiFi secret"
                )
        authorized = sum(1 for s in stations.values() if s.authorized)
        wifi = Wifi(
            self.iface, self.ssid, self.mode, authorized, refused,
            warning(self.ssid, authorized, refused),
        )  # fmt: skip
        return wifi, lines


def watch_for(cfg: Config) -> Watch | None:
    """A watch of the fleet's WiFi when sdfrd joins it at start (`sdfr.host.wifi.setup`: a
    wireless interface, wifi not off, a secret configured), else None."""
    from sdfr.host import wifi

    if cfg.iface is None or not cfg.wifi_wanted or not wifi.is_wireless(cfg.iface):
        return None
    return Watch(cfg.iface, wifi.ssid_for(cfg.fleet), cfg.wifi_mode)


def station_dump(iface: str, timeout: float = 5.0) -> dict[str, Station]:
    """The interface's stations now (`iw`); empty when iw fails (the interface is going)."""
    try:
        res = subprocess.run(
            ["iw", "dev", iface, "station", "dump"],
            capture_output=True,
            text=True,
            timeout=timeout,
            stdin=subprocess.DEVNULL,
        )
    except (OSError, subprocess.TimeoutExpired):
        return {}
    return parse_stations(res.stdout) if res.returncode == 0 else {}
