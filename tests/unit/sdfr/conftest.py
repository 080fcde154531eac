"""Fixtures of the API tests: a configuration on a temporary state dir, and the store's two
connections (the API layer's, and the discovery layer's as its own process has it)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from sdfr.config import Config
from sdfr.store import Store


@pytest.fixture(autouse=True)
def _own_state_home(
    tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`sdfr` and the ROS node keep the user's owner token under XDG_STATE_HOME: in a test,
    not in the home of whoever runs it."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("state-home")))


@pytest.fixture
def cfg(tmp_path: Path) -> Config:
    return Config(state_dir=tmp_path, robot_id="r1", iface="lo", fleet=7)


@pytest.fixture
def store(cfg: Config) -> Iterator[Store]:
    s = Store(cfg.state_dir)
    yield s
    s.close()


@pytest.fixture
def discovery_store(cfg: Config) -> Iterator[Store]:
    """A second connection, as the discovery layer's process has."""
    s = Store(cfg.state_dir)
    yield s
    s.close()
