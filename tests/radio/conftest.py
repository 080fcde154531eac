"""The radio tier's folders: on the guest's own tmpfs in the VM, and a failure keeps them
(tests/support/vmtier.py)."""

from __future__ import annotations

import shutil

import pytest

from netlab import hwsim
from tests.support.vmtier import (
    pytest_runtest_makereport,
    pytest_sessionstart,
    pytest_terminal_summary,
)

__all__ = [
    "pytest_runtest_makereport",
    "pytest_sessionstart",
    "pytest_terminal_summary",
    "radios",
]


@pytest.fixture(autouse=True)
def radios() -> None:
    """Every radio test: skipped, saying why, where the kernel has no mac80211_hwsim (this
    host); in the VM, the programs the robots need must be there."""
    if not hwsim.loaded():
        pytest.skip(
            "no mac80211_hwsim in this kernel (this host has no wireless stack): "
            "`make test-radio` runs these tests in a VM"
        )
    missing = [t for t in ("iw", "wpa_supplicant", "tcpdump") if shutil.which(t) is None]
    assert not missing, f"{missing} not installed: scripts/bootstrap-vm.sh radio installs them"
