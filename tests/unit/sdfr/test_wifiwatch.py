"""Watching the fleet's WiFi (sdfr.host.wifiwatch): stations that never complete the key
handshake are reported, on whose side the secret is likely wrong, and nothing else is."""

from __future__ import annotations

import json

from sdfr.api.handlers.health import health_warnings
from sdfr.host.wifiwatch import GRACE, Station, Watch, parse_stations
from sdfr.records.status import DiscoveryStatus

DUMP = """Station 02:00:00:00:01:00 (on wlan0)
\tinactive time:\t120 ms
\trx bytes:\t5120
\tauthorized:\tyes
\tauthenticated:\tyes
\tassociated:\tyes
\tmesh plink:\tESTAB
Station 02:00:00:00:03:00 (on wlan0)
\tinactive time:\t40 ms
\tauthorized:\tno
\tauthenticated:\tno
\tmesh plink:\tLISTEN
"""


def test_a_station_dump_reads_as_stations() -> None:
    assert parse_stations(DUMP) == {
        "02:00:00:00:01:00": Station("02:00:00:00:01:00", True, "ESTAB"),
        "02:00:00:00:03:00": Station("02:00:00:00:03:00", False, "LISTEN"),
    }
    assert parse_stations("") == {}


def test_a_station_refused_longer_than_the_grace_is_reported_once() -> None:
    watch = Watch("wlan0", "sdfr-fleet-7", "ibss")
    stations = parse_stations(DUMP)
    state, lines = watch.observe(100.0, stations)
    assert state.refused == () and lines == [] and state.warning is None
    state, lines = watch.observe(100.0 + GRACE, stations)
    assert state.authorized == 1 and [s.mac for s in state.refused] == ["02:00:00:00:03:00"]
    assert lines == [
        "wifi: station 02:00:00:00:03:00 has not completed the key handshake with this robot "
        f"in {GRACE:.0f} s: one of the two has another WiFi secret"
    ]
    warning = state.warning
    assert warning is not None and "they do not share the fleet's WiFi secret" in warning
    _, lines = watch.observe(100.0 + 2 * GRACE, stations)
    assert lines == []  # said once


def test_refused_by_every_station_blames_this_robots_secret() -> None:
    watch = Watch("wlan0", "sdfr-fleet-7", "ibss", grace=5.0)
    alone = {"02:00:00:00:01:00": Station("02:00:00:00:01:00", False)}
    watch.observe(0.0, alone)
    state, _ = watch.observe(5.0, alone)
    warning = state.warning
    assert warning is not None and "this robot's WiFi secret is likely not the fleet's" in warning


def test_a_late_handshake_or_a_station_gone_clears_it() -> None:
    watch = Watch("wlan0", "sdfr-fleet-7", "ibss", grace=5.0)
    mac = "02:00:00:00:01:00"
    watch.observe(0.0, {mac: Station(mac, False)})
    state, _ = watch.observe(6.0, {mac: Station(mac, False)})
    assert state.refused
    state, lines = watch.observe(7.0, {mac: Station(mac, True)})
    assert state.refused == () and lines == [
        f"wifi: station {mac} completed the key handshake after all"
    ]
    watch.observe(8.0, {mac: Station(mac, False)})
    state, _ = watch.observe(9.0, {})
    assert state.refused == ()
    state, _ = watch.observe(20.0, {mac: Station(mac, False)})
    assert state.refused == ()  # its clock started again when it came back


def test_the_warning_reaches_health_through_the_status_record() -> None:
    """The discovery layer's record carries the watch's state to the API layer intact, and
    /health's warnings include what it says."""
    watch = Watch("wlan0", "sdfr-fleet-7", "mesh", grace=1.0)
    mac = "02:00:00:00:01:00"
    watch.observe(0.0, {mac: Station(mac, False)})
    wifi, _ = watch.observe(2.0, {mac: Station(mac, False)})
    record = DiscoveryStatus(pid=1, heartbeat=0.0, wifi=wifi)
    back = DiscoveryStatus.from_json(json.loads(json.dumps(record.to_json())))
    assert back is not None and back.wifi == wifi
    assert wifi.warning is not None and wifi.warning in health_warnings(back, now=0.0)
    assert health_warnings(DiscoveryStatus(pid=1, heartbeat=0.0), now=0.0) == []
