"""The asyncio client's public name: `from sdfr.aio import AsyncClient` (it lives in
`sdfr.client.aio`; needs the `aio` extra)."""

from __future__ import annotations

from sdfr.client.aio import AsyncClient, AsyncKeptLease, Change

__all__ = ["AsyncClient", "AsyncKeptLease", "Change"]
