"""The write API stays on the robot: an `api` address other than loopback is refused unless
explicitly allowed with a token, and then every request from off the robot carries it."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest
from aiohttp import ClientSession

from sdfr.api import Runner, TCPSite, create_app
from sdfr.config.load import Config, from_args
from sdfr.errors import ConfigError
from sdfr.store import Store
from tests.support.api import aio, free_port

TOKEN = "a-fleet-operators-api-token-0123456789"


@pytest.fixture
def token_file(tmp_path: Path) -> Path:
    path = tmp_path / "api-token"
    path.write_text(TOKEN + "\n")
    path.chmod(0o600)
    return path


@pytest.mark.parametrize("api", ["0.0.0.0:8700", "192.0.2.7:8700", "[::]:8700", "10.1.2.3:1"])
def test_a_non_loopback_api_is_refused_unless_allowed_and_tokened(
    api: str, token_file: Path
) -> None:
    with pytest.raises(ConfigError) as err:
        from_args(["--api", api])
    says = str(err.value)
    assert says.startswith("api: ") and "not a loopback address" in says
    assert "api_allow_remote" in says and "api_token_file" in says
    with pytest.raises(ConfigError, match="api_token_file"):
        from_args(["--api", api, "--api-allow-remote", "true"])
    with pytest.raises(ConfigError, match="api_allow_remote"):
        from_args(["--api", api, "--api-token-file", str(token_file)])
    cfg = from_args(
        ["--api", api, "--api-allow-remote", "true", "--api-token-file", str(token_file)]
    )
    assert cfg.api_allow_remote and cfg.api_token_file == token_file


@pytest.mark.parametrize("api", ["127.0.0.1:8700", "127.0.0.9:1", "[::1]:8700", "localhost:80"])
def test_loopback_needs_nothing(api: str) -> None:
    assert from_args(["--api", api]).api == api


def test_the_options_read_from_toml_and_flags(tmp_path: Path, token_file: Path) -> None:
    conf = tmp_path / "r.toml"
    conf.write_text(
        f'api = "0.0.0.0:8700"\napi_allow_remote = true\napi_token_file = "{token_file}"\n'
    )
    cfg = from_args(["--config", str(conf)])
    assert (cfg.api, cfg.api_allow_remote, cfg.api_token_file) == ("0.0.0.0:8700", True, token_file)
    with pytest.raises(ConfigError, match="api_allow_remote: expected true or false"):
        from_args(["--api-allow-remote", "maybe"])
    conf.write_text('api_allow_remote = "yes"\n')
    with pytest.raises(ConfigError, match="api_allow_remote: expected true or false"):
        from_args(["--config", str(conf)])


def test_sdfrd_s_api_layer_says_so_in_one_line(tmp_path: Path, token_file: Path) -> None:
    base = [sys.executable, "-m", "sdfr.daemon.apiserver", "--state-dir", str(tmp_path / "s")]
    base += ["--describe", f"127.0.0.1:{free_port()}", "--robot-id", "r1", "--iface", "lo"]
    for extra, says in (
        (["--api", f"0.0.0.0:{free_port()}"], "not a loopback address"),
        (
            ["--api", f"0.0.0.0:{free_port()}", "--api-allow-remote", "true",
             "--api-token-file", str(tmp_path / "none")],
            "api_token_file: ",
        ),
    ):  # fmt: skip
        try:
            done = subprocess.run([*base, *extra], capture_output=True, text=True, timeout=10)
        except subprocess.TimeoutExpired:
            pytest.fail(f"sdfrd's API layer started with {extra}")
        assert done.returncode == 2, done.stderr
        assert len(done.stderr.strip().splitlines()) == 1 and says in done.stderr, done.stderr


def test_a_token_file_that_cannot_serve_is_named(tmp_path: Path, store: Store) -> None:
    short = tmp_path / "short"
    short.write_text("abc\n")
    for path, says in ((short, "at least 16 characters"), (tmp_path / "none", "cannot read")):
        cfg = Config(
            state_dir=store.path.parent,
            api="0.0.0.0:8700",
            api_allow_remote=True,
            api_token_file=path,
        ).validate()
        with pytest.raises(ConfigError) as err:
            create_app(cfg, store)
        assert str(err.value).startswith("api_token_file: ") and str(path) in str(err.value)
        assert says in str(err.value)


def this_machines_address() -> str:
    """An address of this machine other than loopback (what a robot of the fleet would
    connect from, as far as the server can tell)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.1", 9))  # (no datagram is sent)
            address: str = probe.getsockname()[0]
        except OSError:
            address = "127.0.0.1"
    if address.startswith("127."):
        pytest.skip("this machine has no address but loopback")
    return address


@aio
async def test_requests_from_off_the_robot_carry_the_token(
    tmp_path: Path, store: Store, token_file: Path
) -> None:
    address = this_machines_address()
    port = free_port()
    cfg = Config(
        state_dir=store.path.parent,
        robot_id="r1",
        api=f"0.0.0.0:{port}",
        api_allow_remote=True,
        api_token_file=token_file,
    ).validate()
    runner = Runner(create_app(cfg, store))
    await runner.setup()
    await TCPSite(runner, "0.0.0.0", port).start()
    body = {"name": "cam", "type": "camera/rgb"}
    try:
        async with ClientSession(base_url=f"http://{address}:{port}") as remote:
            refused = (
                {},
                {"Authorization": "Bearer wrong-token-wrong-token"},
                {"Authorization": TOKEN},
                {"Authorization": f"Basic {TOKEN}"},
            )
            for headers in refused:
                for method, path in (("GET", "/neighbors"), ("POST", "/services")):
                    r = await remote.request(method, path, json=body, headers=headers)
                    answer = await r.json()
                    assert r.status == 401, (headers, r.status, answer)
                    assert r.headers["WWW-Authenticate"].startswith("Bearer")
                    assert answer["field"] == "Authorization"
                    assert "api_token_file" in answer["error"]
            assert store.local_state() == (0, [])
            bearer = {"Authorization": f"Bearer {TOKEN}"}
            assert (await remote.get("/neighbors", headers=bearer)).status == 200
            r = await remote.post("/services", json=body, headers=bearer)
            assert r.status == 201, await r.text()
        # Programs on the robot need no token.
        async with ClientSession(base_url=f"http://127.0.0.1:{port}") as local:
            assert (await local.get("/services")).status == 200
    finally:
        await runner.cleanup()
