"""The API layer as a real process, driven through `sdfr.client.Client` and the `sdfr` command."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from sdfr.cli import main as sdfr
from sdfr.cli import typed_value
from sdfr.client import Client
from sdfr.config import keystore
from sdfr.errors import ApiError
from sdfr.protocol import auth
from sdfr.protocol.auth import Keyring
from sdfr.records.model import PeerRecord, Service
from sdfr.store import Store
from tests.support.api import ApiLayer, free_port

REPO = Path(__file__).resolve().parents[3]


def save_fleet(state_dir: Path) -> None:
    """What the discovery layer would have found: two reachable robots, one out of reach."""
    now = time.time()

    def robot(rid: str, reachable: bool, *services: Service) -> PeerRecord:
        return PeerRecord(
            robot_id=rid,
            address=f"10.1.0.{len(rid)}",
            location=f"http://10.1.0.{len(rid)}:8701/description.json",
            boot_id=1,
            version=1,
            digest="0" * 16,
            reachable=reachable,
            first_seen=now - 100,
            last_seen=now - (1 if reachable else 80),
            indicator=0.95 if reachable else None,
            rtt_ms=2.5 if reachable else None,
            pings=10,
            services=services,
        )

    cam = Service("c1", "front camera", "camera/rgb", None, {"fps": 30, "frame-rate": 30})
    lidar = Service("l1", "lidar", "lidar", "udp://10.1.0.4:2368", {})
    store = Store(state_dir)
    try:
        store.save_peers(
            [
                robot("atlas", True, cam, lidar),
                robot("bee", True, Service("c2", "cam", "camera/rgb", None, {"fps": 15})),
                robot("gone", False, Service("c3", "old cam", "camera/rgb", None, {"fps": 30})),
            ]
        )
    finally:
        store.close()


def write_healthy_status(state_dir: Path, **extra: object) -> None:
    store = Store(state_dir)
    try:
        store.write_status({"pid": os.getpid(), "robot_id": "r1", "address": "10.1.9.9", **extra})
    finally:
        store.close()


# -- the Python client -------------------------------------------------------------------------


def test_registrations_survive_a_killed_api_layer(layer: ApiLayer) -> None:
    with Client(layer.api) as client:
        ids = [client.publish(f"s{i}", "thing", attributes={"i": i}) for i in range(3)]
        client.unpublish(ids[1])
        layer.kill()
        with pytest.raises(ApiError):
            client.services()
        assert layer.socket.exists()  # left behind by SIGKILL: the restart must replace it
        layer.start()
        # The same client reconnects; the state is the one before the kill.
        assert [s["id"] for s in client.services()] == [ids[0], ids[2]]
        assert client.self_info()["version"] == 4
    with Client(unix_socket=layer.socket) as unix:
        assert len(unix.services()) == 2
        # A keep-alive connection the server dropped meanwhile: retried once, transparently.
        layer.kill()
        layer.start()
        assert len(unix.services()) == 2


# -- the apiserver process ---------------------------------------------------------------------


def test_apiserver_stops_cleanly_on_sigterm(layer: ApiLayer) -> None:
    assert layer.proc is not None
    assert layer.socket.stat().st_mode & 0o777 == 0o660
    layer.proc.send_signal(signal.SIGTERM)
    assert layer.proc.wait(timeout=10) == 0
    assert not layer.socket.exists()
    assert "Traceback" not in layer.logs()


def test_apiserver_port_in_use_is_one_line(tmp_path: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        api = ApiLayer(tmp_path, api_port=busy.getsockname()[1])
        done = subprocess.run(api.argv(), capture_output=True, text=True, timeout=30)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert f"--api {api.api}" in lines[0] and "already in use" in lines[0]


def test_apiserver_bad_flag_value_is_one_line(tmp_path: Path) -> None:
    argv = [sys.executable, "-m", "sdfr.daemon.apiserver", "--state-dir", str(tmp_path)]
    done = subprocess.run([*argv, "--fleet", "300"], capture_output=True, text=True, timeout=30)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [done.stderr.strip()]
    assert "fleet" in done.stderr


# -- the sdfr command --------------------------------------------------------------------------


def test_cli_publish_services_and_unpublish(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["--api", layer.api, "publish", "front cam", "camera/rgb", "--url", "rtsp://cam"]
    argv += ["--attr", "fps=30", "--attr", "hdr=true", "--attr", "model=x-1", "--attr", "gain=0.5"]
    assert sdfr(argv) == 0
    sid = capsys.readouterr().out.strip()
    with Client(layer.api) as client:
        [published] = client.services()
    assert published["id"] == sid
    assert published["attributes"] == {"fps": 30, "hdr": True, "model": "x-1", "gain": 0.5}

    assert sdfr(["--socket", str(layer.socket), "services"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split() == ["ID", "NAME", "TYPE", "URL", "ATTRIBUTES", "LEASE"]
    assert out[1].startswith(sid) and "fps=30 hdr=true model=x-1 gain=0.5" in out[1]

    assert sdfr(["--api", layer.api, "services", "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer == {"services": [published], "version": 1}

    assert sdfr(["--api", layer.api, "--json", "publish", "arm", "manipulator"]) == 0
    created = json.loads(capsys.readouterr().out)
    assert set(created) == {"id", "service", "version", "ttl", "expires", "owner_token"}

    assert sdfr(["--api", layer.api, "unpublish", sid]) == 0
    assert capsys.readouterr().out == ""
    with Client(layer.api) as client:
        assert [s["id"] for s in client.services()] == [created["id"]]


def test_cli_neighbors_search_history_self(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    save_fleet(layer.state_dir)
    api = ["--api", layer.api]

    assert sdfr([*api, "neighbors"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split() == ["ROBOT", "ADDRESS", "REACHABLE", "INDICATOR", "RTT", "SERVICES"]
    assert table[1].split()[:6] == ["atlas", "10.1.0.5", "yes", "0.95", "2.5", "ms"]
    assert [line.split()[0] for line in table[1:]] == ["atlas", "bee"]
    # Columns are aligned: every row's ADDRESS starts where the header's does.
    col = table[0].index("ADDRESS")
    assert all(line[col - 2 : col] == "  " and line[col] != " " for line in table[1:])

    assert sdfr([*api, "neighbors", "--all"]) == 0
    rows = capsys.readouterr().out.splitlines()[1:]
    assert rows[2].split()[:3] == ["gone", "10.1.0.4", "no"]

    assert sdfr([*api, "neighbors", "--json"]) == 0
    assert [n["robot_id"] for n in json.loads(capsys.readouterr().out)["neighbors"]] == [
        "atlas",
        "bee",
    ]

    assert sdfr([*api, "search", "--type", "camera/rgb", "--attr", "fps=30"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert rows[0].split()[:4] == ["ROBOT", "ADDRESS", "ID", "NAME"]
    assert [r.split()[0] for r in rows[1:]] == ["atlas"]

    assert sdfr([*api, "--json", "search", "--attr", "frame-rate=30"]) == 0
    assert [n["robot_id"] for n in json.loads(capsys.readouterr().out)["neighbors"]] == ["atlas"]

    assert sdfr([*api, "history"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert "LAST SEEN" in rows[0] and len(rows) == 4

    assert sdfr([*api, "self"]) == 0
    out = capsys.readouterr().out
    assert "r1" in out and "discovery: down" in out


def test_cli_health_exit_status(layer: ApiLayer, capsys: pytest.CaptureFixture[str]) -> None:
    assert sdfr(["--api", layer.api, "health"]) == 1  # discovery down: degraded
    assert capsys.readouterr().out.startswith("degraded: api up, discovery down")
    write_healthy_status(layer.state_dir)
    assert sdfr(["--api", layer.api, "health", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["status"] == "ok"
    # Up, with something to look at: a warning, not a failure.
    conflict = {"address": "10.1.9.7", "boot_id": 3, "last_seen": time.time(), "count": 1}
    write_healthy_status(layer.state_dir, robot_id_conflict=conflict)
    assert sdfr(["--api", layer.api, "health"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("warning: api up, discovery up") and "10.1.9.7" in out


def test_cli_errors_are_one_line(layer: ApiLayer, capsys: pytest.CaptureFixture[str]) -> None:
    assert sdfr(["--api", layer.api, "unpublish", "nosuchid"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == (
        "sdfr: no service of this robot has the id or name 'nosuchid' (`sdfr services`)\n"
    )

    assert sdfr(["--api", layer.api, "publish", "x", "bad type"]) == 1
    assert capsys.readouterr().err.startswith("sdfr: type: ")

    assert sdfr(["--api", f"127.0.0.1:{free_port()}", "neighbors"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("sdfr: cannot reach sdfrd at 127.0.0.1:") and err.count("\n") == 1

    # Usage errors: exit status 2, one line.
    assert sdfr(["--api", layer.api, "publish", "x", "t", "--attr", "novalue"]) == 2
    assert "KEY=VALUE" in capsys.readouterr().err
    assert sdfr(["--api", "nonsense", "neighbors"]) == 2
    assert sdfr([]) == 2
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("true", True),
        ("false", False),
        ("30", 30),
        ("-2", -2),
        ("0.5", 0.5),
        ("007", "007"),
        ("0.50", "0.50"),
        ("1e3", "1e3"),
        ("nan", "nan"),
        ("inf", "inf"),
        ("True", "True"),
        ("x-1", "x-1"),
        ("", ""),
    ],
)
def test_cli_attribute_values_are_typed_when_they_read_back(text: str, value: object) -> None:
    got = typed_value(text)
    assert got == value and type(got) is type(value)


def test_cli_keys_generate_and_manage_a_running_daemon(
    layer: ApiLayer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    k1, k2 = tmp_path / "k1.key", tmp_path / "k2.key"
    assert sdfr(["keys", "generate", str(k1)]) == 0
    assert "wrote key" in capsys.readouterr().out
    assert k1.stat().st_mode & 0o777 == 0o600
    assert sdfr(["keys", "generate", str(k1)]) == 1
    assert "exists already" in capsys.readouterr().err
    assert sdfr(["--json", "keys", "generate", str(k2)]) == 0
    id2 = json.loads(capsys.readouterr().out)["id"]
    id1 = auth.key_id(keystore.read_key_file(k1))
    where = ["keys", "--state-dir", str(layer.state_dir)]

    assert sdfr([*where, "list"]) == 0
    assert "the fleet is open" in capsys.readouterr().out
    assert sdfr([*where, "install", str(k1)]) == 0
    out = capsys.readouterr().out
    assert f"key {id1} installed" in out and "mode: accept" in out and "mode enforce" in out
    assert sdfr([*where, "install", str(k2)]) == 0
    assert "this robot had no key" not in capsys.readouterr().out
    assert sdfr([*where, "use", id2]) == 0
    assert sdfr([*where, "remove", id1]) == 0
    assert sdfr([*where, "mode", "enforce"]) == 0
    capsys.readouterr()
    assert sdfr(["--json", *where, "list"]) == 0
    ring = json.loads(capsys.readouterr().out)
    assert ring["mode"] == "enforce" and ring["primary"] == id2
    assert [k["id"] for k in ring["keys"]] == [id2]
    # --socket works as well as --state-dir; a mistake is one line, exit status 1.
    assert sdfr(["--socket", str(layer.socket), "keys", "remove", id2]) == 1
    err = capsys.readouterr().err
    assert "is the last key" in err and "--open-fleet" in err
    assert sdfr(["keys", "--state-dir", str(tmp_path / "none"), "list"]) == 1
    err = capsys.readouterr().err
    assert "no sdfrd answers on" in err and "api.sock" in err and len(err.splitlines()) == 1
    # And the keyring is on disk for the discovery layer and the next start.
    assert keystore.load_keyring(layer.state_dir) == Keyring.of(
        [keystore.read_key_file(k2)], mode="enforce"
    )


def test_cli_keys_generate_force_replaces_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "fleet.key"
    assert sdfr(["--json", "keys", "generate", str(path)]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first == {"id": auth.key_id(keystore.read_key_file(path)), "file": str(path)}
    assert sdfr(["keys", "generate", str(path)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("sdfr: ") and "--force" in err and len(err.splitlines()) == 1
    assert auth.key_id(keystore.read_key_file(path)) == first["id"]  # untouched
    assert sdfr(["keys", "generate", "--force", str(path)]) == 0
    out = capsys.readouterr().out
    kid = auth.key_id(keystore.read_key_file(path))
    assert kid != first["id"] and f"wrote key {kid} to {path}" in out
    assert path.stat().st_mode & 0o777 == 0o600


def test_cli_keys_json_shapes_and_mistakes(
    layer: ApiLayer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    key_file = tmp_path / "k.key"
    sdfr(["keys", "generate", str(key_file)])
    kid = auth.key_id(keystore.read_key_file(key_file))
    key_text = key_file.read_text().splitlines()[1]
    capsys.readouterr()
    where = ["--socket", str(layer.socket), "keys"]

    assert sdfr(["--json", *where, "list"]) == 0
    assert json.loads(capsys.readouterr().out) == {
        "mode": "open",
        "primary": None,
        "keyed": False,
        "ssdp_interop": True,
        "keys": [],
    }
    # Nothing to sign with yet: a mode is refused, in one line.
    assert sdfr([*where, "mode", "sign"]) == 1
    err = capsys.readouterr().err
    assert "install" in err and len(err.splitlines()) == 1
    assert sdfr([*where, "mode", "lax"]) == 2  # not a mode: a usage error
    capsys.readouterr()

    assert sdfr(["--json", *where, "install", str(key_file)]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["id"] == kid and answer["mode"] == "accept" and answer["primary"] == kid
    [entry] = answer["keys"]
    assert set(entry) == {"id", "primary", "installed", "received"}
    assert entry["id"] == kid and entry["primary"] is True and entry["received"] == 0
    assert sdfr(["--json", *where, "use", kid]) == 0
    assert json.loads(capsys.readouterr().out)["primary"] == kid
    assert sdfr(["--json", *where, "mode", "sign"]) == 0
    assert json.loads(capsys.readouterr().out)["mode"] == "sign"
    assert sdfr([*where, "list"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"mode: sign, signing with {kid}")
    assert "KEY" in out and "RECEIVED" in out and kid in out
    assert sdfr([*where, "use", "0badc0de"]) == 1
    assert "no key '0badc0de'" in capsys.readouterr().err
    assert sdfr([*where, "remove", "0badc0de"]) == 1
    assert "no key '0badc0de'" in capsys.readouterr().err
    # A second key, used, lets the first one go; remove --json shows the keyring left.
    other = tmp_path / "other.key"
    sdfr(["--json", "keys", "generate", str(other)])
    other_id = json.loads(capsys.readouterr().out)["id"]
    assert sdfr([*where, "install", str(other)]) == 0
    assert "this robot had no key" not in capsys.readouterr().out
    assert sdfr([*where, "use", other_id]) == 0
    capsys.readouterr()
    assert sdfr(["--json", *where, "remove", kid]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert [k["id"] for k in answer["keys"]] == [other_id] and answer["mode"] == "sign"
    assert sdfr([*where, "mode", "enforce"]) == 0
    assert capsys.readouterr().out.startswith(f"mode: enforce, signing with {other_id}")
    # The key itself never comes back over the API, nor shows up in the daemon's log.
    assert key_text not in layer.logs()
    assert keystore.load_keyring(layer.state_dir).mode == "enforce"


def test_cli_health_exit_status_when_discovery_fails_or_warns(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    write_healthy_status(layer.state_dir, auth={"mode": "accept", "received": {}})
    assert sdfr(["--api", layer.api, "health", "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["status"] == "warning" and answer["auth"] == "accept"
    write_healthy_status(layer.state_dir, errors={"recent": 4, "last": "timer failed: boom"})
    assert sdfr(["--api", layer.api, "health"]) == 1
    out = capsys.readouterr().out
    assert out.startswith("degraded: api up, discovery failing")
    assert "error: timer failed: boom" in out
    write_healthy_status(layer.state_dir, errors={"recent": 0, "persistent": "set too large"})
    assert sdfr(["--api", layer.api, "health", "--json"]) == 1
    answer = json.loads(capsys.readouterr().out)
    assert answer["discovery"] == "failing" and answer["discovery_error"] == "set too large"


def test_cli_keys_talks_only_to_a_unix_socket_and_says_why_it_cannot(
    layer: ApiLayer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # --socket after `keys`, like --state-dir (and before it, like every command).
    assert sdfr(["--json", "keys", "--socket", str(layer.socket), "list"]) == 0
    assert json.loads(capsys.readouterr().out)["keyed"] is False
    # Never over TCP, and one place at a time: usage errors.
    assert sdfr(["--api", layer.api, "keys", "list"]) == 2
    err = capsys.readouterr().err
    assert "only available on sdfrd's unix socket" in err and "--api" in err
    assert sdfr(["--socket", str(layer.socket), "keys", "--state-dir", str(tmp_path), "list"]) == 2
    assert "not both" in capsys.readouterr().err
    assert sdfr(["keys", "--socket", "a", "--state-dir", "b", "list"]) == 2
    capsys.readouterr()
    # A file that is no socket; a socket nobody listens on (sdfrd died without cleaning up).
    plain = tmp_path / "plain.sock"
    plain.touch()
    assert sdfr(["keys", "--socket", str(plain), "list"]) == 1
    err = capsys.readouterr().err
    assert err == f"sdfr: {plain} is not a unix socket: is --state-dir (or --socket) right?\n"
    stale = tmp_path / "api.sock"
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(stale))
    assert sdfr(["keys", "--state-dir", str(tmp_path), "list"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"sdfr: cannot reach sdfrd at {stale}: Connection refused; is it")
    assert len(err.splitlines()) == 1
    # `generate` needs no daemon: it works whatever the socket.
    assert sdfr(["keys", "--socket", str(plain), "generate", str(tmp_path / "k.key")]) == 0


@pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("setpriv") is None, reason="needs root and setpriv"
)
def test_cli_keys_says_when_this_user_may_not_use_the_socket(tmp_path: Path) -> None:
    """As an unprivileged user: a socket of mode 0660 owned by root, and one in a directory
    that user cannot enter."""
    nobody = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
    probe = subprocess.run([*nobody, sys.executable, "-c", "pass"], capture_output=True, text=True)
    if probe.returncode != 0:  # e.g. a pyenv build under /root that loads its libpython there
        pytest.skip(f"user 65534 cannot run {sys.executable}: {probe.stderr.strip()[:200]}")
    open_dir = Path(tempfile.mkdtemp(prefix="sdfr-keys-", dir="/tmp"))
    try:
        open_dir.chmod(0o755)
        sock = open_dir / "api.sock"
        private = open_dir / "private"
        private.mkdir(mode=0o700)
        with socket.socket(socket.AF_UNIX) as s:
            s.bind(str(sock))
            s.listen()
            sock.chmod(0o660)
            for where, says in (
                (["--socket", str(sock)], f"cannot reach sdfrd at {sock}: Permission denied"),
                (["--state-dir", str(private)], f"cannot look at {private / 'api.sock'}"),
            ):
                res = subprocess.run(
                    [
                        "setpriv", "--reuid=65534", "--regid=65534", "--clear-groups",
                        sys.executable, "-m", "sdfr.cli", "keys", *where, "list",
                    ],
                    capture_output=True, text=True, timeout=30, cwd=REPO,
                )  # fmt: skip
                assert res.returncode == 1, res.stderr
                assert res.stderr.startswith(f"sdfr: {says}")
                assert "needs access to the socket" in res.stderr
                assert len(res.stderr.splitlines()) == 1
    finally:
        shutil.rmtree(open_dir)
