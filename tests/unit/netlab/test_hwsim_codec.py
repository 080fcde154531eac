"""netlab.hwsim's generic netlink codec, on bytes (the radios themselves: tests/radio), what
the doctor says of radios, and what a radio lab refuses."""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path
from typing import cast

import pytest

from netlab import doctor, hwsim
from netlab.errors import NetlabError
from netlab.labmedium import LabMedium
from netlab.ranges import Topology
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
    """The medium part of a radio lab, alone (its lab is up, robots r1 and r2)."""

    def __init__(self) -> None:
        self.air, self._state, self._batch = "radio", "up", 0
        self.topology = Topology()
        self._robots = {}
        self._shapes, self._nft_loss = {}, {}
        for name in ("r1", "r2"):
            self.topology.add(name)
            self._robots[name] = cast(Robot, name)

    def robot(self, ref: RobotRef) -> Robot:
        return cast(Robot, ref)

    def _check_up(self) -> None:
        pass


@pytest.mark.parametrize(
    ("what", "call"),
    [
        ("a partition", lambda m: m.partition([["r1"], ["r2"]])),
        ("a merge", lambda m: m.merge()),
        ("moving a robot", lambda m: m.move("r1", (5.0, 0.0))),
        ("a pair's loss", lambda m: m.set_pair_quality("r1", "r2", loss=10.0)),
        ("shaping a link", lambda m: m.shape("r1", delay=10)),
    ],
)
def test_a_radio_lab_refuses_what_needs_the_wired_medium(
    what: str, call: Callable[[LabMedium], object]
) -> None:
    """docs/scenarios.md: every radio hears every other; the wired medium's rules say so."""
    medium = _RadioMedium()
    with pytest.raises(NetlabError, match=f"{what}: not on the radio medium yet"):
        call(medium)
    assert medium.links() == {("r1", "r2"): 0.0, ("r2", "r1"): 0.0}
