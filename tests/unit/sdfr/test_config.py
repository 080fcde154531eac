"""Configuration: defaults, TOML file, flags, and errors that name the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from sdfr.config import load
from sdfr.config import options as config_options
from sdfr.config.load import Config, build_parser, from_args, to_args
from sdfr.daemon import supervisor
from sdfr.errors import ConfigError


def test_defaults_are_the_papers() -> None:
    cfg = from_args([])
    assert cfg.beacon_interval == 10.0 and cfg.miss_limit == 3
    assert cfg.api == "127.0.0.1:8700"
    assert cfg.effective_ping_interval == 10.0 and cfg.ping_window == 20


def test_toml_then_flags_override(tmp_path: Path) -> None:
    conf = tmp_path / "sdfrd.toml"
    conf.write_text(
        '[sdfrd]\nfleet = 7\nbeacon-interval = 2.5\nrobot_id = "scout-1"\napi = "127.0.0.1:9000"\n'
    )
    cfg = from_args(["--config", str(conf), "--fleet", "8"])
    assert (cfg.fleet, cfg.beacon_interval, cfg.robot_id, cfg.api) == (
        8,
        2.5,
        "scout-1",
        "127.0.0.1:9000",
    )
    # A top-level table works too.
    conf.write_text("fleet = 9\n")
    assert from_args(["--config", str(conf)]).fleet == 9


@pytest.mark.parametrize(
    ("text", "word"),
    [
        ("fleet = 300\n", "fleet"),
        ('fleet = "x"\n', "fleet"),
        ("beacon_interval = 0\n", "beacon_interval"),
        ('api = "nowhere"\n', "api"),
        ('group = "10.0.0.1"\n', "group"),
        ("colour = 1\n", "unknown key 'colour'"),
        ("fleet = \n", "not valid TOML"),
        ('robot_id = "has space"\n', "robot_id"),
    ],
)
def test_bad_config_file_names_the_key(tmp_path: Path, text: str, word: str) -> None:
    conf = tmp_path / "bad.toml"
    conf.write_text(text)
    with pytest.raises(ConfigError, match=word):
        from_args(["--config", str(conf)])


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ('[sdfrd]\nifce = "lo"\n', "unknown key 'ifce' in .* \\(did you mean 'iface'\\?\\)"),
        ("beacon-intervall = 2\n", "did you mean 'beacon_interval'"),
        ('[sdrfd]\niface = "lo"\n', "unknown section \\[sdrfd\\] .*did you mean \\[sdfrd\\]"),
        ('[sdfrd]\niface = "lo"\n[wifi]\nmode = 1\n', "unknown section \\[wifi\\]"),
        (
            'fleet = 3\n[sdfrd]\niface = "lo"\n',
            "'fleet' is at the top level of .* which has an \\[sdfrd\\] table.*move 'fleet'",
        ),
        ("zzz = 1\n", "unknown key 'zzz' in [^(]*; known keys"),  # no hint when none is close
        ("indicator_thresholds = [0.5, 2]\n", "indicator_thresholds: each must be above 0"),
        ("indicator_thresholds = [true]\n", "indicator_thresholds: expected a list of numbers"),
    ],
)
def test_unknown_keys_and_sections_are_errors_with_a_hint(
    tmp_path: Path, text: str, says: str
) -> None:
    conf = tmp_path / "c.toml"
    conf.write_text(text)
    with pytest.raises(ConfigError, match=says):
        from_args(["--config", str(conf)])


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        from_args(["--config", str(tmp_path / "nope.toml")])


def test_to_args_round_trips() -> None:
    cfg = Config(iface="eth0", fleet=4, robot_id="r9", beacon_interval=1.5, state_dir=Path("/x"))
    assert from_args(to_args(cfg)) == cfg


PLAIN = [
    [],
    ["--iface", "eth0", "--fleet", "3"],
    ["--iface=eth0", "--fleet=3", "--fleet", "4"],  # the last one wins
    ["--state-dir", "/x y", "--api", "0.0.0.0:1", "--api-allowed-hosts", "a,b"],
    ["--log-level="],
]
# Every one of these goes to argparse: an abbreviation, a value that looks like a flag, a
# negative number, a lone flag, a positional, `--`, and a short option.
NOT_PLAIN = [
    ["--beacon", "2"],
    ["--iface", "--fleet", "3"],
    ["--fleet", "-1"],
    ["--iface"],
    ["eth0"],
    ["--", "--iface", "eth0"],
    ["-h"],
]


@pytest.mark.parametrize("argv", PLAIN + NOT_PLAIN)
def test_plain_flags_read_as_argparse_reads_them(argv: list[str]) -> None:
    """The daemon reads a plain command line without argparse; it must agree with argparse
    on every one it takes, and leave every other to it."""
    try:
        args = vars(build_parser().parse_args(argv))
    except SystemExit:
        args = None
    plain = load._plain_flags(argv)
    if argv in NOT_PLAIN:
        assert plain is None
    else:
        assert args is not None and plain is not None
        assert plain == {k: str(v) for k, v in args.items() if v is not None}


def test_argparse_still_reads_and_rejects_what_is_not_plain(tmp_path: Path) -> None:
    assert from_args(["--beacon", "2.5"]).beacon_interval == 2.5  # (an abbreviation)
    with pytest.raises(SystemExit):
        from_args(["--iface"])
    with pytest.raises(SystemExit):
        from_args(["--no-such-flag", "1"])
    conf = tmp_path / "c.toml"
    conf.write_text("fleet = 6\n")
    assert from_args(["--config", str(conf)]).fleet == 6
    assert from_args([f"--config={conf}", "--fleet", "7"]).fleet == 7


def test_help_documents_every_option() -> None:
    text = build_parser().format_help()
    for flag in (
        "--iface",
        "--fleet",
        "--api",
        "--config",
        "--state-dir",
        "--beacon-interval",
        "--robot-id",
        "--miss-limit",
        "--describe",
    ):
        assert flag in text


def test_sdfrd_reports_bad_flags_in_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    assert supervisor.main(["--iface", "nope0", "--state-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sdfrd: iface:") and err.count("\n") == 1
    assert supervisor.main(["--iface", "lo", "--beacon-interval", "-1"]) == 2
    assert "beacon_interval" in capsys.readouterr().err


def test_the_shipped_robot_config_parses() -> None:
    cfg = from_args(
        ["--config", str(Path(__file__).resolve().parents[3] / "examples" / "robot.toml")]
    )
    assert (cfg.addressing, cfg.fleet, cfg.iface) == ("auto", 3, "wlan0")


def test_fleet_key_options(tmp_path: Path) -> None:
    conf = tmp_path / "sdfrd.toml"
    conf.write_text('key_file = "/etc/sdfr/fleet.key"\nauth = "sign"\nssdp_interop = "on"\n')
    cfg = from_args(["--config", str(conf)])
    assert (cfg.key_file, cfg.auth, cfg.ssdp_interop) == (Path("/etc/sdfr/fleet.key"), "sign", "on")
    assert from_args(to_args(cfg)) == cfg  # the layers get them too
    defaults = from_args([])
    assert (defaults.key_file, defaults.auth, defaults.ssdp_interop) == (None, None, "auto")
    with pytest.raises(ConfigError, match="auth: must be accept, sign or enforce"):
        from_args(["--auth", "lax"])
    with pytest.raises(ConfigError, match="ssdp_interop: must be auto, on or off"):
        from_args(["--ssdp-interop", "yes"])


def test_fleet_key_options_from_flags() -> None:
    cfg = from_args(["--key-file", "/etc/sdfr/k.key", "--auth", "accept", "--ssdp-interop", "off"])
    assert (cfg.key_file, cfg.auth, cfg.ssdp_interop) == (Path("/etc/sdfr/k.key"), "accept", "off")
    args = to_args(cfg)
    assert args[args.index("--key-file") + 1] == "/etc/sdfr/k.key"
    assert args[args.index("--auth") + 1] == "accept"
    assert args[args.index("--ssdp-interop") + 1] == "off"
    assert from_args(args) == cfg
    assert "--auth" not in to_args(from_args([]))  # unset: the keyring's own mode is kept
    assert "--key-file" not in to_args(from_args([]))
    for mode in ("accept", "sign", "enforce"):
        assert from_args(["--auth", mode]).auth == mode
    for interop in ("auto", "on", "off"):
        assert from_args(["--ssdp-interop", interop]).ssdp_interop == interop


def test_flags_override_the_fleet_key_options_of_the_file(tmp_path: Path) -> None:
    conf = tmp_path / "sdfrd.toml"
    conf.write_text('[sdfrd]\nkey-file = "/a.key"\nauth = "enforce"\nssdp-interop = "off"\n')
    cfg = from_args(["--config", str(conf), "--auth", "sign", "--key-file", "/b.key"])
    assert (cfg.key_file, cfg.auth, cfg.ssdp_interop) == (Path("/b.key"), "sign", "off")


@pytest.mark.parametrize(
    ("text", "word"),
    [
        ('auth = "lax"\n', "auth: must be accept, sign or enforce, got 'lax'"),
        ("auth = 1\n", "auth: expected a string"),
        ('auth = "Enforce"\n', "auth:"),
        ('ssdp_interop = "yes"\n', "ssdp_interop: must be auto, on or off, got 'yes'"),
        ("ssdp_interop = true\n", "ssdp_interop: expected a string"),
    ],
)
def test_bad_fleet_key_options_name_the_key(tmp_path: Path, text: str, word: str) -> None:
    conf = tmp_path / "bad.toml"
    conf.write_text(text)
    with pytest.raises(ConfigError, match=word):
        from_args(["--config", str(conf)])


def test_help_documents_the_fleet_key_options() -> None:
    text = build_parser().format_help()
    for flag in ("--key-file", "--auth", "--ssdp-interop"):
        assert flag in text
    assert "sdfr keys generate" in " ".join(text.split())


def test_the_core_takes_its_config_by_field_name_and_the_defaults_agree() -> None:
    from dataclasses import fields

    from sdfr.protocol import CoreConfig

    default = Config(robot_id="r1")
    core = default.core_config()
    assert core == CoreConfig(fleet=1, robot_id="r1")  # one set of defaults
    cfg = Config(
        robot_id="r7", fleet=3, beacon_interval=2.0, miss_limit=5, ping_window=7, ssdp_interop="on"
    )
    core = cfg.core_config()
    assert (core.fleet, core.robot_id, core.beacon_interval, core.miss_limit) == (3, "r7", 2.0, 5)
    assert core.ping_interval == 2.0  # unset: the beacon interval
    assert core.ping_window == 7 and core.ssdp_interop is True
    shared = {f.name for f in fields(CoreConfig)} & {f.name for f in fields(Config)}
    assert shared >= {"beacon_interval", "miss_limit", "ping_window", "group", "port"}


def test_the_layers_option(tmp_path: Path) -> None:
    conf = tmp_path / "sdfrd.toml"
    conf.write_text('layers = "threads"\n')
    cfg = from_args(["--config", str(conf)])
    assert cfg.layers == "threads" and from_args(to_args(cfg)) == cfg
    assert from_args(["--config", str(conf), "--layers", "processes"]).layers == "processes"
    with pytest.raises(ConfigError, match="layers: must be processes or threads, got 'thread'"):
        from_args(["--layers", "thread"])


def test_every_option_is_one_field_with_its_help_and_kind() -> None:
    """The one place an option is defined: a Config field whose metadata the flags, the TOML
    keys, `to_args` and netlab's checks read."""
    for name, f in load.OPTIONS.items():
        assert f.metadata["help"] and config_options.kind(name), name
        assert load.flag(name) in build_parser().format_help()
    assert [n for n, f in load.OPTIONS.items() if not f.metadata["passed"]] == ["wifi_secret"]


