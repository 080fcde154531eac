"""The `sdfr` command against a real API layer: names in change lines, unpublish by name,
search (everything, --wait, --parsable, exit statuses), events --once, --state-dir and
--socket anywhere, keys wording and the way back to an open fleet, one-line usage errors."""

from __future__ import annotations

import base64
import json
import logging
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest

from sdfr.api import create_app
from sdfr.cli import main as sdfr
from sdfr.cli.args import KIND_NAMES
from sdfr.cli.show import ChangeLines, escape
from sdfr.client import Change
from sdfr.config import keystore
from sdfr.config.load import Config
from sdfr.protocol import auth
from sdfr.records.events import Tracker
from sdfr.records.model import PeerRecord, Service
from sdfr.store import Store
from tests.support.api import ApiLayer, aio
from tests.unit.sdfr.test_api_doors import over_unix_socket
from tests.unit.sdfr.test_client_cli import save_fleet

MAP = Service("8294a3360201", "map", "map/grid", None, {})
LIDAR = Service("l1", "lidar", "lidar", "udp://10.1.0.4:2368", {"hz": 10})


def atlas(*services: Service) -> PeerRecord:
    now = time.time()
    return PeerRecord("atlas", "10.1.0.5", "http://10.1.0.5:8701/d.json", 1, 1, "0" * 16, True,
                      now - 10, now, 0.9, 2.0, 5, services)  # fmt: skip


def map_removed(state_dir: Path) -> None:
    """What the discovery layer stores when atlas appears with a map and a lidar, then
    withdraws its map: the records and the tracker's events."""
    tracker = Tracker()
    store = Store(state_dir)
    try:
        for rec in (atlas(MAP, LIDAR), replace(atlas(LIDAR), version=2)):
            store.save_peers([rec], tracker.observe(rec))
    finally:
        store.close()


# -- change lines ------------------------------------------------------------------------------


def test_a_removed_service_is_named_in_its_change_line() -> None:
    lines = ChangeLines()
    appeared = {"new": True, "address": "10.1.0.5", "services": [MAP.to_json()]}
    first = lines.line(Change(1, "robot.appeared", 0.0, "atlas", appeared))
    assert first.endswith("+ atlas appeared at 10.1.0.5 (map)")
    gone = {"added": [LIDAR.to_json()], "removed": [MAP.id], "changed": []}
    line = lines.line(Change(2, "robot.services", 0.0, "atlas", gone))
    assert line.endswith("~ atlas services: +lidar (l1), -map (8294a3360201)")
    # Never seen: the id alone.
    line = ChangeLines().line(Change(2, "robot.services", 0.0, "atlas", gone))
    assert line.endswith("-8294a3360201")


