"""Every test a document names as the proof of a claim exists.

The README, CONTRIBUTING.md and every page of docs/ name their proofs as
``test_file.py::test_name`` (or a whole ``test_file.py``); a renamed or deleted test would leave a
claim with nothing behind it.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", *sorted((ROOT / "docs").glob("*.md"))]
#: `test_x.py::test_y` or `test_x.py`, in backquotes, optionally with a folder.
REF = re.compile(r"`((?:[\w./-]*/)?(test_\w+\.py))(?:::(\w+))?`")


def _tests() -> dict[str, list[Path]]:
    found: dict[str, list[Path]] = {}
    for path in (ROOT / "tests").rglob("test_*.py"):
        found.setdefault(path.name, []).append(path)
    return found


def _names(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    return {
        node.name
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)
    }


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_test_a_document_names_exists(doc: Path) -> None:
    files = _tests()
    missing = []
    refs = REF.findall(doc.read_text())
    for full, name, function in refs:
        paths = [p for p in files.get(name, []) if str(p).endswith(full)]
        if not paths:
            missing.append(full)
        elif function and not any(function in _names(p) for p in paths):
            missing.append(f"{full}::{function}")
    assert not missing, f"{doc.name} names tests that do not exist: {missing}"
    if doc.name == "security.md":
        assert len(refs) >= 30  # (the claims are there to be checked)


def test_the_documents_are_found() -> None:
    names = {d.name for d in DOCS}
    assert {"README.md", "CONTRIBUTING.md", "security.md", "api.md", "scenarios.md"} <= names
