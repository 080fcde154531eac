"""Nothing the project ships or benchmarks with depends on its tests.

The package (`sdfr/`, `netlab/`) and the benchmarks (`bench/`) neither import `tests` nor run
a module of it (``python -m tests....``): what they share with the tests lives in the package
(`sdfr.testing`). Read statically (ast), so a lazy import inside a function counts too.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CHECKED = ("sdfr", "netlab", "bench")
#: A string naming a module of the tests, as `python -m` takes it.
TEST_MODULE = re.compile(r"tests(\.\w+)+")


def uses_of_tests(source: str) -> Iterator[tuple[int, str]]:
    """(line, what) for each import of `tests` (or a module under it) and each string that
    names a module under `tests` (`python -m tests.x`, `importlib.import_module("tests.x")`)."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "tests":
                    yield node.lineno, f"import {alias.name}"
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0 and node.module and node.module.split(".")[0] == "tests":
                yield node.lineno, f"from {node.module} import ..."
        elif (
            isinstance(node, ast.Constant)
            and isinstance(node.value, str)
            and TEST_MODULE.fullmatch(node.value)
        ):
            yield node.lineno, repr(node.value)


def sources() -> list[Path]:
    return sorted(p for d in CHECKED for p in (ROOT / d).rglob("*.py"))


def test_the_checked_trees_hold_code() -> None:
    assert len(sources()) > 50


@pytest.mark.parametrize(
    "source",
    [
        "import tests",
        "import tests.support.simnet as s",
        "from tests.ros import harness",
        "def f():\n    from tests.support.simnet import SimNet",
        "importlib.import_module('tests.support.fakes')",
        "argv = [sys.executable, '-m', 'tests.support.outsider', 'flood']",
    ],
)
def test_a_use_of_tests_is_found(source: str) -> None:
    assert list(uses_of_tests(source))


@pytest.mark.parametrize(
    "source",
    [
        "import testsuite",
        "from sdfr.testing.simnet import SimNet",
        "from . import tests",
        "doc = 'the tests pass'",
        "path = 'tests/ros/probe_ros2.py'",
    ],
)
def test_other_code_is_not_taken_for_a_use_of_tests(source: str) -> None:
    assert not list(uses_of_tests(source))


def test_no_shipped_or_bench_code_uses_the_tests() -> None:
    found = [
        f"{path.relative_to(ROOT)}:{line}: {what}"
        for path in sources()
        for line, what in uses_of_tests(path.read_text())
    ]
    assert not found, "code outside tests/ that depends on them:\n" + "\n".join(found)
