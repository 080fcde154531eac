"""docs/architecture.md names every part of the packages: each folder of `sdfr/` and
`netlab/` as `name/`, each top-level module as `name.py`, and each module of a folder by its
name in backticks (`name` or `folder/name.py`), in that package's section.
A file added without saying where it belongs fails here."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOC = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")


def named(package: str) -> set[str]:
    """What the package's section (from its `## package/` heading to the next) names."""
    section = DOC.split(f"\n## {package}/", 1)[1].split("\n## ", 1)[0]
    return set(re.findall(r"`([\w./]+)`", section))


def missing(package: str) -> list[str]:
    out: list[str] = []
    names = named(package)
    base = ROOT / package
    for path in sorted(base.rglob("*.py")):
        rel = path.relative_to(base)
        if "__pycache__" in rel.parts or path.name in ("__init__.py", "__main__.py"):
            continue
        if len(rel.parts) == 1:
            if path.name not in names:
                out.append(f"{package}/{rel}")
        elif rel.parts[0] + "/" not in names:
            out.append(f"{package}/{rel.parts[0]}/")
        elif path.stem not in names and f"{rel.parts[-2]}/{path.name}" not in names:
            out.append(f"{package}/{rel}")
    return sorted(set(out))


def test_every_part_of_sdfr_is_in_the_architecture_document() -> None:
    assert missing("sdfr") == []


def test_every_part_of_netlab_is_in_the_architecture_document() -> None:
    assert missing("netlab") == []
