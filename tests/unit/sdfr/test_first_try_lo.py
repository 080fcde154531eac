"""`sdfrd --iface lo`, a first try on one machine: a robot id without a MAC, and no false alarm
from hearing its own multicast (which the kernel sends from 0.0.0.0 on lo)."""

from __future__ import annotations

import os
import random
import select
import socket

import pytest

from sdfr import wire
from sdfr.config.load import Config
from sdfr.daemon.discovery import open_multicast_socket
from sdfr.host import netif
from sdfr.protocol import Core, CoreConfig
from sdfr.records.model import ROBOT_ID_RE


def test_own_multicast_heard_from_0_0_0_0_on_lo_is_our_echo() -> None:
    """A socket that names no multicast source on lo sends from 0.0.0.0 (127.0.0.1 is
    host-scoped), and hears its datagrams come back: they are our echo, not a second daemon's
    claim; no challenge goes out (to 0.0.0.0, that is to ourselves)."""
    core = Core(
        CoreConfig(fleet=1, robot_id="me", beacon_interval=1.0),
        boot_id=7,
        rng=random.Random(1),
        location="http://127.0.0.1:8701/description.json",
    )
    now = 0.0
    core.start(now)
    echoed = 0
    while now < 10.0:
        for data, dst in core.datagrams_to_send():
            assert dst is None, f"a unicast {data[:40]!r} to {dst}"  # no challenge
            core.receive(data, ("0.0.0.0", wire.DEFAULT_PORT), now + 0.001)
            echoed += 1
        deadline = core.next_deadline()
        assert deadline is not None
        now = max(deadline, now)
        core.handle_timer(now)
    assert echoed >= 10  # its searches, its set, its beacons
    assert core.counters.rejects["own"] == echoed
    assert core.counters.rejects["own-claim"] == 0
    assert core.conflict is None


def test_a_robot_id_without_a_mac_is_the_host_name() -> None:
    assert netif.host_robot_id("lab-pc.example.org") == "lab-pc.example.org"
    assert netif.host_robot_id("Rob's box #2") == "Rob-s-box-2"
    assert netif.host_robot_id("-x" + "y" * 80) == "x" + "y" * 63
    assert netif.host_robot_id("___") == ""
    rid = netif.robot_id_from_mac("lo")  # lo's MAC is 00:00:00:00:00:00
    assert rid == netif.host_robot_id(socket.gethostname()) and ROBOT_ID_RE.fullmatch(rid)


@pytest.mark.skipif(os.geteuid() != 0, reason="SO_BINDTODEVICE needs root")
def test_the_discovery_socket_on_lo_multicasts_from_the_address_it_announces() -> None:
    """Left to the kernel, multicast on lo goes out from 0.0.0.0 or another interface's
    address (the issue's false alarm: the daemon took its own beacon for another's); the
    discovery layer names 127.0.0.1, the host of its LOCATION."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = Config(iface="lo", robot_id="me", port=port)
    sock = open_multicast_socket(cfg, "lo", "127.0.0.1")
    try:
        sock.sendto(b"hello", (cfg.group, port))
        assert select.select([sock], [], [], 2.0)[0], "nothing came back on lo"
        data, src = sock.recvfrom(64)
        assert (data, src[0]) == (b"hello", "127.0.0.1")
    finally:
        sock.close()
