"""The pytest hooks of a VM tier (tests/netem, tests/radio): the tests' folders on the
guest's own tmpfs, and a failed test's lab folders kept (see tests/support/vmkeep.py).
A tier's conftest.py imports them by name, which is how pytest finds them there."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.support.vmkeep import check_guest_folders, keep_failed

_kept: list[str] = []


def pytest_sessionstart(session: pytest.Session) -> None:
    factory = getattr(session.config, "_tmp_path_factory", None)
    if factory is not None and (why := check_guest_folders(Path(factory.getbasetemp()))):
        raise pytest.UsageError(why)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    outcome = yield
    report: pytest.TestReport = outcome.get_result()
    if not report.failed:
        return
    factory = getattr(item.config, "_tmp_path_factory", None)
    if factory is None:  # (no tmpdir plugin: no folders to keep)
        return
    text = keep_failed(Path(factory.getbasetemp()), f"{item.nodeid} ({report.when})")
    report.sections.append(("kept logs", text))
    _kept.append(text)


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    if _kept:
        terminalreporter.section("VM tier: kept logs")
        for text in _kept:
            terminalreporter.write_line(text)
