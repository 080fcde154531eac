"""Process-level adapters: the supervisor and the two layers it runs.

`main` is sdfrd's entry point (the `sdfrd` command, `python -m sdfr.daemon`). Before anything
imports them it keeps out of the daemon the modules it does not need (NOT_LOADED), whose
memory every daemon would carry (docs/fleet-behaviour.md has the figures):

- OpenSSL: `ssl` (which asyncio loads only to offer TLS) and `_hashlib` (hashlib's OpenSSL
  backend) map libssl and libcrypto for nothing sdfrd does. hashlib then uses CPython's own
  SHA-256 and BLAKE2, and hmac its pure-Python HMAC (slower per signed datagram). A
  library that needs OpenSSL (pyroute2, with `--addressing auto`) gets it: `allow_openssl`.
- `typing_extensions`, which msgspec uses when it is installed and does without (typing's
  own `get_type_hints`, `Required` and `NotRequired` since Python 3.11, and msgspec's
  fallback on 3.10).

First of all, the `sdfrd` command pins glibc malloc's mmap threshold (`pin_malloc`).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping

#: Modules sdfrd's processes never load (see the module docstring).
NOT_LOADED = ("ssl", "_ssl", "_hashlib", "typing_extensions")

#: glibc's default mmap threshold, pinned (see `pin_malloc`).
MALLOC_TUNABLES = "glibc.malloc.mmap_threshold=131072"


def own_malloc_settings(env: Mapping[str, str]) -> bool:
    """Whether `env` has malloc settings of its user's (which sdfrd leaves alone)."""
    return bool(env.get("GLIBC_TUNABLES")) or any(k.startswith("MALLOC_") for k in env)


def pin_malloc() -> None:
    """Run under glibc with a fixed mmap threshold: re-exec once with GLIBC_TUNABLES set.

    glibc raises its mmap threshold to the size of any mmap-ed block that is freed, and its
    trim threshold to twice that, in every thread's heap. Reading a large .pyc, resizing the
    interned-strings table and asyncio's large socket reads (each freed whole when the peer
    closes) raise them, after which each heap keeps that much memory it has freed, for
    good: a share of the daemon's memory (docs/fleet-behaviour.md). A fixed threshold turns
    the adjustment off. The tunables are read when the process starts, hence the exec (same
    pid, same argv); a user's own GLIBC_TUNABLES or MALLOC_* settings are left alone, as is
    a C library that is not glibc.
    """
    if own_malloc_settings(os.environ):
        return
    if not sys.executable or not sys.orig_argv:  # (an embedded interpreter: nothing to exec)
        return
    try:
        if not os.confstr("CS_GNU_LIBC_VERSION"):
            return
    except (ValueError, OSError):  # not glibc
        return
    os.environ["GLIBC_TUNABLES"] = MALLOC_TUNABLES
    try:
        os.execv(sys.executable, sys.orig_argv)
    except (OSError, ValueError):  # then without: nothing but memory depends on it
        del os.environ["GLIBC_TUNABLES"]


def allow_openssl() -> None:
    """Let a library that needs OpenSSL load it after all: pyroute2 (imported by the discovery
    layer only with `--addressing auto`) imports ssl. Only that process pays for it."""
    for name in NOT_LOADED:
        if name in sys.modules and sys.modules[name] is None:
            del sys.modules[name]


def main(argv: list[str] | None = None) -> int:
    """sdfrd (its command line when `argv` is None: only then is it the process's own)."""
    if argv is None:
        pin_malloc()
    for name in NOT_LOADED:
        if name not in sys.modules:
            sys.modules[name] = None  # type: ignore[assignment]
    from sdfr.daemon import supervisor

    return supervisor.main(argv)
