"""The local API and its OpenAPI document agree: schemathesis, with every check, against a
live sdfrd (both layers up, in a netlab robot), fails on any disagreement."""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from netlab.lab import Lab

pytestmark = pytest.mark.root

CONFIG = Path(__file__).resolve().parents[1] / "support" / "schemathesis.toml"
SCHEMATHESIS = Path(sys.executable).with_name("schemathesis")
API = "http://127.0.0.1:8700"


def schemathesis(lab: Lab, cwd: Path, schema: str, *extra: str) -> tuple[int, str]:
    """Run schemathesis inside robot r1 (where its API listens); exit status and output."""
    argv = [
        str(SCHEMATHESIS), "--no-color", "--config-file", str(CONFIG), "run", schema,
        "--max-examples", "25", "--seed", "1", "--generation-database", "none", *extra,
    ]  # fmt: skip
    res = lab.exec("r1", argv, cwd=cwd, timeout=600)
    return res.returncode, res.stdout + res.stderr


def _document(lab: Lab) -> str:
    """The OpenAPI document r1's sdfrd serves."""
    res = lab.exec("r1", [sys.executable, "-c", (
        "import sys, urllib.request; "
        f"sys.stdout.write(urllib.request.urlopen('{API}/openapi.json').read().decode())"
    )])  # fmt: skip
    assert res.returncode == 0, res.stderr
    return res.stdout


@pytest.fixture
def robot(fleet_factory: Callable[..., Lab]) -> Lab:
    if not SCHEMATHESIS.exists():
        pytest.fail(f"{SCHEMATHESIS} is missing: `make test` installs the dev extra")
    return fleet_factory(1, beacon=1.0)


def test_the_api_keeps_to_its_openapi_document(robot: Lab, tmp_path: Path) -> None:
    status, out = schemathesis(robot, tmp_path, f"{API}/openapi.json")
    assert status == 0, out[-6000:]
    operations = sum(len(ops) for ops in json.loads(_document(robot))["paths"].values())
    selected = re.search(r"Selected: (\d+)/(\d+)", out)
    tested = re.search(r"Tested: (\d+)", out)
    assert selected and tested, out[-2000:]
    # Every operation but the document's own URL, which schemathesis does not test.
    assert int(tested[1]) == int(selected[1]) == int(selected[2]) == operations - 1, out[-2000:]


def test_a_document_that_drifted_from_the_code_fails(robot: Lab, tmp_path: Path) -> None:
    """The check can fail: the same daemon against its document with one old drift put back
    (`?all=` was answered though the enum left the bare flag out)."""
    doc = json.loads(_document(robot))
    (param,) = doc["paths"]["/neighbors"]["get"]["parameters"]
    param["schema"]["enum"].remove("")
    del param["allowEmptyValue"]
    drifted = tmp_path / "drifted.json"
    drifted.write_text(json.dumps(doc))
    status, out = schemathesis(robot, tmp_path, str(drifted), "--url", API)
    assert status != 0, out[-3000:]
    assert "/neighbors" in out and "all=" in out, out[-3000:]
