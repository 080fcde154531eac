"""Process-level adapters: the supervisor and the two layers it runs.

`main` is sdfrd's entry point (the `sdfrd` command, `python -m sdfr.daemon`). Before anything
imports them it keeps OpenSSL out of the daemon: `ssl` (which asyncio loads only to offer
TLS) and `_hashlib` (hashlib's OpenSSL backend) map libssl and libcrypto, about 4 MiB of
every sdfrd's process tree, for nothing sdfrd does. hashlib then uses CPython's own SHA-256
and BLAKE2, and hmac its pure-Python HMAC (about 5 us a signed datagram instead of 2). A
library that needs OpenSSL (pyroute2, with `--addressing auto`) gets it: `allow_openssl`.
It also keeps out `typing_extensions`, which msgspec uses when it is installed and does
without (typing's own `get_type_hints`, `Required` and `NotRequired` since Python 3.11, and
msgspec's fallback on 3.10): 0.35 MiB less for each daemon (USS, measured with netlab).

First of all, the `sdfrd` command pins glibc malloc's mmap threshold (`pin_malloc`).
"""

from __future__ import annotations

import os
import sys

#: Modules sdfrd's processes never load (see the module docstring).
NOT_LOADED = ("ssl", "_ssl", "_hashlib", "typing_extensions")

#: glibc's default mmap threshold, pinned (see `pin_malloc`).
MALLOC_TUNABLES = "glibc.malloc.mmap_threshold=131072"


def pin_malloc() -> None:
    """Run under glibc with a fixed mmap threshold: re-exec once with GLIBC_TUNABLES set.

    glibc raises its mmap threshold to the size of any mmap-ed block that is freed, and its
    trim threshold to twice that, in every thread's heap. Reading a large .pyc, resizing the
    interned-strings table and asyncio's 256 KiB socket reads (each freed whole when the
    peer closes) raise them to ~0.25 MiB and ~0.5 MiB, after which each heap keeps up to
    0.5 MiB it has freed: 0.5 MiB of a 16 MiB daemon with 100 services (measured alone in a
    namespace; docs/fleet-behaviour.md). A fixed threshold turns the adjustment off. The
    tunables are read when the process starts, hence the exec (same pid, same argv; ~36 ms);
    a user's own GLIBC_TUNABLES or MALLOC_* settings are left alone, as is a C library that
    is not glibc.
    """
    if os.environ.get("GLIBC_TUNABLES") or any(k.startswith("MALLOC_") for k in os.environ):
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
