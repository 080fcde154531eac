"""The fleet's WiFi set-up: plan (SSID, key, wpa_supplicant text, commands), apply, CLI, sdfrd.

This machine has no radio: these tests check the generated configuration and command lines,
and run `apply` with a fake runner. Nothing here needs root or touches an interface.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from sdfr.cli import main as sdfr
from sdfr.config.load import Config, from_args, to_args
from sdfr.daemon import supervisor
from sdfr.errors import ConfigError, SdfrError
from sdfr.host import wifi

SECRET = "correct horse battery staple"


def cfg_for(tmp_path: Path, **kw: Any) -> Config:
    base: dict[str, Any] = {"iface": "wlan0", "fleet": 7, "state_dir": tmp_path}
    base["wifi_secret"] = SECRET
    base.update(kw)
    return Config(**base).validate()


class FakeRunner:
    """Records the commands; `fail` names the program whose command exits 1 (or is missing)."""

    def __init__(self, fail: str | None = None, missing: str | None = None) -> None:
        self.calls: list[list[str]] = []
        self.fail = fail
        self.missing = missing

    def __call__(self, argv: list[str], **kw: Any) -> subprocess.CompletedProcess[str]:
        assert kw.get("check") is False and kw.get("capture_output") is True
        if argv[0] == self.missing:
            raise FileNotFoundError(2, "No such file or directory", argv[0])
        self.calls.append(argv)
        if argv[0] == self.fail:
            return subprocess.CompletedProcess(argv, 1, "", "command failed (-95)\n")
        return subprocess.CompletedProcess(argv, 0, "", "")


# -- plan --------------------------------------------------------------------------------------


def test_same_secret_and_fleet_give_the_same_network_on_every_robot(tmp_path: Path) -> None:
    a = wifi.plan(cfg_for(tmp_path / "a", iface="wlan0", robot_id="r1"))
    b = wifi.plan(cfg_for(tmp_path / "b", iface="wlp2s0", robot_id="r2"))
    assert a.ssid == b.ssid == "sdfr-fleet-7"
    assert a.key == b.key and len(a.key) == 64 and int(a.key, 16) >= 0
    # The documented derivation, computed independently.
    expected = hashlib.pbkdf2_hmac("sha256", SECRET.encode(), b"sdfr-fleet-7", 100_000, 32)
    assert a.key == expected.hex()
    # Surrounding whitespace (a file's newline) does not change the key.
    assert wifi.derive_key(SECRET + "\n", 7) == a.key


def test_another_fleet_or_secret_gives_another_network(tmp_path: Path) -> None:
    a = wifi.plan(cfg_for(tmp_path))
    b = wifi.plan(cfg_for(tmp_path, fleet=8))
    c = wifi.plan(cfg_for(tmp_path, wifi_secret="another secret"))
    assert b.ssid == "sdfr-fleet-8" != a.ssid
    assert len({a.key, b.key, c.key}) == 3


def test_ibss_supplicant_config(tmp_path: Path) -> None:
    p = wifi.plan(cfg_for(tmp_path, wifi_freq=2437))
    lines = p.config_text.splitlines()
    assert "ap_scan=2" in lines
    # Its control sockets in sdfrd's state directory, not the /run/wpa_supplicant every
    # namespace (and any other wpa_supplicant) shares.
    assert p.ctrl_dir == p.config_path.parent / "wpa_supplicant"
    assert f"ctrl_interface={p.ctrl_dir}" in lines
    assert f"wpa_cli -p {p.ctrl_dir} -i wlan0 status" in p.describe()
    net = lines[lines.index("network={") + 1 : lines.index("}")]
    assert [x.strip() for x in net] == [
        'ssid="sdfr-fleet-7"',
        "mode=1",
        f"bssid={wifi.bssid_for(7)}",  # one cell for the whole fleet
        "frequency=2437",
        "proto=RSN",
        "key_mgmt=WPA-PSK",
        "pairwise=CCMP",
        "group=CCMP",
        f"psk={p.key}",  # raw 64-hex PSK: unquoted
    ]
    assert not any(x.startswith("country=") for x in lines)


def test_mesh_supplicant_config(tmp_path: Path) -> None:
    p = wifi.plan(cfg_for(tmp_path, wifi_mode="mesh", wifi_freq=5180, wifi_country="de"))
    lines = p.config_text.splitlines()
    assert "country=DE" in lines and "ap_scan=2" not in lines
    assert "mesh_max_inactivity=60" in lines  # a peer whose SAE failed is blocked 60 s
    net = lines[lines.index("network={") + 1 : lines.index("}")]
    assert [x.strip() for x in net] == [
        'ssid="sdfr-fleet-7"',
        "mode=5",
        "frequency=5180",
        "key_mgmt=SAE",
        f'sae_password="{p.key}"',
        # peering's timers, for slow CPUs: 1 s for a Confirm, not 40 ms
        "dot11MeshRetryTimeout=1000",
        "dot11MeshConfirmTimeout=1000",
        "dot11MeshMaxRetries=3",
    ]
    assert p.commands[0] == ("iw", "reg", "set", "DE")
    assert ("iw", "dev", "wlan0", "set", "type", "mesh") in p.commands


def test_command_lines(tmp_path: Path) -> None:
    p = wifi.plan(cfg_for(tmp_path))
    conf = tmp_path / "wpa_supplicant-wlan0.conf"
    pid = tmp_path / "wpa_supplicant-wlan0.pid"
    assert (p.config_path, p.pid_path) == (conf, pid)
    assert p.command_lines() == [
        "ip link set wlan0 down",
        "iw dev wlan0 set type ibss",
        "ip link set wlan0 up",
        f"wpa_supplicant -B -D nl80211 -i wlan0 -c {conf} -P {pid}",
    ]


def test_plan_does_no_io(tmp_path: Path) -> None:
    wifi.plan(cfg_for(tmp_path / "nothing-here"))
    assert not (tmp_path / "nothing-here").exists()


def test_key_never_in_repr(tmp_path: Path) -> None:
    cfg = cfg_for(tmp_path)
    p = wifi.plan(cfg)
    assert SECRET not in repr(cfg) and p.key not in repr(p)
    assert p.key not in p.config_shown() and p.key in p.config_shown(show_key=True)


# -- configuration -----------------------------------------------------------------------------


def test_defaults() -> None:
    cfg = from_args([])
    assert (cfg.wifi, cfg.wifi_mode, cfg.wifi_freq) == ("auto", "ibss", 2412)
    assert cfg.wifi_secret is None and cfg.wifi_secret_file is None and cfg.wifi_country is None


@pytest.mark.parametrize(
    ("text", "word"),
    [
        ('wifi = "on"\n', "wifi: must be auto or off"),
        ('wifi_mode = "adhoc"\n', "wifi_mode"),
        ("wifi_freq = 2400\n", "wifi_freq"),
        ("wifi_freq = 5190\n", "wifi_freq"),
        ('wifi_freq = "x"\n', "wifi_freq"),
        ('wifi_country = "GER"\n', "wifi_country"),
        ('wifi_secret = "short"\n', "wifi_secret"),
        ("wifi_secret = 12345678\n", "wifi_secret"),
        ('wifi_secret = "long enough"\nwifi_secret_file = "/x"\n', "wifi_secret"),
    ],
)
def test_bad_wifi_keys_are_named(tmp_path: Path, text: str, word: str) -> None:
    conf = tmp_path / "bad.toml"
    conf.write_text(text)
    with pytest.raises(ConfigError, match=word):
        from_args(["--config", str(conf)])


def test_wifi_keys_from_toml_and_flags(tmp_path: Path) -> None:
    conf = tmp_path / "sdfrd.toml"
    conf.write_text(
        '[sdfrd]\nwifi-mode = "mesh"\nwifi_freq = 5745\nwifi_country = "FR"\n'
        'wifi_secret_file = "/etc/sdfr/wifi.secret"\n'
    )
    cfg = from_args(["--config", str(conf), "--wifi-freq", "2462"])
    assert (cfg.wifi_mode, cfg.wifi_freq, cfg.wifi_country) == ("mesh", 2462, "FR")
    assert cfg.wifi_secret_file == Path("/etc/sdfr/wifi.secret")


def test_secret_is_not_passed_to_the_layers(tmp_path: Path) -> None:
    cfg = cfg_for(tmp_path, wifi_mode="mesh")
    args = to_args(cfg)
    assert SECRET not in args and "--wifi-secret" not in args and "--wifi-mode" in args
    assert from_args(args) == replace(cfg, wifi_secret=None)


def test_secret_file(tmp_path: Path) -> None:
    path = tmp_path / "wifi.secret"
    path.write_text(SECRET + "\n")
    path.chmod(0o600)
    cfg = cfg_for(tmp_path, wifi_secret=None, wifi_secret_file=path)
    secret, warnings = wifi.load_secret(cfg)
    assert secret is not None and warnings == []
    assert wifi.plan(cfg, secret).key == wifi.plan(cfg_for(tmp_path)).key
    path.chmod(0o644)
    assert "readable by every user" in wifi.load_secret(cfg)[1][0]
    path.write_text("short\n")
    with pytest.raises(ConfigError, match="wifi_secret_file"):
        wifi.load_secret(cfg)
    with pytest.raises(ConfigError, match=r"wifi_secret_file: .* does not exist"):
        wifi.load_secret(replace(cfg, wifi_secret_file=tmp_path / "nope"))


def test_plan_without_secret_names_the_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="wifi_secret"):
        wifi.plan(cfg_for(tmp_path, wifi_secret=None))


# -- apply -------------------------------------------------------------------------------------


def test_apply_writes_private_config_and_runs_commands_in_order(tmp_path: Path) -> None:
    p = wifi.plan(cfg_for(tmp_path / "state"))
    runner = FakeRunner()
    wifi.apply(p, runner)
    assert runner.calls == [list(argv) for argv in p.commands]
    assert p.config_path.read_text() == p.config_text
    assert p.config_path.stat().st_mode & 0o777 == 0o600


def test_apply_stops_at_the_failing_command_and_says_what_to_check(tmp_path: Path) -> None:
    p = wifi.plan(cfg_for(tmp_path, wifi_mode="mesh"))
    runner = FakeRunner(fail="iw")
    with pytest.raises(SdfrError, match=r"`iw dev wlan0 set type mesh` failed.*mesh point"):
        wifi.apply(p, runner)
    assert [c[0] for c in runner.calls] == ["ip", "iw"]
    with pytest.raises(SdfrError, match=r"wpa_supplicant -B .* failed.*other wpa_supplicant"):
        wifi.apply(p, FakeRunner(fail="wpa_supplicant"))


def test_a_failure_shows_what_the_tool_said_not_its_tear_down() -> None:
    """wpa_supplicant ends a failed start with its tear-down lines: the cause is before them."""
    out = (
        "Successfully initialized wpa_supplicant\n"
        "Failed to initialize control interface '/run/wpa_supplicant'.\n"
        "You may have another wpa_supplicant process already running\n"
        "nl80211: deinit ifname=wlan0 disabled_11b_rates=0\n"
    )
    assert wifi.said(out, "") == (
        ": Failed to initialize control interface '/run/wpa_supplicant'. / You may have "
        "another wpa_supplicant process already running"
    )
    assert wifi.said("", "") == "" and wifi.said(None, "a\nb\nc\nd\ne") == ": b / c / d / e"


def test_apply_names_the_missing_package(tmp_path: Path) -> None:
    p = wifi.plan(cfg_for(tmp_path))
    with pytest.raises(
        SdfrError, match=r"`wpa_supplicant` is not installed.*apt install wpasupplicant"
    ):
        wifi.apply(p, FakeRunner(missing="wpa_supplicant"))
    with pytest.raises(SdfrError, match=r"`iw` is not installed.*apt install iw"):
        wifi.apply(p, FakeRunner(missing="iw"))


def test_apply_says_root_is_needed() -> None:
    with pytest.raises(SdfrError, match="needs root"):
        wifi.check_root(lambda: 1000)
    wifi.check_root(lambda: 0)


# -- is_wireless and sdfrd ---------------------------------------------------------------------


def test_is_wireless() -> None:
    assert not wifi.is_wireless("lo")
    assert not wifi.is_wireless("no-such-iface0")


def test_is_wireless_reads_sysfs(tmp_path: Path) -> None:
    (tmp_path / "wlan0" / "phy80211").mkdir(parents=True)
    (tmp_path / "wlan1" / "wireless").mkdir(parents=True)
    (tmp_path / "eth0").mkdir()
    assert wifi.is_wireless("wlan0", tmp_path) and wifi.is_wireless("wlan1", tmp_path)
    assert not wifi.is_wireless("eth0", tmp_path)


def test_setup_applies_only_to_a_wireless_iface_with_a_secret(tmp_path: Path) -> None:
    sys_net = tmp_path / "sys"
    (sys_net / "wlan0" / "wireless").mkdir(parents=True)
    (sys_net / "eth0").mkdir()
    root = lambda: 0  # noqa: E731
    runner = FakeRunner()
    cfg = cfg_for(tmp_path)
    assert wifi.setup(replace(cfg, iface="eth0"), runner, sys_net, root) is None
    assert wifi.setup(replace(cfg, wifi="off"), runner, sys_net, root) is None
    assert wifi.setup(replace(cfg, wifi_secret=None), runner, sys_net, root) is None
    assert runner.calls == []
    done = wifi.setup(cfg, runner, sys_net, root)
    assert done is not None and runner.calls == [list(a) for a in done.commands]


def test_sdfrd_does_not_touch_a_wired_iface(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[object] = []

    def no_commands(*args: object, **kw: object) -> None:
        calls.append(args)
        raise AssertionError("sdfrd ran a command on a non-wireless interface")

    monkeypatch.setattr(subprocess, "run", no_commands)
    monkeypatch.setattr(wifi, "apply", no_commands)
    monkeypatch.setattr(supervisor.Supervisor, "run", lambda self: 0)
    argv = ["--iface", "lo", "--robot-id", "r1", "--state-dir", str(tmp_path)]
    argv += ["--wifi-secret", SECRET]
    assert supervisor.main(argv) == 0
    assert calls == [] and not list(tmp_path.glob("wpa_supplicant*"))


# -- sdfr wifi-config --------------------------------------------------------------------------


def write_config(tmp_path: Path, extra: str = "") -> Path:
    secret = tmp_path / "wifi.secret"
    secret.write_text(SECRET + "\n")
    secret.chmod(0o600)
    conf = tmp_path / "sdfrd.toml"
    conf.write_text(
        f'[sdfrd]\nfleet = 7\nstate_dir = "{tmp_path}"\nwifi_secret_file = "{secret}"\n{extra}'
    )
    return conf


def test_wifi_config_dry_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    conf = write_config(tmp_path)
    assert sdfr(["wifi-config", "--config", str(conf), "--iface", "wlan0", "--dry-run"]) == 0
    out = capsys.readouterr().out
    key = wifi.derive_key(SECRET, 7)
    assert key not in out and f"psk={wifi.MASK}" in out
    assert 'ssid="sdfr-fleet-7"' in out
    assert "ip link set wlan0 down\niw dev wlan0 set type ibss\nip link set wlan0 up\n" in out
    assert f"wpa_supplicant -B -D nl80211 -i wlan0 -c {tmp_path}/wpa_supplicant-wlan0.conf" in out
    assert "wlan0 is not a wireless interface" in out  # no radio here
    assert not list(tmp_path.glob("wpa_supplicant*"))  # a dry run writes nothing
    # --fleet overrides the file; --show-key prints the key.
    assert sdfr(["wifi-config", "--config", str(conf), "--iface", "wlan0", "--fleet", "9",
                 "--dry-run", "--show-key"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert 'ssid="sdfr-fleet-9"' in out and f"psk={wifi.derive_key(SECRET, 9)}" in out


def test_wifi_config_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    conf = write_config(tmp_path, 'wifi_mode = "mesh"\nwifi_freq = 2437\n')
    argv = ["--json", "wifi-config", "--config", str(conf), "--iface", "lo", "--dry-run"]
    assert sdfr(argv) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["ssid"] == "sdfr-fleet-7" and answer["mode"] == "mesh"
    assert answer["frequency"] == 2437 and answer["key"] is None
    assert answer["config_path"] == str(tmp_path / "wpa_supplicant-lo.conf")
    assert answer["commands"][1] == ["iw", "dev", "lo", "set", "type", "mesh"]
    assert f'sae_password="{wifi.MASK}"' in answer["config"]
    assert (answer["dry_run"], answer["applied"], answer["wireless"]) == (True, False, False)
    assert answer["sdfrd_applies"] is False


def test_wifi_config_refuses_a_wired_iface(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    conf = write_config(tmp_path)
    # A name no interface has (not `lo`: a bug here must not take a real interface down).
    assert sdfr(["wifi-config", "--config", str(conf), "--iface", "sdfrtest0"]) == 1
    assert "sdfrtest0 is not a wireless interface; not touching it" in capsys.readouterr().err
    assert not list(tmp_path.glob("wpa_supplicant*"))


def test_wifi_config_errors_name_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    conf = write_config(tmp_path)
    assert sdfr(["wifi-config", "--config", str(conf), "--iface", "wlan0",
                 "--wifi-freq", "2400", "--dry-run"]) == 2  # fmt: skip
    assert "wifi_freq" in capsys.readouterr().err
    empty = tmp_path / "empty.toml"
    empty.write_text("")
    assert sdfr(["wifi-config", "--config", str(empty), "--iface", "wlan0", "--dry-run"]) == 2
    assert "wifi_secret" in capsys.readouterr().err


def test_world_readable_secret_file_warns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    conf = write_config(tmp_path)
    os.chmod(tmp_path / "wifi.secret", 0o644)
    assert sdfr(["wifi-config", "--config", str(conf), "--iface", "wlan0", "--dry-run"]) == 0
    assert "readable by every user" in capsys.readouterr().err


def test_the_key_is_the_same_without_openssl() -> None:
    """sdfrd keeps OpenSSL out of its processes (sdfr.daemon): the fallback PBKDF2 gives
    OpenSSL's key."""
    for password, salt, rounds in ((b"password", b"IEEE", 4096), (SECRET.encode(), b"x", 1000)):
        expected = hashlib.pbkdf2_hmac("sha256", password, salt, rounds, 32)
        saved = sys.modules["_hashlib"]
        sys.modules["_hashlib"] = None  # type: ignore[assignment]
        try:
            assert wifi.pbkdf2_sha256(password, salt, rounds) == expected
        finally:
            sys.modules["_hashlib"] = saved
    long = b"p" * 100  # longer than a SHA-256 block: hashed first, as HMAC does
    saved = sys.modules["_hashlib"]
    sys.modules["_hashlib"] = None  # type: ignore[assignment]
    try:
        fallback = wifi.pbkdf2_sha256(long, b"s", 10)
    finally:
        sys.modules["_hashlib"] = saved
    assert fallback == hashlib.pbkdf2_hmac("sha256", long, b"s", 10, 32)


