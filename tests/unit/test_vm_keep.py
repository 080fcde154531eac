"""A VM tier keeps a failed test's lab folders (tests/support/vmkeep.py): daemon logs and
state copied out of the VM, sockets left behind, and the failure says where."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from tests.support.vmkeep import (
    GUEST_ENV,
    KEEP_ENV,
    check_guest_folders,
    fs_type,
    keep_failed,
    keep_tree,
)


def a_lab(base: Path) -> Path:
    """A lab folder as a fleet leaves it: logs, state, a pcap, the API's socket, a fifo."""
    robot = base / "netem-fleet0" / "lab" / "r3"
    (robot / "state").mkdir(parents=True)
    (robot / "sdfrd.log").write_text("sdfrd INFO api layer started\n")
    (robot / "state" / "status.json").write_text('{"up": true}')
    (base / "netem-fleet0" / "r3.pcap").write_bytes(b"\xd4\xc3\xb2\xa1")
    os.symlink("sdfrd.log", robot / "latest.log")
    # (Bound through the folder's descriptor: a worker's tmp_path can be longer than
    # AF_UNIX's 107 bytes.)
    folder = os.open(robot / "state", os.O_PATH | os.O_DIRECTORY)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        listener.bind(f"/proc/self/fd/{folder}/api.sock")
    finally:
        listener.close()
        os.close(folder)
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


# A guest's mount table as virtme-ng makes it: / from the host (9p), /tmp an overlay whose
# lower layer is the host's /tmp, /run a tmpfs, and the tmpfs vm.sh mounts for the tests.
MOUNTINFO = """\
22 1 0:20 / / ro,relatime - 9p /dev/root ro,access=any,trans=virtio
30 22 0:26 / /run rw,relatime - tmpfs run rw,mode=755
41 22 0:35 / /tmp rw,relatime - overlay virtme_rw_overlay7 rw,lowerdir=/tmp,upperdir=/run/tmp
44 41 0:38 / /tmp/sdfr-vm-netem.abc rw,relatime - 9p rwdir1 rw,access=any
52 30 0:41 / /run/sdfr-vm rw,relatime - tmpfs sdfr-vm rw,mode=700
53 22 0:42 / /srv/a\\040b rw,relatime - tmpfs x rw
"""


@pytest.mark.parametrize(
    ("path", "kind"),
    [
        ("/tmp/pytest-of-root/pytest-306/netem-fleet0/lab/r3/state", "overlay"),
        ("/tmp", "overlay"),
        ("/tmp/sdfr-vm-netem.abc/junit.xml", "9p"),
        ("/tmp/sdfr-vm-netem.abcd", "overlay"),  # (not under the 9p mount: a longer name)
        ("/run/sdfr-vm/pytest/netem-fleet0", "tmpfs"),
        ("/run/tmp", "tmpfs"),
        ("/srv/a b/c", "tmpfs"),
        ("/work/main", "9p"),
    ],
)
def test_fs_type_is_the_deepest_mount_above_a_path(path: str, kind: str) -> None:
    assert fs_type(Path(path), MOUNTINFO) == kind


def test_in_the_guest_the_tests_folders_must_not_be_on_the_hosts_overlay(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    overlay = Path("/tmp/pytest-of-root/pytest-306")
    own = Path("/run/sdfr-vm/pytest")
    monkeypatch.delenv(GUEST_ENV, raising=False)
    assert check_guest_folders(overlay, MOUNTINFO) is None  # (not in the VM: wherever it is)
    monkeypatch.setenv(GUEST_ENV, "1")
    why = check_guest_folders(overlay, MOUNTINFO)
    assert why is not None and str(overlay) in why and "overlay" in why and "tmpfs" in why
    assert check_guest_folders(own, MOUNTINFO) is None
