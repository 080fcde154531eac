"""netlab.hwsim's generic netlink codec, on bytes (the radios themselves: tests/radio), what
the doctor says of radios, what a radio lab refuses, and how its medium changes reach its
radio medium (`netlab.airmedium`'s links file)."""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import pytest

from netlab import airmedium, doctor, hwsim, naming
from netlab.errors import NetlabError
from netlab.labmedium import LabMedium
from netlab.ranges import Topology, UnitDisc
from netlab.robots import Robot, RobotRef


def test_an_attribute_is_padded_to_four_bytes_and_reads_back() -> None:
    raw = hwsim.attr_str(hwsim.ATTR_RADIO_NAME, "nl1-r1") + hwsim.attr_u32(hwsim.ATTR_CHANNELS, 1)
    assert len(raw) % 4 == 0
    assert dict(hwsim.attrs(raw)) == {
        hwsim.ATTR_RADIO_NAME: b"nl1-r1\0",
        hwsim.ATTR_CHANNELS: struct.pack("=I", 1),
    }


def test_a_truncated_attribute_ends_the_walk() -> None:
    raw = hwsim.attr_u32(hwsim.ATTR_RADIO_ID, 7) + struct.pack("=HH", 40, hwsim.ATTR_FREQ)
    assert list(hwsim.attrs(raw)) == [(hwsim.ATTR_RADIO_ID, struct.pack("=I", 7))]


def test_a_request_reads_back_as_a_message() -> None:
    payload = hwsim.attr_str(hwsim.ATTR_RADIO_NAME, "x")
    raw = hwsim.encode(29, hwsim.CMD_NEW_RADIO, payload, seq=5, flags=hwsim.NLM_F_REQUEST)
    (msg,) = hwsim.decode(raw)
    assert (msg.kind, msg.seq, msg.cmd) == (29, 5, hwsim.CMD_NEW_RADIO)
    assert msg.attributes == {hwsim.ATTR_RADIO_NAME: b"x\0"}
    assert struct.unpack_from("=I", raw)[0] == len(raw)


def test_an_ack_carries_the_value_the_kernel_returned() -> None:
    header = struct.pack("=IHHII", 16, 0, 0, 0, 0)
    for value in (0, -19, 4):
        body = struct.pack("=i", value) + header
        raw = struct.pack("=IHHII", 16 + len(body), hwsim.NLMSG_ERROR, 0, 9, 0) + body
        (msg,) = hwsim.decode(raw)
        assert msg.kind == hwsim.NLMSG_ERROR and msg.error == value


def test_two_messages_in_one_datagram() -> None:
    a = hwsim.encode(30, 1, b"", seq=1, flags=0)
    b = hwsim.encode(30, 2, hwsim.attr_u32(hwsim.ATTR_FLAGS, 3), seq=2, flags=0)
    assert [m.seq for m in hwsim.decode(a + b)] == [1, 2]


def test_the_doctor_says_why_radio_labs_cannot_run(tmp_path: Path) -> None:
    """On this machine kind's kernel (no wireless stack, no modules) and on one that could
    load the module, the reason names what to do."""
    if hwsim.loaded():
        pytest.skip("this kernel has mac80211_hwsim: the reasons are for one without")
    ok, why = doctor.radio_support(proc=tmp_path / "proc", sys_class=tmp_path / "sys")
    assert not ok and "cannot load modules" in why and "make test-radio" in why
    (tmp_path / "proc").mkdir()
    (tmp_path / "proc" / "modules").write_text("")
    ok, why = doctor.radio_support(proc=tmp_path / "proc", sys_class=tmp_path / "sys")
    assert not ok and "modprobe mac80211_hwsim" in why


class _RadioMedium(LabMedium):
    """The medium part of a radio lab, alone (its lab is up, robots r1 and r2 at 0, 0)."""

    def __init__(self, workdir: Path, air_medium: str = "netlab", robots: int = 2) -> None:
        self.air, self._state, self._batch = "radio", "up", 0
        self.air_medium = air_medium
        self.workdir = workdir
        (workdir / "air").mkdir()
        self.topology = Topology(UnitDisc(10.0))
        self._robots = {}
        names = [f"r{i}" for i in range(1, robots + 1)]
        self._radio_addrs = {name: f"42:00:00:00:0{i}:00" for i, name in enumerate(names, 1)}
        self._shapes, self._nft_loss, self._remote = {}, {}, {}
        self._daemon_opts = {}
        for i, name in enumerate(names):
            self.topology.add(name)
            self._robots[name] = Robot(
                name, i, f"nlx-{name}", f"p-{name}", f"02:00:00:00:0{i}:00",
                naming.address_for(1, i), workdir / name, iface=f"wlan{i}",
            )  # fmt: skip

    def robot(self, ref: RobotRef) -> Robot:
        return self._robots[ref if isinstance(ref, str) else ref.name]

    def _check_up(self) -> None:
        pass

    def air_links(self) -> dict[tuple[str, str], float]:
        """The links the radio medium obeys now (its links file)."""
        return airmedium.read_links(self.air_links_file).links


