"""Robot kinds, without Docker: what a container robot's daemon is given."""

from __future__ import annotations

import os
from ipaddress import IPv4Interface
from pathlib import Path

import pytest

from netlab import docker, robots
from netlab.errors import NetlabError
from netlab.lab import Lab
from netlab.robots import ContainerKind, Robot, daemon_container, kind_for
from sdfr.config.load import option_flags
from sdfr.daemon import MALLOC_TUNABLES


def robot(tmp_path: Path, runtime: str = "docker") -> Robot:
    return Robot(
        "r1", 0, "nl-lab-r1", "vr1", "02:00:00:00:00:01", IPv4Interface("10.1.0.1/16"),
        tmp_path / "r1", runtime,
    )  # fmt: skip


def test_flags_are_sdfrd_options_by_name_without_the_unset_ones() -> None:
    assert option_flags({"beacon_interval": 0.5, "robot_id": "r1", "key_file": None}) == [
        "--beacon-interval", "0.5", "--robot-id", "r1",
    ]  # fmt: skip


def test_a_container_robot_has_two_containers_named_after_its_namespace(tmp_path: Path) -> None:
    assert robot(tmp_path).containers == ("nl-lab-r1", "nl-lab-r1.sdfrd")
    assert robot(tmp_path, "namespace").containers == ()
    # '.' is in no robot name: a daemon container is never another robot's container.
    assert daemon_container("nl-lab-r1-sdfrd") != daemon_container("nl-lab-r1")


def test_the_daemon_container_gets_the_state_volume_and_the_files_its_options_name(
    tmp_path: Path,
) -> None:
    key = tmp_path / "fleet.key"
    key.write_text("k")
    kind = ContainerKind("img:1")
    r = robot(tmp_path)
    opts = {"state_dir": r.state_dir, "key_file": str(key), "iface": "eth0", "config": "/nope"}
    inside = kind.container_options(r, opts)
    assert inside["state_dir"] == "/var/lib/sdfr" and inside["key_file"] == str(key)
    # An existing absolute path is mounted read-only where it is; others are left alone.
    assert kind.host_paths(opts) == {str(key): (str(key), True)}


def test_docker_run_arguments() -> None:
    spec = docker.ContainerSpec(
        name="nl-lab-r1.sdfrd",
        image="img:1",
        labels=docker.labels("lab", "r1", "sdfrd"),
        network="container:nl-lab-r1",
        argv=["--beacon-interval", "1"],
        env={"SDFR_ROBOT_ID": "r1"},
        mounts={"/w/r1/state": ("/var/lib/sdfr", False), "/k": ("/k", True)},
        cap_add=["NET_ADMIN"],
    )
    assert spec.run_args() == [
        "-d", "--name", "nl-lab-r1.sdfrd", "--init", "--network", "container:nl-lab-r1",
        "--label", "netlab.lab=lab", "--label", "netlab.robot=r1", "--label", "netlab.role=sdfrd",
        "--cap-add", "NET_ADMIN", "--env", "SDFR_ROBOT_ID=r1",
        "--volume", "/k:/k:ro", "--volume", "/w/r1/state:/var/lib/sdfr",
        "img:1", "--beacon-interval", "1",
    ]  # fmt: skip


def test_unknown_runtimes_are_refused_naming_the_known_ones() -> None:
    with pytest.raises(NetlabError, match="runtime: one of namespace, docker, got 'vm'"):
        Lab("x", runtime="vm")
    with pytest.raises(ValueError, match="one of namespace, docker"):
        kind_for("vm")


def test_sdfrd_starts_with_its_malloc_tunables_unless_the_user_set_their_own(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """netlab sets what sdfrd's pin_malloc would (one exec fewer per robot), and leaves a
    user's own malloc settings to sdfrd, which leaves them alone too."""
    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    for key in [k for k in os.environ if k.startswith("MALLOC_")]:
        monkeypatch.delenv(key)
    env = robots.daemon_env()
    assert env is not None and env["GLIBC_TUNABLES"] == MALLOC_TUNABLES
    assert env["PATH"] == os.environ["PATH"]
    monkeypatch.setenv("MALLOC_ARENA_MAX", "2")
    assert robots.daemon_env() is None
    monkeypatch.delenv("MALLOC_ARENA_MAX")
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.arena_max=2")
    assert robots.daemon_env() is None
