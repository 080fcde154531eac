"""scripts/vm_hot.py: the files a VM tier's Python processes read at start, which
scripts/vm.sh puts in the guest's memory (the guest reads the host's files over 9p)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def test_the_list_has_the_interpreter_libpython_and_the_daemons_and_tests_modules() -> None:
    out = subprocess.run(
        [sys.executable, "scripts/vm_hot.py", "tests/netem"],
        cwd=REPO, capture_output=True, text=True, check=True, timeout=120,
    )  # fmt: skip
    files = out.stdout.splitlines()
    assert files == sorted(set(files))
    assert all(os.path.isabs(f) and os.path.isfile(f) for f in files)
    listed = set(files)
    assert os.path.realpath(sys.executable) in listed
    assert any(Path(f).name.startswith("libc.so") for f in files)
    for module in ("sdfr/daemon/supervisor.py", "netlab/pcap.py", "tests/netem/test_netem.py"):
        source = str(REPO / module)
        assert source in listed, module
        assert importlib.util.cache_from_source(source) in listed, module


def test_a_module_that_cannot_be_imported_is_named_and_left_to_9p(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = importlib.util.spec_from_file_location("vm_hot", REPO / "scripts" / "vm_hot.py")
    assert spec is not None and spec.loader is not None
    vm_hot = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(vm_hot)
    (tmp_path / "brokentier").mkdir()
    (tmp_path / "brokentier" / "test_nothing_here.py").write_text("raise RuntimeError('no')\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    assert vm_hot.main(["brokentier"]) == 0
    out, err = capsys.readouterr()
    assert "brokentier.test_nothing_here not listed: RuntimeError('no')" in err
    assert os.path.realpath(sys.executable) in out.splitlines()
