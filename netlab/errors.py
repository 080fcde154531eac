"""netlab's exception hierarchy, and the translation of kernel errors into it.

Every error netlab raises on purpose derives from NetlabError, and its
message says what failed and what to do about it. Library errors
(pyroute2's NetlinkError, OSError, CalledProcessError) are translated at
the boundary by `kernel_errors(doing)`, so callers never see a bare errno.
"""

from __future__ import annotations

import errno
import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache


class NetlabError(Exception):
    """Base of every error netlab raises on purpose."""


class LabNameError(NetlabError, ValueError):
    """A lab or robot name does not follow the naming rules."""


class LabExistsError(NetlabError):
    """A lab of that name is already up (or left behind by a runner that died)."""


class LabNotFoundError(NetlabError, LookupError):
    """No lab of that name is up."""


class UnknownRobotError(NetlabError, LookupError):
    """The lab has no robot of that name."""


class LabStateError(NetlabError):
    """The call does not fit the lab's state (not up yet, already down, daemon not running)."""


class DaemonError(NetlabError):
    """sdfrd did not start, did not become healthy in time, or did not stop."""


class InvalidShapeError(NetlabError, ValueError):
    """Link shaping parameters out of range or inconsistent."""


class ShapingUnsupported(NetlabError):
    """This kernel cannot do the requested shaping; the message names the missing module."""


def missing_extra(exc: ImportError, feature: str) -> NetlabError:
    """The error of a feature whose library (scapy, matplotlib: the netlab extra) is missing."""
    from sdfr import need_extra

    package = (exc.name or "").split(".")[0] or str(exc)
    return NetlabError(need_extra("netlab", feature, package))


class KernelError(NetlabError):
    """A netlink, nftables or namespace operation failed; the message says which and why."""

    def __init__(self, message: str, errno_: int | None = None) -> None:
        super().__init__(message)
        self.errno = errno_


_HINTS = {
    errno.EPERM: "netlab needs root (CAP_NET_ADMIN and CAP_SYS_ADMIN): run it with sudo",
    errno.EACCES: "netlab needs root (CAP_NET_ADMIN and CAP_SYS_ADMIN): run it with sudo",
    errno.EEXIST: "it already exists: a lab of that name may be up (`netlab status`), "
    "or left behind (`netlab down NAME`)",
    errno.ENOENT: "it does not exist (any more): was the lab taken down meanwhile?",
    errno.ENODEV: "no such network device: was the robot removed or its namespace deleted?",
    errno.EOPNOTSUPP: "this kernel does not support it: `netlab doctor` lists what is there",
    errno.ENOMEM: "the kernel is out of memory for it: try a smaller lab",
    errno.EBUSY: "it is busy: another netlab command may be working on the same lab",
}


@cache
def _netlink_error() -> type[Exception]:
    # Imported late: pyroute2 takes 0.3 s to import, and the analysis modules, which
    # share this hierarchy, never touch the kernel.
    from pyroute2.netlink.exceptions import NetlinkError

    return NetlinkError  # type: ignore[no-any-return]


def describe(exc: BaseException, doing: str) -> str:
    """A one-line message for a library error raised while `doing` something."""
    if isinstance(exc, _netlink_error()):
        code = int(exc.code)  # type: ignore[attr-defined]
        reason = str(exc.args[1]) if len(exc.args) > 1 and exc.args[1] else _strerror(code)
    elif isinstance(exc, subprocess.CalledProcessError):
        out = exc.stderr or exc.output or b""
        text = out.decode(errors="replace") if isinstance(out, bytes) else str(out)
        detail = " ".join(text.split())[:300] or f"exit status {exc.returncode}"
        return f"{doing} failed: {detail}"
    elif isinstance(exc, OSError):
        code = exc.errno or 0
        reason = exc.strerror or str(exc)
    else:
        return f"{doing} failed: {exc}"
    hint = _HINTS.get(code)
    return f"{doing} failed: {reason}" + (f" ({hint})" if hint else "")


def _strerror(code: int) -> str:
    try:
        return os.strerror(code)
    except ValueError:
        return f"error {code}"


def error_code(exc: BaseException) -> int | None:
    """The errno of a NetlinkError or OSError, else None."""
    if isinstance(exc, _netlink_error()):
        return int(exc.code)  # type: ignore[attr-defined]
    if isinstance(exc, OSError):
        return exc.errno
    return None


@contextmanager
def kernel_errors(doing: str) -> Iterator[None]:
    """Translate NetlinkError/OSError/SubprocessError raised inside into KernelError."""
    try:
        yield
    except NetlabError:
        raise
    except Exception as exc:
        if isinstance(exc, OSError | subprocess.SubprocessError | _netlink_error()):
            raise KernelError(describe(exc, doing), error_code(exc)) from exc
        raise