def test_option_flags_give_lists_comma_separated_and_leave_out_the_unset() -> None:
    opts = {"api_allowed_hosts": ("a", "b"), "key_file": None, "api_allowed_origins": ()}
    assert load.option_flags(opts) == ["--api-allowed-hosts", "a,b"]
    assert from_args(load.option_flags({"indicator_thresholds": [0.3, 0.6]})) == Config(
        indicator_thresholds=(0.3, 0.6)
    )


@pytest.mark.parametrize(
    ("options", "says"),
    [
        ({"mis_limit": 3}, "mis_limit: not an sdfrd option \\(did you mean 'miss_limit'\\?\\)"),
        ({"miss_limit": "x"}, "miss_limit: expected int"),
        ({"beacon_interval": 0}, "beacon_interval: must be 0.05-3600"),
    ],
)
def test_options_config_names_a_typo_or_a_bad_value(options: dict[str, object], says: str) -> None:
    with pytest.raises(ConfigError, match=says):
        load.options_config(options)


def test_options_config_takes_python_and_toml_values() -> None:
    cfg = load.options_config(
        {"miss_limit": 5, "state_dir": Path("/x"), "ping_interval": "0.5", "iface": None}
    )
    assert (cfg.miss_limit, cfg.state_dir, cfg.ping_interval, cfg.iface) == (
        5,
        Path("/x"),
        0.5,
        None,
    )