def test_a_radio_lab_refuses_what_needs_the_wired_medium(tmp_path: Path) -> None:
    """docs/scenarios.md: a radio link has no qdisc to shape."""
    medium = _RadioMedium(tmp_path)
    with pytest.raises(NetlabError, match="shaping a link: not on the radio medium yet"):
        medium.shape("r1", delay=10)


@pytest.mark.parametrize(
    ("call", "links"),
    [
        (lambda m: m.partition([["r1"], ["r2"]]), {}),
        (lambda m: m.move("r1", (50.0, 0.0)), {}),
        (
            lambda m: m.set_pair_quality("r1", "r2", loss=10.0, both=False),
            {("r1", "r2"): 10.0, ("r2", "r1"): 0.0},
        ),
        (
            lambda m: (m.partition([["r1"], ["r2"]]), m.merge()),
            {("r1", "r2"): 0.0, ("r2", "r1"): 0.0},
        ),
    ],
)
def test_a_radio_labs_moves_and_partitions_reach_its_medium_as_links(
    tmp_path: Path, call: Callable[[LabMedium], object], links: dict[tuple[str, str], float]
) -> None:
    """The radio medium obeys the range model as the wired one does: the lab's truth and
    the medium's links file agree after each change."""
    medium = _RadioMedium(tmp_path)
    call(medium)
    assert medium.links() == links
    assert medium.air_links() == links


def test_a_mesh_radio_lab_s_truth_links_robots_through_a_third_and_its_air_does_not(
    tmp_path: Path,
) -> None:
    """r1 - r2 - r3 in a line, r1 and r3 out of each other's range: once their sdfrd run in
    802.11s mesh, the lab's truth links r1 and r3 (r2's radio forwards), while the medium
    still carries each frame only between radios in range; in IBSS nobody forwards."""
    medium = _RadioMedium(tmp_path, robots=3)
    for i, name in enumerate(("r1", "r2", "r3")):
        medium.move(name, (8.0 * i, 0.0))
    direct = {(a, b): 0.0 for a, b in [("r1", "r2"), ("r2", "r1"), ("r2", "r3"), ("r3", "r2")]}
    medium._daemon_opts = {name: {"wifi_mode": "ibss"} for name in ("r1", "r2", "r3")}
    assert medium.mesh_radios() == set() and medium.links() == direct
    medium._daemon_opts = {name: {"wifi_mode": "mesh"} for name in ("r1", "r2", "r3")}
    assert medium.mesh_radios() == {"r1", "r2", "r3"}
    assert medium.links() == {**direct, ("r1", "r3"): 0.0, ("r3", "r1"): 0.0}
    assert medium.air_links() == direct  # the air itself: only radios in range
    medium.move("r2", (8.0, 30.0))  # the relay walks away: nobody hears anybody
    assert medium.links() == {} and medium.air_links() == {}


@pytest.mark.parametrize(
    ("call", "what"),
    [
        (lambda m: m.partition([["r1"], ["r2"]]), "a partition"),
        (lambda m: m.move("r1", (50.0, 0.0)), "moving a robot"),
        (lambda m: m.merge(), "a merge"),
        (lambda m: m.set_pair_quality("r1", "r2", loss=10.0), "a pair's loss"),
    ],
)
def test_a_radio_lab_on_hwsim_s_own_medium_refuses_what_needs_ranges(
    tmp_path: Path, call: Callable[[LabMedium], object], what: str
) -> None:
    """On hwsim's own medium every radio hears every other: the lab's truth says so, and
    what would need the range model is refused, saying which medium would obey it."""
    medium = _RadioMedium(tmp_path, air_medium="hwsim")
    assert medium.links() == {("r1", "r2"): 0.0, ("r2", "r1"): 0.0}
    with pytest.raises(NetlabError, match=f"{what}: this radio lab is on hwsim's own medium"):
        call(medium)
    assert not medium.air_links_file.exists()
