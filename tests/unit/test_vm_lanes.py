"""`make test-vms` runs the VM tiers in two VMs (the Makefile's two lanes, each a
`scripts/vm.sh` run): every test of tests/netem and tests/radio runs in exactly one of them,
each VM loads the module its tests need, and a skipped tier's VM does not boot.
`SDFR_VM_PLAN=1` makes vm.sh say what its VM would run, without booting it."""

from __future__ import annotations

import functools
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LANES = ("test-netem", "test-radio")
MODULES = {"netem": "sch_netem", "radio": "mac80211_hwsim"}


def lane_commands() -> list[list[str]]:
    """The commands `make test-vms` runs, one per lane (make -n: nothing runs)."""
    out = subprocess.run(
        ["make", "-s", "-n", "--no-print-directory", *LANES],
        cwd=ROOT, capture_output=True, text=True, check=True,
    )  # fmt: skip
    lines = out.stdout.replace("\\\n", " ").splitlines()
    commands = [shlex.split(line) for line in lines if "scripts/vm.sh" in line]
    assert len(commands) == len(LANES), out.stdout
    return commands


def plan(command: list[str], **env: str) -> str:
    """What vm.sh says its VM would do (SDFR_VM_PLAN=1): its whole output."""
    keep = {k: v for k, v in os.environ.items() if not k.startswith("SDFR_SKIP_")}
    res = subprocess.run(
        command, cwd=ROOT, capture_output=True, text=True,
        env={**keep, "SDFR_VM_PLAN": "1", **env},
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    return res.stdout


def collected(pytest_args: list[str]) -> list[str]:
    """The test ids pytest collects from these arguments (as the VM's pytest would)."""
    return list(_collected(tuple(a for a in pytest_args if a not in ("-v", "-s"))))


@functools.cache
def _collected(args: tuple[str, ...]) -> tuple[str, ...]:
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", *args],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout + res.stderr
    return tuple(line for line in res.stdout.splitlines() if "::" in line)


def planned(output: str) -> tuple[str, list[str]]:
    """(the modprobe line, pytest's arguments) from a plan's last line."""
    line = output.strip().splitlines()[-1]
    assert "would boot with" in line, output
    modules = line.split("`")[1]
    return modules, shlex.split(line.split(" and run pytest ", 1)[1])


def test_the_two_vms_run_every_vm_test_once_with_the_modules_it_needs() -> None:
    every = collected([f"tests/{tier}" for tier in MODULES])
    assert len(every) > 10
    seen: list[str] = []
    for command in lane_commands():
        modules, args = planned(plan(command))
        tests = collected(args)
        assert tests, f"{command}: no test"
        for test in tests:
            tier = test.split("/")[1]
            assert MODULES[tier] in modules, f"{test} runs in a VM without {MODULES[tier]}"
        seen += tests
    assert sorted(seen) == sorted(every), "each VM test must run in exactly one VM"


@pytest.mark.parametrize("tier", sorted(MODULES))
def test_a_skipped_tier_drops_out_and_says_so(tier: str) -> None:
    var = f"SDFR_SKIP_{tier.upper()}"
    for command in lane_commands():
        out = plan(command, **{var: "1"})
        if "would boot with" not in out:
            continue  # a VM left with nothing to run does not boot
        modules, args = planned(out)
        assert MODULES[tier] not in modules
        assert all(t.split("/")[1] != tier for t in collected(args)), out
    said = [plan(c, **{var: "1"}) for c in lane_commands()]
    assert any(f"{var}=1" in s and "did not run" in s for s in said)


def test_an_unknown_tier_is_refused_with_the_ones_there_are() -> None:
    res = subprocess.run(
        ["bash", "scripts/vm.sh", "wifi"], cwd=ROOT, capture_output=True, text=True
    )
    assert res.returncode == 2 and "netem|radio" in res.stderr
    assert "got wifi" in res.stderr
