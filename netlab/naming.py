"""Names, MAC and IPv4 addresses of lab objects: pure functions, one place for the rules.

Every kernel object of a lab carries the lab's name, so that `netlab down`
can find exactly its objects after the runner died:

* namespaces ``nl-<lab>-air`` (the medium) and ``nl-<lab>-<robot>``;
* everything else (bridge, veths, nft table, qdiscs) lives inside those
  namespaces and disappears with them.

Lab names are 1-8 characters ``[a-z0-9]`` (no dash, so the prefix
``nl-<lab>-`` of one lab never matches another lab's namespaces); robot
names 1-12 characters ``[a-z0-9-]`` starting with a letter or digit, so
that the air-side port ``v<robot>`` fits the kernel's 15-character limit.
"""

from __future__ import annotations

import hashlib
import ipaddress
import itertools
import os
import re
from collections.abc import Iterable

from netlab.errors import LabNameError

NS_PREFIX = "nl-"
AIR = "air"
BRIDGE = "br0"
ROBOT_IFACE = "eth0"
PREFIXLEN = 16
HOSTS_PER_BLOCK = 250
MAX_ROBOTS = 256 * HOSTS_PER_BLOCK

LAB_NAME_RE = re.compile(r"^[a-z0-9]{1,8}$")
ROBOT_NAME_RE = re.compile(r"^[a-z0-9][a-z0-9-]{0,11}$")
MAC_RE = re.compile(r"^[0-9a-f]{2}(:[0-9a-f]{2}){5}$")


def b36(n: int, width: int = 1) -> str:
    """`n` (>= 0) in base 36, lower case, zero-padded to `width`: compact unique names."""
    digits = "0123456789abcdefghijklmnopqrstuvwxyz"
    out = ""
    while n or len(out) < width:
        n, rem = divmod(n, 36)
        out = digits[rem] + out
    return out


def check_lab_name(name: str) -> str:
    """Return `name`, or raise LabNameError saying what a lab name may be."""
    if not LAB_NAME_RE.match(name):
        raise LabNameError(
            f"lab name {name!r}: must be 1-8 characters of a-z and 0-9 (it is part of "
            "every namespace name: nl-<lab>-<robot>)"
        )
    return name


def check_robot_name(name: str) -> str:
    """Return `name`, or raise LabNameError saying what a robot name may be."""
    if not ROBOT_NAME_RE.match(name) or name == AIR:
        raise LabNameError(
            f"robot name {name!r}: must be 1-12 characters of a-z, 0-9 and '-', starting "
            f"with a letter or digit, and not {AIR!r} (reserved for the medium)"
        )
    return name


_serial = itertools.count()


def unique_lab_name(letter: str, taken: Iterable[str] = ()) -> str:
    """`letter` + this process (4 base-36 digits) + a counter: at most 8 characters, unique on
    this machine while the process runs.  A name with a namespace in `taken` is skipped."""
    if not re.fullmatch(r"[a-z]", letter):
        raise ValueError(f"a lab name starts with one letter a-z, got {letter!r}")
    busy = list(taken)
    while True:
        name = f"{letter}{b36(os.getpid() % 36**4, 4)}{b36(next(_serial) % 36**3)}"
        if not any(ns.startswith(prefix(name)) for ns in busy):
            return name


def prefix(lab: str) -> str:
    """The prefix of every namespace of `lab`."""
    return f"{NS_PREFIX}{lab}-"


def air_ns(lab: str) -> str:
    return f"{prefix(lab)}{AIR}"


def robot_ns(lab: str, robot: str) -> str:
    return f"{prefix(lab)}{robot}"


def port(robot: str) -> str:
    """The robot's port on the medium bridge (in the air namespace)."""
    return f"v{robot}"


def mac_text(raw: bytes) -> str:
    """6 bytes as ``aa:bb:cc:dd:ee:ff``."""
    return ":".join(f"{b:02x}" for b in raw)


def mac_for(seed: int, index: int) -> str:
    """A locally administered unicast MAC, the same for the same seed and robot index."""
    digest = hashlib.sha256(f"netlab-mac:{seed}:{index}".encode()).digest()
    return ":".join(f"{b:02x}" for b in (0x02, *digest[:5]))


def check_mac(mac: str) -> str:
    """Return `mac` in lower case, or raise LabNameError unless it is a unicast MAC."""
    low = mac.lower()
    if not MAC_RE.match(low) or int(low[:2], 16) & 1 or low == "00:00:00:00:00:00":
        raise LabNameError(f"mac {mac!r}: expected a unicast MAC like 02:00:00:00:00:01")
    return low


def address_for(fleet: int, index: int) -> ipaddress.IPv4Interface:
    """Robot `index` (from 0) of `fleet`: 10.<fleet>.<index // 250>.<index % 250 + 1>/16.

    Static for now; sdfrd's self-configured addresses replace this later.
    """
    if not 0 <= fleet <= 255:
        raise LabNameError(
            f"fleet: must be 0-255 (the second octet of 10.<fleet>.x.y), got {fleet}"
        )
    if not 0 <= index < MAX_ROBOTS:
        raise LabNameError(f"robot index {index}: at most {MAX_ROBOTS} robots per lab")
    hi, lo = divmod(index, HOSTS_PER_BLOCK)
    return ipaddress.IPv4Interface(f"10.{fleet}.{hi}.{lo + 1}/{PREFIXLEN}")
