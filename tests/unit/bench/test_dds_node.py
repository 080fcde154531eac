"""The ROS 2 / DDS peer's pure parts (`bench.dds_node`; its fleet test is
tests/ros/test_dds_node.py): the lease profile Fast DDS reads, the environment it runs in, the
messages it reads, and the ports `bench.peers` counts for each domain."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from bench.dds_node import environment, lease_profile, robot_of
from bench.peers import PEERS

NS = {"f": "http://www.eprosima.com"}


def test_the_lease_profile_is_fast_dds_xml_with_the_lease_announced_three_times_a_lease() -> None:
    root = ET.fromstring(lease_profile(2.5))
    part = root.find("f:profiles/f:participant", NS)
    assert part is not None and part.get("is_default_profile") == "true"
    disc = part.find("f:rtps/f:builtin/f:discovery_config", NS)
    assert disc is not None

    def seconds(tag: str) -> float:
        node = disc.find(f"f:{tag}", NS)
        assert node is not None
        return int(node.findtext("f:sec", "", NS)) + int(node.findtext("f:nanosec", "", NS)) / 1e9

    assert seconds("leaseDuration") == 2.5
    assert abs(seconds("leaseAnnouncement") - 2.5 / 3) < 1e-9


def test_dds_runs_over_udp_only_in_its_domain_with_a_lease_only_when_asked(tmp_path: Path) -> None:
    env = environment(1, None, str(tmp_path / "p.xml"))
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == "UDPv4"  # (no shared memory around the medium)
    assert env["ROS_DOMAIN_ID"] == "1" and "FASTDDS_DEFAULT_PROFILES_FILE" not in env
    assert not (tmp_path / "p.xml").exists()
    env = environment(0, 3.0, str(tmp_path / "p.xml"))
    assert env["FASTDDS_DEFAULT_PROFILES_FILE"] == str(tmp_path / "p.xml")
    assert "<sec>3</sec>" in (tmp_path / "p.xml").read_text()


def test_a_message_is_a_robot_and_its_services_or_nothing() -> None:
    assert robot_of('{"robot":"r2","services":{"p1x0":{"name":"a"}}}') == (
        "r2",
        {"p1x0": {"name": "a"}},
    )
    for bad in ("", "[]", '{"robot":"r2"}', '{"robot":"r2","services":3}', "not json"):
        assert robot_of(bad) is None, bad


def test_each_dds_peer_counts_its_domain_s_ports() -> None:
    for name, domain in (("dds", 0), ("dds-lease3s", 1)):
        base = 7400 + 250 * domain
        want = {("udp", base), ("udp", base + 1), ("udp", base + 10), ("udp", base + 11)}
        assert set(PEERS[name].flows) == want, name
        args = PEERS[name].args
        assert (args[args.index("--domain") + 1] if "--domain" in args else "0") == str(domain)
