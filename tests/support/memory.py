"""Memory a piece of code kept, by tracemalloc, counted in its own files only."""

from __future__ import annotations

import tracemalloc
from collections.abc import Iterable


def grown(before: tracemalloc.Snapshot, after: tracemalloc.Snapshot, files: Iterable[str]) -> int:
    """Bytes more held from `before` to `after` by allocations made in `files`.

    Comparing every file's traces also counts whatever else the test process allocated
    meanwhile (pytest, a library's thread): a CI run once failed a bounded table by that.
    """
    ours = [tracemalloc.Filter(True, f) for f in files]
    diff = after.filter_traces(ours).compare_to(before.filter_traces(ours), "filename")
    return sum(s.size_diff for s in diff)
