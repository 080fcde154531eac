"""A compose fleet of robot containers: they find each other and each other's services, keep
their registrations through a restart and a re-created container, and `compose down`
leaves no container, network or volume behind."""

from __future__ import annotations

import json
import os
import subprocess

import pytest

from tests.docker.conftest import run
from tests.support.waiting import poll

pytestmark = pytest.mark.root
ROBOTS = 3


def compose_run(project: str, *args: str) -> subprocess.CompletedProcess[str]:
    """scripts/compose.sh ARGS for the compose project `project`."""
    return run("env", f"SDFR_COMPOSE_PROJECT={project}", "bash", "scripts/compose.sh", *args)


def compose(project: str, *args: str) -> str:
    res = compose_run(project, *args)
    assert res.returncode == 0, res.stdout + res.stderr
    return res.stdout


def sdfr(project: str, index: int, *args: str) -> dict[str, object]:
    out = compose(project, "exec", "-T", "--index", str(index), "robot", "sdfr", "--json", *args)
    obj = json.loads(out)
    assert isinstance(obj, dict)
    return obj


def containers(project: str) -> list[str]:
    label = f"label=com.docker.compose.project={project}"
    return run("docker", "ps", "-aq", "--filter", label).stdout.split()


def volumes_of(project: str) -> list[str]:
    """The volumes the project's containers use (their state dirs: anonymous volumes)."""
    ids = containers(project)
    if not ids:
        return []
    fmt = '{{range .Mounts}}{{if eq .Type "volume"}}{{.Name}} {{end}}{{end}}'
    return run("docker", "inspect", "-f", fmt, *ids).stdout.split()


def leftovers(project: str) -> list[str]:
    label = f"label=com.docker.compose.project={project}"
    found = []
    for kind in ("container ls -a", "network ls", "volume ls"):
        res = run("docker", *kind.split(), "-q", "--filter", label)
        found += [f"{kind.split()[0]} {line}" for line in res.stdout.split()]
    return found


def test_three_robots_in_compose_list_each_other_and_leave_nothing(image: str) -> None:
    project = f"sdfrtest{os.getpid()}"
    try:
        compose(project, "up", str(ROBOTS))
        ids: dict[int, str] = {}

        def all_answer() -> bool | str:
            for i in range(1, ROBOTS + 1):
                res = compose_run(
                    project, "exec", "-T", "--index", str(i), "robot", "sdfr", "--json", "self"
                )
                if res.returncode != 0:
                    return f"robot {i}: {res.stderr.strip()}"
                ids[i] = str(json.loads(res.stdout)["robot_id"])
            return True

        poll("every robot's sdfrd answers", all_answer, 30)
        assert len(set(ids.values())) == ROBOTS  # each its container's hostname

        def all_list_all() -> bool | str:
            for i, me in ids.items():
                seen = {n["robot_id"] for n in sdfr(project, i, "neighbors")["neighbors"]}  # type: ignore[index, union-attr]
                if seen != set(ids.values()) - {me}:
                    return f"{me} lists {sorted(seen)}"
            return True

        poll("all robots list each other", all_list_all, 30)
        compose(project, "exec", "-T", "--index", "1", "robot",
                "sdfr", "publish", "front camera", "sensor.camera")  # fmt: skip

        def camera_seen() -> bool | str:
            found = sdfr(project, 2, "search", "--type", "sensor.camera")["neighbors"]
            return [n["robot_id"] for n in found] == [ids[1]] or f"found {found}"  # type: ignore[union-attr, index]

        poll("the camera of robot 1 seen from robot 2", camera_seen, 5)

        # Registrations live in the state volume: a restart and a re-created container keep them.
        def own_services() -> bool | str:
            res = compose_run(
                project, "exec", "-T", "--index", "1", "robot", "sdfr", "--json", "services"
            )
            if res.returncode != 0:
                return res.stderr.strip()
            names = [s["name"] for s in json.loads(res.stdout)["services"]]
            return names == ["front camera"] or f"robot 1 has {names}"

        number_1 = run(
            "docker", "ps", "-aq", "--filter", "label=com.docker.compose.container-number=1"
        )
        first = [c for c in containers(project) if c in number_1.stdout.split()]
        assert len(first) == 1, first
        assert run("docker", "restart", first[0]).returncode == 0
        poll("robot 1's service after docker restart", own_services, 30)
        compose(project, "recreate", str(ROBOTS))
        poll("robot 1's service in its re-created container", own_services, 30)
    finally:
        volumes = volumes_of(project)
        compose(project, "down")
    assert len(volumes) == ROBOTS  # each robot's state volume, kept through the re-creation
    left = [v for v in volumes if run("docker", "volume", "inspect", v).returncode == 0]
    assert leftovers(project) == [] and left == [], left
