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
"""

from __future__ import annotations

import sys

#: Modules sdfrd's processes never load (see the module docstring).
NOT_LOADED = ("ssl", "_ssl", "_hashlib", "typing_extensions")


def allow_openssl() -> None:
    """Let a library that needs OpenSSL load it after all: pyroute2 (imported by the discovery
    layer only with `--addressing auto`) imports ssl. Only that process pays for it."""
    for name in NOT_LOADED:
        if name in sys.modules and sys.modules[name] is None:
            del sys.modules[name]


def main(argv: list[str] | None = None) -> int:
    """sdfrd."""
    for name in NOT_LOADED:
        if name not in sys.modules:
            sys.modules[name] = None  # type: ignore[assignment]
    from sdfr.daemon import supervisor

    return supervisor.main(argv)
