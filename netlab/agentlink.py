"""The controller's end of a host's `netlab.agent` session: `Part` sends requests and reads
answers over the session's stdin and stdout (JSON lines), and `AgentClient` asks a robot's
daemon's API through it, as `sdfr.client.Client` would (`netlab.observe.ClientLike`)."""

from __future__ import annotations

import contextlib
import json
import subprocess
import threading
from collections.abc import Mapping
from typing import Any

from netlab.hosts import HostError, Ssh
from sdfr.errors import ApiError


class Part:
    """One host's agent: requests in, answers out, over the ssh session."""

    def __init__(self, ssh: Ssh, env: Mapping[str, str] | None = None) -> None:
        self.ssh = ssh
        prefix = ["env", *(f"{k}={v}" for k, v in (env or {}).items())] if env else []
        argv = ssh.argv([*prefix, ssh.python, "-m", "netlab.agent"])
        self.proc = subprocess.Popen(
            argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        # One request at a time: the engine's observer asks from its own thread.
        self._lock = threading.Lock()

    def call(self, op: str, **kw: Any) -> Any:
        """One request; its result, or HostError naming the host and what it said (ApiError
        when a robot's daemon refused an ``api`` call, as the client there raised it)."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        with self._lock:
            try:
                self.proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
                self.proc.stdin.flush()
            except (BrokenPipeError, OSError):
                raise HostError(f"host {self.ssh.destination}: {op}: {self._ended()}") from None
            line = self.proc.stdout.readline()
        if not line:
            raise HostError(f"host {self.ssh.destination}: {op}: {self._ended()}")
        answer = json.loads(line)
        if not answer.get("ok"):
            api = answer.get("api")
            if isinstance(api, dict):
                raise ApiError(int(api["status"]), str(api["message"]), api.get("field"))
            raise HostError(f"host {self.ssh.destination}: {answer.get('error')}")
        return answer.get("result")

    def _ended(self) -> str:
        try:
            code: int | None = self.proc.wait(5)  # its stdout closed: it is ending
        except subprocess.TimeoutExpired:
            code = None
        err = self.proc.stderr.read() if self.proc.stderr and code is not None else ""
        said = err.strip().splitlines()[-1] if err.strip() else "no word"
        if code == 255:
            return f"cannot be reached over ssh ({said})"
        return f"its agent ended ({said})"

    def close(self, timeout: float = 60.0) -> None:
        if self.proc.stdin is not None:
            with contextlib.suppress(OSError):
                self.proc.stdin.close()
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


class AgentClient:
    """A robot's daemon's API, asked through its host's agent (`netlab.observe.ClientLike`).
    A host that cannot be asked is an ApiError too: the robot cannot be asked."""

    def __init__(self, part: Part, robot: str) -> None:
        self.part = part
        self.robot = robot

    def _call(self, call: str, **args: Any) -> Any:
        try:
            return self.part.call("api", robot=self.robot, call=call, args=args)
        except HostError as exc:
            raise ApiError(0, str(exc)) from None

    def neighbors(self, include_unreachable: bool = False) -> list[dict[str, Any]]:
        return list(self._call("neighbors", include_unreachable=include_unreachable))

    def history(self) -> list[dict[str, Any]]:
        return list(self._call("history"))

    def publish(self, name: str, type: str, url: str | None = None,
                attributes: Mapping[str, Any] | None = None) -> str:  # fmt: skip
        attrs = dict(attributes) if attributes is not None else None
        return str(self._call("publish", name=name, type=type, url=url, attributes=attrs))

    def unpublish(self, service_id: str) -> None:
        self._call("unpublish", service_id=service_id)

    def self_info(self) -> dict[str, object]:
        return dict(self._call("self_info"))

    def close(self) -> None:
        pass
