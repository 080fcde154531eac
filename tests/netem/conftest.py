"""The netem tier's folders: on the guest's own tmpfs in the VM, and a failure keeps them
(tests/support/vmtier.py)."""

from __future__ import annotations

from tests.support.vmtier import (
    pytest_runtest_makereport,
    pytest_sessionstart,
    pytest_terminal_summary,
)

__all__ = ["pytest_runtest_makereport", "pytest_sessionstart", "pytest_terminal_summary"]