def test_events_once_prints_the_changes_kept_with_names_and_exits(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    map_removed(layer.state_dir)
    assert sdfr(["events", "--once", "--socket", str(layer.socket)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 2
    assert out[0].endswith("+ atlas appeared at 10.1.0.5 (map, lidar)")
    assert out[1].endswith("~ atlas services: -map (8294a3360201)")
    assert (
        sdfr(["events", "--once", "--json", "--event", "robot.services", "--api", layer.api]) == 0
    )
    [change] = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert change["event"] == "robot.services" and change["removed"] == [MAP.id]
    assert sdfr(["--api", layer.api, "events", "--once", "--since", str(change["id"])]) == 0
    assert capsys.readouterr().out == ""


def sdfr_process(*argv: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "sdfr.cli", *argv], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip


def test_neighbors_watch_prints_the_table_then_each_change_with_names(layer: ApiLayer) -> None:
    proc = sdfr_process("neighbors", "--watch", "--socket", str(layer.socket))
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "no reachable robots\n"
        map_removed(layer.state_dir)
        assert proc.stdout.readline().endswith("+ atlas appeared at 10.1.0.5 (map, lidar)\n")
        assert proc.stdout.readline().endswith("~ atlas services: -map (8294a3360201)\n")
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 130


def test_publish_hold_keeps_the_lease_until_interrupted_then_unpublishes(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    proc = sdfr_process("publish", "cam", "camera/rgb", "--ttl", "1", "--hold",
                        "--socket", str(layer.socket))  # fmt: skip
    assert proc.stdout is not None
    sid = proc.stdout.readline().strip()
    time.sleep(2.5)  # past two ttls: renewed meanwhile
    assert sdfr(["--json", "services", "--socket", str(layer.socket)]) == 0
    assert [s["id"] for s in json.loads(capsys.readouterr().out)["services"]] == [sid]
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=30) == 0
    assert sdfr(["--json", "services", "--socket", str(layer.socket)]) == 0
    assert json.loads(capsys.readouterr().out)["services"] == []


def test_the_event_kinds_are_listed_once_each() -> None:
    assert len(KIND_NAMES) == len(set(KIND_NAMES)) and "resync" in KIND_NAMES


# -- unpublish by name -------------------------------------------------------------------------


def test_unpublish_by_name_when_unambiguous_else_the_ids(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    api = ["--api", layer.api]
    ids = []
    for kind in ("map/grid", "map/grid", "camera/rgb"):
        assert sdfr([*api, "publish", "map" if kind == "map/grid" else "cam", kind]) == 0
        ids.append(capsys.readouterr().out.strip())
    assert sdfr([*api, "unpublish", "cam"]) == 0
    assert sdfr([*api, "unpublish", "map"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("sdfr: 2 services of this robot are named 'map': ")
    assert ids[0] in err and ids[1] in err and "give the id" in err and err.count("\n") == 1
    assert sdfr([*api, "unpublish", ids[0]]) == 0
    assert sdfr([*api, "unpublish", "map"]) == 0  # one left: by name
    assert sdfr([*api, "--json", "services"]) == 0
    assert json.loads(capsys.readouterr().out)["services"] == []


# -- search ------------------------------------------------------------------------------------


def test_search_without_a_filter_lists_every_service_and_exit_1_is_no_match(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    api = ["--api", layer.api]
    assert sdfr([*api, "search"]) == 1
    assert capsys.readouterr().out == "no reachable robot offers any service\n"
    save_fleet(layer.state_dir)
    assert sdfr([*api, "search"]) == 0
    rows = capsys.readouterr().out.splitlines()[1:]
    assert sorted(r.split()[2] for r in rows) == ["c1", "c2", "l1"]  # reachable robots only
    assert sdfr([*api, "search", "--type", "nothing"]) == 1
    assert capsys.readouterr().out == "no reachable robot offers a matching service\n"


def test_search_wait_returns_when_a_match_appears_or_fails_after_the_time(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    api = ["--api", layer.api]
    t0 = time.monotonic()
    assert sdfr([*api, "search", "--type", "lidar", "--wait", "0.6"]) == 1
    assert 0.6 <= time.monotonic() - t0 < 5
    capsys.readouterr()
    later = threading.Timer(0.5, save_fleet, [layer.state_dir])
    later.start()
    try:
        t0 = time.monotonic()
        assert sdfr([*api, "search", "--type", "lidar", "--wait", "20"]) == 0
        assert time.monotonic() - t0 < 10
    finally:
        later.join()
    assert capsys.readouterr().out.splitlines()[1].split()[:3] == ["atlas", "10.1.0.5", "l1"]


def test_search_wait_also_waits_for_sdfrd_to_answer(
    tmp_path_factory: pytest.TempPathFactory, capsys: pytest.CaptureFixture[str]
) -> None:
    api = ApiLayer(tmp_path_factory.mktemp("late"))
    save_fleet(api.state_dir)
    started = threading.Timer(0.5, api.start)
    started.start()
    try:
        argv = ["search", "--type", "lidar", "--wait", "30", "--socket", str(api.socket)]
        assert sdfr(argv) == 0
        assert "atlas" in capsys.readouterr().out
    finally:
        started.join()
        api.stop()
    # Without --wait, a daemon that does not answer is an error at once.
    assert sdfr(["search", "--socket", str(api.socket)]) == 1
    assert "cannot reach sdfrd" in capsys.readouterr().err


def test_search_parsable_one_line_per_service_escaped(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    assert escape("a;b\\c\nd é") == "a\\059b\\092c\\010d é"
    odd = Service("o1", "odd;name", "x/y", None, {"k": "v;w", "n": 3})
    store = Store(layer.state_dir)
    try:
        store.save_peers([atlas(odd, LIDAR)])
    finally:
        store.close()
    assert sdfr(["--api", layer.api, "search", "-p"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "=;atlas;10.1.0.5;o1;odd\\059name;x/y;;k=v\\059w;n=3",
        "=;atlas;10.1.0.5;l1;lidar;lidar;udp://10.1.0.4:2368;hz=10",
    ]
    assert sdfr(["--api", layer.api, "search", "--parsable", "--type", "none"]) == 1
    assert capsys.readouterr().out == ""


# -- where sdfrd is ----------------------------------------------------------------------------


def test_state_dir_and_socket_anywhere_on_the_line(
    layer: ApiLayer, capsys: pytest.CaptureFixture[str]
) -> None:
    sd, sock = str(layer.state_dir), str(layer.socket)
    for argv in (
        ["--state-dir", sd, "services"],
        ["services", "--state-dir", sd],
        ["services", "--socket", sock],
        ["--json", "services", "--timeout", "2", "--socket", sock],
        ["keys", "list", "--state-dir", sd],
        ["keys", "--state-dir", sd, "list"],
        ["--state-dir", sd, "keys", "list"],
        ["keys", "list", "--socket", sock],
    ):
        assert sdfr(argv) == 0, argv
    capsys.readouterr()
    for argv in (
        ["services", "--state-dir", sd, "--socket", sock],
        ["--api", layer.api, "services", "--state-dir", sd],
        ["keys", "list", "--api", layer.api],
    ):
        assert sdfr(argv) == 2, argv
        err = capsys.readouterr().err
        assert "not both" in err or "not --api" in err
        assert err.count("\n") == 1


# -- usage errors ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["search", "--state_dir", "x"], "option --state_dir (did you mean '--state-dir'?)"),
        (["neighbors", "--jsno"], "unknown option --jsno (did you mean '--json'?)"),
        (["neighbours"], "unknown command 'neighbours' (did you mean 'neighbors'?)"),
        (["keys", "lsit"], "unknown command 'lsit' (did you mean 'list'?)"),
        (["keys", "mode", "lax"], "'lax' (one of accept, sign, enforce)"),
    ],
)
def test_a_usage_error_is_one_line_with_the_closest_spelling(
    argv: list[str], said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert sdfr(argv) == 2
    err = capsys.readouterr().err
    assert said in err and err.count("\n") == 1, err
    action = " ".join(a for a in argv[:2] if not a.startswith("-") and a in ("search", "keys"))
    assert err.rstrip().endswith("shows usage") and err.startswith(f"sdfr {action}".rstrip())


# -- keys --------------------------------------------------------------------------------------


def test_keys_list_says_what_signs_in_each_mode_and_the_last_key_opens_the_fleet(
    layer: ApiLayer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    key = tmp_path / "fleet.key"
    assert sdfr(["keys", "generate", str(key)]) == 0
    kid = auth.key_id(keystore.read_key_file(key))
    where = ["keys", "--socket", str(layer.socket)]
    assert sdfr([*where, "install", str(key)]) == 0
    capsys.readouterr()
    said = {
        "accept": f"mode: accept, not signing yet (key {kid} signs after `sdfr keys mode "
        "sign`), accepting signed and unsigned datagrams",
        "sign": f"mode: sign, signing with {kid}, accepting signed and unsigned datagrams",
        "enforce": f"mode: enforce, signing with {kid}, accepting signed datagrams only",
    }
    for mode in ("sign", "enforce", "accept"):
        assert sdfr([*where, "mode", mode]) == 0
        assert capsys.readouterr().out.splitlines()[0] == said[mode]
    # The last key: only with --open-fleet, and only once this robot no longer signs.
    assert sdfr([*where, "mode", "sign"]) == 0
    assert sdfr([*where, "remove", kid]) == 1
    assert f"`sdfr keys remove {kid} --open-fleet`" in capsys.readouterr().err
    assert sdfr([*where, "remove", kid, "--open-fleet"]) == 1
    err = capsys.readouterr().err
    assert "mode sign" in err and "`sdfr keys mode accept` on every robot" in err
    assert keystore.load_keyring(layer.state_dir).keyed
    assert sdfr([*where, "mode", "accept"]) == 0
    assert sdfr([*where, "remove", kid, "--open-fleet"]) == 0
    out = capsys.readouterr().out
    assert "the fleet is open" in out and "key_file" in out
    assert keystore.load_keyring(layer.state_dir) == auth.OPEN
    assert sdfr(["--json", *where, "list"]) == 0
    assert json.loads(capsys.readouterr().out)["mode"] == "open"


def test_keys_open_fleet_is_refused_while_other_keys_remain(
    layer: ApiLayer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    k1, k2 = tmp_path / "1.key", tmp_path / "2.key"
    where = ["keys", "--socket", str(layer.socket)]
    for k in (k1, k2):
        assert sdfr(["keys", "generate", str(k)]) == 0
        assert sdfr([*where, "install", str(k)]) == 0
    id2 = auth.key_id(keystore.read_key_file(k2))
    capsys.readouterr()
    assert sdfr([*where, "remove", id2, "--open-fleet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"sdfr: open_fleet: key {id2} is not the last key")
    assert len(keystore.load_keyring(layer.state_dir).keys) == 2


# -- the API with curl (docs/sdfr-cli.md's example) ---------------------------------------------


@pytest.mark.skipif(shutil.which("curl") is None, reason="needs curl")
def test_curl_posts_json_over_the_unix_socket_and_without_the_header_gets_415(
    layer: ApiLayer,
) -> None:
    body = '{"name": "front camera", "type": "camera/rgb", "attributes": {"fps": 30}}'
    curl = ["curl", "-s", "-w", "\n%{http_code}", "--unix-socket", str(layer.socket)]
    url = "http://localhost/services"
    json_type = ["-H", "Content-Type: application/json"]
    done = subprocess.run([*curl, *json_type, "-d", body, url], capture_output=True, text=True)
    answer, status = done.stdout.rsplit("\n", 1)
    assert status == "201" and json.loads(answer)["service"]["attributes"] == {"fps": 30}
    done = subprocess.run([*curl, "-d", body, url], capture_output=True, text=True)
    answer, status = done.stdout.rsplit("\n", 1)
    assert status == "415" and json.loads(answer)["field"] == "Content-Type"


@aio
async def test_an_open_fleet_with_key_file_configured_is_warned_of_in_the_log(
    cfg: Config, store: Store, tmp_path_factory: pytest.TempPathFactory,
    caplog: pytest.LogCaptureFixture,
) -> None:  # fmt: skip
    key = bytes(range(32))
    kid = auth.key_id(key)
    sock = tmp_path_factory.mktemp("s") / "api.sock"
    app = create_app(replace(cfg, key_file=Path("/etc/sdfr/fleet.key")), store)
    async with over_unix_socket(app, sock) as s:
        r = await s.post("http://localhost/keys", json={"key": base64.b64encode(key).decode()})
        assert r.status == 201
        for query in ("?open_fleet=maybe", "?open=1"):
            r = await s.delete(f"http://localhost/keys/{kid}{query}")
            assert r.status == 422, query
        with caplog.at_level(logging.WARNING):
            r = await s.delete(f"http://localhost/keys/{kid}?open_fleet=1")
        assert r.status == 204
    assert keystore.load_keyring(cfg.state_dir) == auth.OPEN
    assert "key_file = /etc/sdfr/fleet.key in the configuration seeds" in caplog.text
