"""Start sdfrd when none answers, and stop it again -- only the one the node started."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from sdfr.client import Client
from sdfr.errors import ApiError, SdfrError
from sdfr.ros.params import NodeParams

STOP_TIMEOUT = 10.0


class SpawnError(SdfrError):
    """sdfrd could not be started (or did not answer); the message says why."""


@dataclass(frozen=True, slots=True)
class SpawnedDaemon:
    proc: subprocess.Popen[bytes]
    argv: tuple[str, ...]
    log_path: Path


def answers(connect: Callable[[], Client]) -> bool:
    """Whether a daemon answers on the API (503 from /health is an answer too)."""
    with connect() as client:
        try:
            client.health()
        except ApiError as exc:
            return exc.status != 0
    return True


def resolve(argv: list[str]) -> list[str]:
    """`argv` with its program found: on PATH, else beside this interpreter (a venv's bin/,
    which is not on PATH when the venv is not activated)."""
    program = argv[0]
    if os.sep in program or shutil.which(program):
        return argv
    beside = Path(sys.executable).parent / program
    if beside.is_file() and os.access(beside, os.X_OK):
        return [str(beside), *argv[1:]]
    raise SpawnError(
        f"parameter sdfrd_command: {program!r} is not on PATH nor beside {sys.executable}"
    )


def ensure_daemon(params: NodeParams, connect: Callable[[], Client]) -> SpawnedDaemon | None:
    """None when a daemon answers already (or spawning is off); else the one started here,
    answering.  SpawnError naming the reason when it cannot start."""
    if answers(connect) or not params.spawn:
        return None
    argv = resolve(params.sdfrd_argv())
    log_path = Path(params.sdfrd_log) if params.sdfrd_log else _default_log()
    try:
        with open(log_path, "ab") as out:
            proc = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # its own group: stop_daemon reaches its layers too
            )
    except OSError as exc:
        raise SpawnError(f"cannot start sdfrd ({' '.join(argv)}): {exc}") from None
    spawned = SpawnedDaemon(proc, tuple(argv), log_path)
    deadline = time.monotonic() + params.spawn_timeout
    while True:
        code = proc.poll()
        if code is not None:
            raise SpawnError(
                f"sdfrd ({' '.join(argv)}) exited with status {code} before it answered on "
                f"{params.api}; {log_path} ends with:\n{_tail(log_path)}"
            )
        if answers(connect):
            return spawned
        if time.monotonic() > deadline:
            stop_daemon(spawned)
            raise SpawnError(
                f"sdfrd ({' '.join(argv)}) did not answer on {params.api} within "
                f"{params.spawn_timeout} s; stopped it. {log_path} ends with:\n{_tail(log_path)}"
            )
        time.sleep(0.05)


def stop_daemon(spawned: SpawnedDaemon, timeout: float = STOP_TIMEOUT) -> int:
    """SIGTERM to the daemon (it stops its layers and says Byebye), SIGKILL to its whole
    process group if it lingers."""
    proc = spawned.proc
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode


def _default_log() -> Path:
    fd, name = tempfile.mkstemp(prefix="sdfr-node-sdfrd-", suffix=".log")
    os.close(fd)
    return Path(name)


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no output)"
