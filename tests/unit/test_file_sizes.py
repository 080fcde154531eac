"""Files of one job each: no source file of the package or the benches over 600 lines (a
file that grows past it holds several jobs; split it along them, see docs/architecture.md)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
LIMIT = 600


def test_no_source_file_is_over_600_lines() -> None:
    sizes = {
        path.relative_to(ROOT): len(path.read_text().splitlines())
        for folder in ("sdfr", "netlab", "bench")
        for path in (ROOT / folder).rglob("*.py")
    }
    assert len(sizes) > 100  # the walk found the tree
    over = {str(path): n for path, n in sorted(sizes.items()) if n > LIMIT}
    assert not over, f"over {LIMIT} lines: {over}"