@pytest.mark.parametrize("where", [["--api", "10.0.0.2:8042"], ["--state-dir", "/tmp/x"]])
def test_local_actions_refuse_options_that_name_a_daemon(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], where: list[str]
) -> None:
    """wifi-config and example never talk to sdfrd: --api/--socket/--state-dir there would be
    silently ignored (a user who meant another robot's daemon would plan this one's)."""
    conf = write_config(tmp_path)
    assert sdfr([*where, "wifi-config", "--config", str(conf), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert f"wifi-config does not talk to sdfrd: {where[0]} has no use here" in err
    assert "--config" in err
    assert sdfr(["example", "robot.toml", *where]) == 2
    assert f"example does not talk to sdfrd: {where[0]}" in capsys.readouterr().err


def test_an_ibss_fleet_has_one_fixed_cell() -> None:
    """Robots that start at once join one cell (fixed BSSID), not one each."""
    bssid = wifi.bssid_for(7)
    first = int(bssid[:2], 16)
    assert first & 0x02 and not first & 0x01  # locally administered, unicast
    assert bssid == wifi.bssid_for(7) != wifi.bssid_for(8)
    text = wifi.supplicant_config("ibss", "sdfr-fleet-7", 2412, "00" * 32, bssid=bssid)
    assert f"\tbssid={bssid}" in text
