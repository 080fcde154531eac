"""The netem tier keeps a failed test's lab folders (tests/netem/keep.py): daemon logs and
state copied out of the VM, sockets left behind, and the failure says where."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from tests.netem.keep import KEEP_ENV, keep_failed, keep_tree


def a_lab(base: Path) -> Path:
    """A lab folder as a fleet leaves it: logs, state, a pcap, the API's socket, a fifo."""
    robot = base / "netem-fleet0" / "lab" / "r3"
    (robot / "state").mkdir(parents=True)
    (robot / "sdfrd.log").write_text("sdfrd INFO api layer started\n")
    (robot / "state" / "status.json").write_text('{"up": true}')
    (base / "netem-fleet0" / "r3.pcap").write_bytes(b"\xd4\xc3\xb2\xa1")
    os.symlink("sdfrd.log", robot / "latest.log")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(robot / "state" / "api.sock"))
    listener.close()
    os.mkfifo(robot / "state" / "pipe")
    return robot


def test_keep_tree_copies_folders_files_and_links_not_sockets(tmp_path: Path) -> None:
    robot = a_lab(tmp_path / "base")
    dest = tmp_path / "kept"
    assert keep_tree(tmp_path / "base", dest) == []
    kept = dest / robot.relative_to(tmp_path / "base")
    assert (kept / "sdfrd.log").read_text() == "sdfrd INFO api layer started\n"
    assert (kept / "state" / "status.json").read_text() == '{"up": true}'
    assert (dest / "netem-fleet0" / "r3.pcap").read_bytes() == b"\xd4\xc3\xb2\xa1"
    assert os.readlink(kept / "latest.log") == "sdfrd.log"
    assert not (kept / "state" / "api.sock").exists()
    assert not (kept / "state" / "pipe").exists()
    # A later failure copies again over what is there: the log has grown since.
    (robot / "sdfrd.log").write_text("sdfrd INFO api layer started\nsdfrd INFO stopped\n")
    assert keep_tree(tmp_path / "base", dest) == []
    assert (kept / "sdfrd.log").read_text().endswith("stopped\n")


def test_keep_tree_says_what_it_could_not_copy(tmp_path: Path) -> None:
    a_lab(tmp_path / "base")
    dest = tmp_path / "kept"
    dest.write_text("a file where the folder should go")
    problems = keep_tree(tmp_path / "base", dest)
    assert len(problems) == 1 and str(dest) in problems[0], problems


def test_a_failure_copies_the_labs_into_keep_logs_and_says_where(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    a_lab(tmp_path / "base")
    dest = tmp_path / "host" / "sdfr-vm-netem-logs.abc"
    monkeypatch.setenv(KEEP_ENV, str(dest))
    text = keep_failed(tmp_path / "base", "tests/netem/test_netem_fleet.py::t (setup)")
    assert text == (
        "the lab folders (daemon logs, state, pcaps) of tests/netem/test_netem_fleet.py::t "
        f"(setup) are kept in {dest}"
    )
    assert (dest / "netem-fleet0" / "lab" / "r3" / "sdfrd.log").is_file()


def test_without_keep_logs_a_failure_names_pytests_own_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(KEEP_ENV, raising=False)
    text = keep_failed(tmp_path, "t (call)")
    assert f"are in {tmp_path}" in text and KEEP_ENV in text
