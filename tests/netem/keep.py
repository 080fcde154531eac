"""Keeping the lab folders of a failed netem test: what the daemons logged, their state.

The netem tier runs in a VM whose /tmp (where pytest makes the tests' folders, the labs'
workdirs among them) ends with it. When a test fails, `keep_tree` copies the session's
temporary folders -- every lab's robots' `sdfrd.log`, `state/` and the pcaps -- into
$SDFR_KEEP_LOGS, a folder `scripts/vm-netem.sh` shares with the guest (`--rwdir`), so they
are on the host after the VM is gone, even if it is killed later on. Sockets, pipes and
devices are not copied: they mean nothing once their process is gone.
"""

from __future__ import annotations

import os
import shutil
import stat
from pathlib import Path

#: The folder a failed test's lab folders are copied into (set by scripts/vm-netem.sh).
KEEP_ENV = "SDFR_KEEP_LOGS"


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
