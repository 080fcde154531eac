"""The ns tier's failed-test log keeping (tests/support/fleets.py), without a lab: what is
copied, and where."""

from __future__ import annotations

import socket
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import pytest

from tests.support.fleets import keep_folder, keep_lab_folders


def test_a_failed_tests_lab_folder_is_copied_without_its_sockets(tmp_path: Path) -> None:
    work = tmp_path / "netlab-f1-x"
    (work / "r1" / "state").mkdir(parents=True)
    (work / "r1" / "sdfrd.log").write_text("--- netlab: sdfrd\nstarted\n")
    (work / "r1" / "state" / "peers.json").write_text("{}")
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(work / "r1" / "state" / "api.sock"))
    try:
        lab = cast(Any, SimpleNamespace(name="f1", workdir=work))
        gone = cast(Any, SimpleNamespace(name="f2", workdir=tmp_path / "gone"))
        lines = keep_lab_folders([lab, gone], tmp_path / "kept")
    finally:
        sock.close()
    kept = tmp_path / "kept" / "f1"
    assert lines[0] == f"lab f1: daemon logs kept in {kept} (r1/sdfrd.log)"
    assert lines[1].startswith("lab f2: no folder to keep")
    assert (kept / "r1" / "sdfrd.log").read_text().endswith("started\n")
    assert (kept / "r1" / "state" / "peers.json").exists()
    assert not (kept / "r1" / "state" / "api.sock").exists()


def test_kept_logs_go_under_sdfr_keep_logs_named_after_the_test(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SDFR_KEEP_LOGS", str(tmp_path))
    folder = keep_folder("test_x.py::test_y[3-robots]")
    assert folder.parent == tmp_path and folder.name.startswith("test_x.py_test_y_3-robots-2")
    monkeypatch.delenv("SDFR_KEEP_LOGS")
    assert keep_folder("test_x.py::test_y").parent.name == "tests"  # runs/tests/
