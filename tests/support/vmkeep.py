"""Where a VM tier's folders are, and keeping them when a test fails.

In the VM the tests' folders (the labs: their daemons' logs, sockets and state) must be on a
filesystem of the guest's own: its /tmp is an overlay of the host's /tmp, which the host
changes underneath (`check_guest_folders`; scripts/vm.sh mounts a tmpfs for them).

Those folders end with the VM. When a test fails, `keep_tree` copies the session's
temporary folders -- every lab's robots' `sdfrd.log`, `state/` and the pcaps -- into
$SDFR_KEEP_LOGS, a folder `scripts/vm.sh` shares with the guest (`--rwdir`), so they
are on the host after the VM is gone, even if it is killed later on. Sockets, pipes and
devices are not copied: they mean nothing once their process is gone.
"""

from __future__ import annotations

import os
import re
import shutil
import stat
from pathlib import Path

#: The folder a failed test's lab folders are copied into (set by scripts/vm.sh).
KEEP_ENV = "SDFR_KEEP_LOGS"
#: Set by scripts/vm.sh in the guest, whose tests' folders must be on its own tmpfs.
GUEST_ENV = "SDFR_VM_GUEST"


def _unescape(field: str) -> str:
    """A path of /proc/self/mountinfo, whose spaces and such are written in octal (\\040)."""
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), field)


def fs_type(path: Path, mountinfo: str) -> str:
    """The type of the filesystem `path` (absolute, links resolved) is on, by the mount table
    `mountinfo` (the text of /proc/self/mountinfo): its deepest mount point above `path`."""
    best, kind = "", "?"
    for line in mountinfo.splitlines():
        fields = line.split()
        if "-" not in fields[6:]:
            continue
        point = _unescape(fields[4])
        sep = fields.index("-", 6)
        inside = path == Path(point) or Path(point) in path.parents
        if inside and len(point) >= len(best):  # (a later mount on the same point hides it)
            best, kind = point, fields[sep + 1]
    return kind


def check_guest_folders(basetemp: Path, mountinfo: str | None = None) -> str | None:
    """In the VM (GUEST_ENV set): why the tests' folders must not be where they are, or None.
    The guest's /tmp is an overlay of the host's /tmp, which the host changes underneath
    (its own pytest runs make and remove pytest-of-root/pytest-N there). `mountinfo`: the
    mount table (default: this process's)."""
    if not os.environ.get(GUEST_ENV):
        return None
    if mountinfo is None:
        with open("/proc/self/mountinfo") as f:
            mountinfo = f.read()
    kind = fs_type(basetemp.resolve(), mountinfo)
    if kind == "overlay":
        return (
            f"the tests' folders ({basetemp}) are on an overlay of the host's filesystem, "
            "which the host changes underneath; scripts/vm.sh gives them a tmpfs "
            "(pytest --basetemp) of the guest's own"
        )
    return None


def _copy(src: Path, dest: Path) -> None:
    """One entry: a folder is made, a file copied, a link made again (replacing what is at
    `dest`); anything else (a socket, a pipe, a device) is left."""
    mode = src.lstat().st_mode
    if stat.S_ISDIR(mode):
        dest.mkdir(parents=True, exist_ok=True)
    elif stat.S_ISLNK(mode):
        target = os.readlink(src)
        if dest.is_symlink() or dest.exists():
            dest.unlink()
        os.symlink(target, dest)
    elif stat.S_ISREG(mode):
        shutil.copy2(src, dest)


def keep_tree(src: Path, dest: Path) -> list[str]:
    """Copy the folder `src` into `dest` (made if needed; what is there already is updated),
    folders, files and links only; the problems met, one line each (a file that vanished
    while copied, a full disk), empty when all was copied."""
    problems = []
    for folder, dirs, files in os.walk(src):
        here = Path(folder)
        links = [d for d in dirs if (here / d).is_symlink()]  # (os.walk does not enter them)
        for name in ["", *links, *files]:  # ("": the folder itself)
            entry = here / name if name else here
            target = dest / entry.relative_to(src)
            try:
                _copy(entry, target)
            except OSError as exc:
                problems.append(f"{entry} -> {target}: {exc.strerror or exc}")
                if not name:  # the folder cannot be made: nothing in it can be copied
                    dirs.clear()
                    break
    return problems


def keep_failed(basetemp: Path, test: str) -> str:
    """After `test` failed: copy `basetemp` (the session's temporary folders) into
    $SDFR_KEEP_LOGS when set, and say where the lab folders are (the text for the report)."""
    where = os.environ.get(KEEP_ENV)
    if not where:
        return (
            f"the lab folders (daemon logs, state, pcaps) of {test} are in {basetemp} "
            f"(set {KEEP_ENV}=DIR to copy them elsewhere)"
        )
    dest = Path(where)
    problems = keep_tree(basetemp, dest)
    text = f"the lab folders (daemon logs, state, pcaps) of {test} are kept in {dest}"
    if problems:
        text += f"; not all could be copied ({len(problems)}):\n  " + "\n  ".join(problems[:10])
    return text
