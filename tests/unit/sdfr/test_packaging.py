"""What `pip install sdfr-robots` gets: the metadata (one version source), py.typed, the
robot configuration and the systemd unit as package data; the unit passes systemd's own
checker and the configuration sdfrd's."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from email.parser import Parser
from pathlib import Path

import pytest

import sdfr
from sdfr.cli import EXAMPLES, example_text
from sdfr.config.load import load_toml

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> zipfile.ZipFile:
    out = tmp_path_factory.mktemp("wheel")
    res = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
         "-w", str(out), str(ROOT)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    [path] = out.glob("*.whl")
    return zipfile.ZipFile(path)


def test_the_wheel_has_its_name_version_license_and_data(wheel: zipfile.ZipFile) -> None:
    names = set(wheel.namelist())
    meta_name = next(n for n in names if n.endswith(".dist-info/METADATA"))
    meta = Parser().parsestr(wheel.read(meta_name).decode())
    assert meta["Name"] == "sdfr-robots" == sdfr.DIST_NAME
    assert meta["Version"] == sdfr.__version__  # the one version source
    assert meta["Requires-Python"] == ">=3.10"
    assert "Programming Language :: Python :: 3.10" in meta.get_all("Classifier")
    assert "Typing :: Typed" in meta.get_all("Classifier")
    assert any(u.startswith("Homepage, https://") for u in meta.get_all("Project-URL"))
    assert any("tomli" in r and "python_version < " in r for r in meta.get_all("Requires-Dist"))
    assert any(n.endswith(".dist-info/licenses/LICENSE") or n.endswith("/LICENSE") for n in names)
    for data in ("sdfr/py.typed", "sdfr/deploy/robot.toml", "sdfr/deploy/sdfrd.service"):
        assert data in names
    entry = wheel.read(next(n for n in names if n.endswith("entry_points.txt"))).decode()
    for command in ("sdfrd = sdfr.daemon:main", "sdfr = sdfr.cli:main", "netlab ="):
        assert command in entry


def test_the_example_configuration_is_valid(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(example_text("robot.toml"))
    values = load_toml(path)
    assert values["addressing"] == "auto" and values["state_dir"] == Path("/var/lib/sdfr")
    assert (ROOT / "examples" / "robot.toml").read_text() == path.read_text()
    assert set(EXAMPLES) == {p.name for p in (ROOT / "sdfr" / "deploy").iterdir()}


def test_the_unit_passes_systemd_analyze(tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed (Debian: systemd)")
    unit = tmp_path / "sdfrd.service"
    text = example_text("sdfrd.service")
    for needed in ("Type=notify", "WatchdogSec=", "StateDirectory=sdfr", "ProtectSystem=strict"):
        assert needed in text
    # verify checks that ExecStart exists: point it at this sdfrd.
    sdfrd = Path(sys.executable).with_name("sdfrd")
    unit.write_text(text.replace("/usr/local/bin/sdfrd", str(sdfrd)))
    res = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True)
    assert res.returncode == 0 and not res.stderr.strip(), res.stderr
    res = subprocess.run(
        [analyze, "security", "--offline=yes", "--threshold=30", str(unit)],
        capture_output=True, text=True,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout[-2000:]  # (exposure 2.5 of 10, "OK")
