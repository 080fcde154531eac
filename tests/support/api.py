"""Helpers for tests of the API layer: an async test runner, raw HTTP exchanges, a free
port, and the API layer's process on a state directory."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import os
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Coroutine
from pathlib import Path
from typing import Any

import pytest
from aiohttp import ClientSession

from sdfr.api import App, Runner, TCPSite
from sdfr.client import Client
from sdfr.errors import ApiError


def aio(fn: Callable[..., Coroutine[Any, Any, None]]) -> Callable[..., None]:
    """Run an async test in its own event loop (no pytest-asyncio here); fixtures still apply."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> None:
        asyncio.run(fn(*args, **kwargs))

    return run


def raw_exchange(port: int, request: bytes) -> tuple[int, dict[str, str], bytes]:
    """Send bytes to a server on 127.0.0.1, read its whole answer: status, headers, body."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
        sock.sendall(request)
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    headers = {k.lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])}
    return int(lines[0].split()[1]), headers, body


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class ApiLayer:
    """`python -m sdfr.daemon.apiserver` on a state directory; always stopped by its owner."""

    def __init__(self, state_dir: Path, api_port: int | None = None) -> None:
        self.state_dir = state_dir
        self.api = f"127.0.0.1:{api_port or free_port()}"
        self.describe = f"127.0.0.1:{free_port()}"
        self.socket = state_dir / "api.sock"
        self.log = state_dir / "apiserver.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def argv(self) -> list[str]:
        return [
            sys.executable,
            "-m",
            "sdfr.daemon.apiserver",
            "--state-dir",
            str(self.state_dir),
            "--api",
            self.api,
            "--describe",
            self.describe,
            "--robot-id",
            "r1",
            "--iface",
            "lo",
        ]

    def start(self, timeout: float = 20.0) -> None:
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen(self.argv(), stdout=log, stderr=log)
        deadline = time.monotonic() + timeout
        with Client(self.api, timeout=1.0) as client:
            while True:
                if self.proc.poll() is not None:
                    pytest.fail(f"apiserver exited with {self.proc.returncode}: {self.logs()}")
                try:
                    client.health()  # 503 while discovery is down: still an answer
                    return
                except ApiError as exc:
                    if exc.status != 0 or time.monotonic() > deadline:
                        self.stop()
                        pytest.fail(f"apiserver not ready: {exc}; log: {self.logs()}")
                time.sleep(0.05)

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.kill()
        self.proc.wait(timeout=10)

    def stop(self) -> int | None:
        """SIGTERM, then SIGKILL if it lingers; the exit status."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        return self.proc.returncode

    def logs(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""


#: The owner token `serve`'s client sends: its requests are one program's (a test that
#: needs another program makes a client of its own).
TEST_OWNER = "tests-one-program-s-owner-token"


@contextlib.asynccontextmanager
async def serve(app: App) -> AsyncIterator[ClientSession]:
    """`app` served on a free port of 127.0.0.1 by the API's runner, and an HTTP client of it
    (aiohttp's: a client independent of the server under test) taking paths, sending
    TEST_OWNER with each request."""
    runner = Runner(app)
    await runner.setup()
    port = free_port()
    await TCPSite(runner, "127.0.0.1", port).start()
    try:
        async with ClientSession(
            base_url=f"http://127.0.0.1:{port}", headers={"X-SDFR-Owner": TEST_OWNER}
        ) as client:
            yield client
    finally:
        await runner.cleanup()


def status(**extra: Any) -> dict[str, Any]:
    return {
        "pid": os.getpid(),
        "robot_id": "r1",
        "fleet": 7,
        "iface": "lo",
        "address": "10.7.3.4",
        "boot_id": 5,
        "version": 0,
        "started": time.time() - 10,
        "location": "http://10.7.3.4:8701/description.json",
        "peers_reachable": 2,
        "peers_known": 3,
        "counters": {
            "datagrams_in": {"discovery": 1, "response": 2, "update": 3, "alive": 7, "byebye": 0},
            "datagrams_out": {"discovery": 1, "response": 0, "update": 1, "alive": 9, "byebye": 0},
            "bytes_in": 4200,
            "bytes_out": 3100,
            "rejects": {"bad-fleet": 2, 'odd"reason': 1},
        },
        **extra,
    }
