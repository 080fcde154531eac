"""No import circle in `sdfr` or `netlab`: the modules' imports, read from the source (no
module is imported), form no cycle, except the ones listed in `KNOWN`, which may only go.

An edge is any ``import`` or ``from ... import`` of a module of the two packages, wherever it
stands: at module level, in a function (a late import hides a circle, it does not remove it)
and under ``if TYPE_CHECKING:`` (two modules whose types need each other are one design cut in
two, even if Python never runs those lines).  ``from package import name`` is an edge to the
module ``package.name`` when there is one, else to ``package``.  Importing ``a.b.c`` also
runs the packages ``a`` and ``a.b`` first; that is not an edge here, or every package whose
``__init__`` re-exports its modules would be a circle with each of them.

A circle is reported as the modules that reach each other (a strongly connected component),
with one path around it.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator, Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("sdfr", "netlab")

#: Circles known today, each with who is removing it.  The test fails on a circle not listed
#: here and on a listed one that is gone (or changed): delete its line when you break it.
KNOWN: dict[frozenset[str], str] = {}


def modules() -> dict[str, Path]:
    """Module name -> its file, for every module of the packages."""
    out: dict[str, Path] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def imported(name: str, path: Path, known: Mapping[str, Path]) -> Iterator[str]:
    """The modules of `known` that module `name` (at `path`) imports, anywhere in it."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in known:
                    yield alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                source = ".".join([*base, *([node.module] if node.module else [])])
            else:
                source = node.module or ""
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                if sub in known:
                    yield sub
                elif source in known:
                    yield source


def graph() -> dict[str, set[str]]:
    known = modules()
    return {
        name: {m for m in imported(name, path, known) if m != name} for name, path in known.items()
    }


def circles(edges: Mapping[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components of more than one module (Tarjan, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[frozenset[str]] = []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                members = set()
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    members.add(top)
                    if top == node:
                        break
                if len(members) > 1:
                    found.append(frozenset(members))
    return found


def path_around(edges: Mapping[str, set[str]], members: frozenset[str]) -> list[str]:
    """One cycle through the component, from its first module back to it."""
    start = min(members)
    seen = {start}
    trail = [(start, [start])]
    while trail:
        node, path = trail.pop(0)
        for nxt in sorted(edges[node] & members):
            if nxt == start:
                return [*path, start]
            if nxt not in seen:
                seen.add(nxt)
                trail.append((nxt, [*path, nxt]))
    raise AssertionError(f"no cycle through {start}")  # a component always has one


def describe(edges: Mapping[str, set[str]], members: frozenset[str]) -> str:
    return f"{', '.join(sorted(members))}\n    e.g. {' -> '.join(path_around(edges, members))}"


def test_the_walk_reads_imports_of_every_form() -> None:
    edges = graph()
    # A plain import, a from-import of a module, and one under TYPE_CHECKING.
    assert "netlab.scenario.spec" in edges["netlab.scenario.steps"]
    assert "netlab.scenario.engine" in edges["netlab.scenario"]
    assert "sdfr.errors" in edges["netlab.scenario.engine"]


def test_relative_imports_are_edges_to_the_modules_they_name(tmp_path: Path) -> None:
    known = dict.fromkeys(("p", "p.a", "p.b", "p.sub", "p.sub.c"), tmp_path)
    init = tmp_path / "__init__.py"
    init.write_text("from . import a, name\n")
    assert list(imported("p", init, known)) == ["p.a", "p"]
    module = tmp_path / "c.py"
    module.write_text("from . import c\nfrom .. import a\nfrom ..b import x\nimport os\n")
    assert list(imported("p.sub.c", module, known)) == ["p.sub.c", "p.a", "p.b"]


def test_the_cycle_finder_finds_each_circle_once() -> None:
    edges = {"a": {"b"}, "b": {"a", "c"}, "c": {"d"}, "d": {"c"}, "e": {"a"}}
    assert sorted(map(sorted, circles(edges))) == [["a", "b"], ["c", "d"]]
    assert path_around(edges, frozenset({"a", "b"})) == ["a", "b", "a"]


def test_no_import_circle_in_sdfr_or_netlab() -> None:
    edges = graph()
    found = set(circles(edges))
    new = [describe(edges, c) for c in found if c not in KNOWN]
    gone = [f"{', '.join(sorted(c))} ({who})" for c, who in KNOWN.items() if c not in found]
    problems = []
    if new:
        problems.append("import circles:\n  " + "\n  ".join(sorted(new)))
    if gone:
        problems.append(
            "listed in KNOWN but no longer a circle (or a different one now): remove or "
            "update its line:\n  " + "\n  ".join(sorted(gone))
        )
    assert not problems, "\n".join(problems)
