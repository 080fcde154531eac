"""Which sdfr was measured, and the same bench run against another sdfr (a git revision or a
checkout) in a child process, its figures side by side with this run's."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import sdfr
from bench.auth.fixtures import ROOT

#: The files whose behaviour this bench measures (the others do not take part in it).
TRUST_CORE = (
    "sdfr/protocol/",
    "sdfr/wire/",
    "sdfr/records/model.py",
)


def core_identity() -> dict[str, Any]:
    """Which sdfr was measured: its files, the git revision of the tree they are in, and
    whether the trust core's files differ from it."""
    package = Path(sdfr.__file__).resolve().parent
    out: dict[str, Any] = {"sdfr": str(package / "__init__.py")}
    stamp = package.parent / ".bench-revision"
    if stamp.exists():
        out["git"] = stamp.read_text().strip()
        out["modified"] = out["trust_core_modified"] = []
        return out

    def git(*args: str) -> str:
        res = subprocess.run(
            ["git", "-C", str(package.parent), *args], capture_output=True, text=True
        )
        return res.stdout.rstrip() if res.returncode == 0 else ""

    out["git"] = git("describe", "--always", "--tags") or "unknown"
    out["modified"] = [
        line[3:] for line in git("status", "--porcelain", "--", "sdfr").splitlines() if line
    ]
    out["trust_core_modified"] = [m for m in out["modified"] if m.startswith(TRUST_CORE)]
    return out


#: Run in the child: import sdfr from the baseline's tree before anything else, then the
#: bench and the simulator (`sdfr.testing`) from this checkout; the rest of sdfr stays the
#: baseline's, already imported.
_LAUNCH = """
import importlib.util, runpy, sys
core, root = sys.argv[1], sys.argv[2]
sys.path[:] = [p for p in sys.path if p not in ("", ".", root)]
sys.path.insert(0, core)
import sdfr
assert sdfr.__file__.startswith(core), sdfr.__file__
testing = root + "/sdfr/testing"
spec = importlib.util.spec_from_file_location(
    "sdfr.testing", testing + "/__init__.py", submodule_search_locations=[testing]
)
sdfr.testing = sys.modules["sdfr.testing"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(sdfr.testing)
sys.path[0] = root
sys.argv = ["bench.auth", *sys.argv[3:]]
runpy.run_module("bench.auth", run_name="__main__", alter_sys=True)
"""


def baseline_tree(spec: str, tmp: Path) -> Path:
    """A directory holding the baseline's sdfr package: `spec` itself when it is one (a
    checkout, a worktree), else the revision `spec` of this repository extracted there."""
    path = Path(spec)
    if (path / "sdfr" / "__init__.py").exists():
        return path.resolve()
    rev = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--verify", f"{spec}^{{commit}}"],
        capture_output=True,
        text=True,
    )
    if rev.returncode != 0:
        raise SystemExit(f"bench: --baseline {spec}: neither a checkout nor a revision")
    tmp.mkdir(parents=True, exist_ok=True)
    archive = tmp / "sdfr.tar"
    with archive.open("wb") as f:
        subprocess.run(
            ["git", "-C", str(ROOT), "archive", "--format=tar", rev.stdout.strip(), "sdfr"],
            stdout=f,
            check=True,
        )
    with tarfile.open(archive) as tar:
        tar.extractall(tmp, filter="data")
    described = subprocess.run(
        ["git", "-C", str(ROOT), "describe", "--always", "--tags", rev.stdout.strip()],
        capture_output=True,
        text=True,
    ).stdout.strip()
    (tmp / ".bench-revision").write_text(described + "\n")
    return tmp


def run_baseline(spec: str, argv: list[str]) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="bench-auth-baseline-") as d:
        tmp = Path(d)
        tree = baseline_tree(spec, tmp / "tree")
        out = tmp / "baseline.json"
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        cmd = [sys.executable, "-c", _LAUNCH, str(tree), str(ROOT), *argv, "--out", str(out)]
        res = subprocess.run(cmd, env=env, cwd=tmp, stdout=subprocess.DEVNULL)
        if res.returncode != 0:
            raise SystemExit(f"bench: the baseline run failed (status {res.returncode})")
        result: dict[str, Any] = json.loads(out.read_text())
        return result


def run_with_core(spec: str, argv: list[str]) -> int:
    """This bench, run in a child process against the sdfr of `spec` (see `baseline_tree`)."""
    with tempfile.TemporaryDirectory(prefix="bench-auth-core-") as d:
        tree = baseline_tree(spec, Path(d) / "tree")
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        cmd = [sys.executable, "-c", _LAUNCH, str(tree), str(ROOT), *argv]
        return subprocess.run(cmd, env=env, cwd=d).returncode


def leaves(obj: object, path: str = "") -> Iterator[tuple[str, float | None]]:
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from leaves(v, f"{path}.{k}" if path else str(k))
    elif isinstance(obj, bool):
        return
    elif isinstance(obj, (int, float)) or obj is None:
        yield path, obj


SKIP = ("baseline", "side_by_side", "core", "started", "wall_s")


def side_by_side(old: dict[str, Any], new: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Every number of both runs, by its path in the JSON: baseline, this one, and the change."""
    olds = dict(leaves({k: v for k, v in old.items() if k not in SKIP}))
    news = dict(leaves({k: v for k, v in new.items() if k not in SKIP}))
    out: dict[str, dict[str, Any]] = {}
    for path in list(dict.fromkeys([*olds, *news])):
        a, b = olds.get(path), news.get(path)
        row: dict[str, Any] = {"old": a, "new": b}
        if isinstance(a, (int, float)) and isinstance(b, (int, float)):
            row["change"] = round(b - a, 3)
            if a:
                row["change_pct"] = round(100 * (b / a - 1), 1)
        out[path] = row
    return out
