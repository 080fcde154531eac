"""The README's first hour, followed literally in a fresh clone.

The README marks the shell blocks a newcomer types first with ``<!-- first-hour -->`` (the
set-up, putting the commands on PATH, the netlab tour). This test clones the repository at HEAD
into a temporary folder and runs those blocks there, in order, in one clean shell (``env -i``
with a plain PATH and HOME; no virtualenv), and every command must exit 0. ``make test`` is not
among them: this test is part of it. One change: the README's lab name ``lab1`` becomes one of
this run's own (``fh`` and a number), so that a lab someone else named ``lab1`` on this host
cannot make the test fail, nor the test take that lab down.

It takes a few minutes (``make netlab`` creates the clone's own ``.venv``, then runs its three
scenarios) and needs root, like the rest of tests/ns.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MARK = "<!-- first-hour -->"
CLEAN_PATH = "/usr/sbin:/usr/bin:/sbin:/bin"
README_LAB = "lab1"


def own_lab(commands: list[str], name: str) -> list[str]:
    """`commands` with the README's lab name replaced by `name` (a word, not a part of one)."""
    return [re.sub(rf"\b{README_LAB}\b", name, c) for c in commands]


def first_hour_commands(readme: str) -> list[str]:
    """The commands of the shell blocks right after each MARK, in order, one a line (a line
    ending in a backslash is joined with the next)."""
    commands: list[str] = []
    lines = readme.splitlines()
    for i, line in enumerate(lines):
        if line.strip() != MARK:
            continue
        rest = list(lines[i + 1 :])
        while rest and not rest[0].strip():
            rest.pop(0)
        if not rest or rest[0].strip() not in ("```sh", "```bash", "```shell"):
            raise ValueError(f"README line {i + 1}: {MARK} is not followed by a ```sh block")
        end = next((k for k, x in enumerate(rest[1:], 1) if x.strip() == "```"), None)
        if end is None:
            raise ValueError(f"README line {i + 1}: the marked block never ends")
        pending = ""
        for raw in rest[1:end]:
            text = pending + raw
            if text.rstrip().endswith("\\"):
                pending = text.rstrip()[:-1] + " "
                continue
            pending = ""
            if text.strip() and not text.lstrip().startswith("#"):
                commands.append(text.strip())
    return commands


def shell_script(commands: list[str]) -> str:
    """One bash script running `commands` in order in one shell (so `source` carries over),
    saying each before it runs and stopping at the first that does not exit 0."""
    out = []
    for cmd in commands:
        quoted = shlex.quote(cmd)
        out.append(f"echo {shlex.quote('first-hour$ ')}{quoted}")
        out.append(cmd)
        out.append(
            f'rc=$?; if [ "$rc" -ne 0 ]; then echo "first-hour: exit status $rc from: "{quoted}'
            " >&2; exit 1; fi"
        )
    return "\n".join(out) + "\necho first-hour: every command exited 0\n"


def test_the_marked_blocks_are_found_in_order_with_their_commands() -> None:
    readme = f"""# x
{MARK}
```sh
make netlab   # a comment
```

```sh
make test
```
{MARK}

```sh
# a comment line
source .venv/bin/activate
netlab up lab1 \\
    --robots 3
```
"""
    assert first_hour_commands(readme) == [
        "make netlab   # a comment",
        "source .venv/bin/activate",
        "netlab up lab1      --robots 3",
    ]
    with pytest.raises(ValueError, match="not followed by a ```sh block"):
        first_hour_commands(f"{MARK}\ntext\n")


def test_a_failing_command_stops_the_script_and_is_named(tmp_path: Path) -> None:
    script = shell_script(["true", "false  # the second", "touch never"])
    done = subprocess.run(
        ["bash", "-c", script], cwd=tmp_path, capture_output=True, text=True, check=False
    )
    assert done.returncode == 1
    assert "exit status 1 from: false  # the second" in done.stderr
    assert not (tmp_path / "never").exists()


def test_the_readme_starts_with_make_netlab_and_marks_the_tour() -> None:
    commands = first_hour_commands((ROOT / "README.md").read_text())
    assert commands[0].split("#")[0].strip() == "make netlab"
    assert "source .venv/bin/activate" in [c.split("#")[0].strip() for c in commands]
    assert any(c.startswith("netlab ") for c in commands)
    assert not any(re.match(r"make\s+test\b", c) for c in commands), "make test runs this test"
    ours = own_lab(commands, "fh42")
    tour = [c for c in commands if README_LAB in c]
    assert tour and not any(README_LAB in c for c in ours)
    assert own_lab(["netlab down lab1 --cleanup  # lab1x"], "fh42") == [
        "netlab down fh42 --cleanup  # lab1x"
    ]


@pytest.mark.root
def test_the_readme_first_hour_in_a_fresh_clone(tmp_path: Path) -> None:
    clone = tmp_path / "sdfr"
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
    commands = first_hour_commands((clone / "README.md").read_text())
    commands = own_lab(commands, f"fh{os.getpid() % 1000000}")
    env = {"PATH": CLEAN_PATH, "HOME": os.environ.get("HOME", "/root"), "LANG": "C.UTF-8"}
    argv = ["env", "-i", *(f"{k}={v}" for k, v in env.items())]
    argv += ["bash", "--noprofile", "--norc", "-c", shell_script(commands)]
    try:
        done = subprocess.run(
            argv, cwd=clone, capture_output=True, text=True, timeout=1800, check=False
        )
        stdout, stderr, status = done.stdout, done.stderr, done.returncode
    except subprocess.TimeoutExpired as exc:
        stdout, stderr, status = _text(exc.stdout), _text(exc.stderr) + "\n(timed out)", -1
    if status != 0:
        _down_labs_it_made(clone, stdout)
    for folder in re.findall(r"^folder (/tmp/[^\s,()]+)", stdout, flags=re.M):
        shutil.rmtree(folder, ignore_errors=True)  # a lab's folder, if a failure left it
    output = stdout + stderr
    assert status == 0, f"the README's first hour failed in {clone}:\n{output[-6000:]}"
    assert "every command exited 0" in stdout
    shutil.rmtree(clone, ignore_errors=True)


def _text(data: bytes | str | None) -> str:
    if isinstance(data, bytes):
        return data.decode(errors="replace")
    return data or ""


def _down_labs_it_made(clone: Path, stdout: str) -> None:
    """Take down the labs this run brought up (`netlab up` said so) and left up by failing."""
    netlab = clone / ".venv" / "bin" / "netlab"
    for lab in set(re.findall(r"^lab (\w+): \d+ robots", stdout, flags=re.M)):
        if netlab.exists():
            subprocess.run(
                [str(netlab), "down", lab, "--cleanup"],
                capture_output=True,
                timeout=120,
                check=False,
            )
