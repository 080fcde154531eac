"""netlab.hwsim's generic netlink codec, on bytes (the radios themselves: tests/radio)."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from netlab import doctor, hwsim


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
