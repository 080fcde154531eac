"""Fixtures of the API tests: a configuration on a temporary state dir, the store's two
connections (the API layer's, and the discovery layer's as its own process has it), and the
API layer as a real process."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from sdfr.config.load import Config
from sdfr.store import Store
from tests.support.api import ApiLayer


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


@pytest.fixture
def layer(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiLayer]:
    """The API layer as a process (no discovery layer), on a state dir of its own."""
    # A short path: a unix socket's path is limited to 107 bytes.
    api = ApiLayer(tmp_path_factory.mktemp("api"))
    api.start()
    try:
        yield api
    finally:
        api.stop()
