"""Daemon configuration: defaults, TOML file, command-line flags, one validated dataclass."""

from __future__ import annotations

import ipaddress
import os
import re
import sys
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sdfr import version_text, wire
from sdfr.errors import ConfigError
from sdfr.hints import did_you_mean
from sdfr.model import ROBOT_ID_RE
from sdfr.protocol import (
    BEACON_INTERVAL,
    MISS_LIMIT,
    PING_WINDOW,
    REPLY_DELAY_MAX,
    CoreConfig,
)

if TYPE_CHECKING:
    import argparse

DEFAULT_API = "127.0.0.1:8700"
DEFAULT_DESCRIBE = "iface:8701"
#: The host of `describe` that means "the fleet interface's address, wherever it moves".
IFACE_HOST = "iface"
#: How sdfrd runs its two layers (`layers`): as processes, or as threads of one process.
LAYER_MODES = ("processes", "threads")


def default_state_dir() -> Path:
    if os.geteuid() == 0:
        return Path("/var/lib/sdfr")
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "sdfr"


@dataclass(frozen=True, slots=True)
class Config:
    """Everything `sdfrd` can be told; every field is a flag and a TOML key of the same name."""

    iface: str | None = None
    fleet: int = 1
    api: str = DEFAULT_API
    describe: str = DEFAULT_DESCRIBE
    state_dir: Path = field(default_factory=default_state_dir)
    beacon_interval: float = BEACON_INTERVAL
    robot_id: str | None = None
    group: str = wire.DEFAULT_GROUP
    port: int = wire.DEFAULT_PORT
    miss_limit: int = MISS_LIMIT
    ping_interval: float | None = None
    ping_window: int = PING_WINDOW
    reply_delay_max: float = REPLY_DELAY_MAX
    ttl: int = 1
    addressing: str = "manual"
    log_level: str = "info"
    log_format: str = "text"
    wifi: str = "auto"
    wifi_secret: str | None = field(default=None, repr=False)
    wifi_secret_file: Path | None = None
    wifi_mode: str = "ibss"
    wifi_freq: int = 2412
    wifi_country: str | None = None
    key_file: Path | None = None
    auth: str | None = None
    ssdp_interop: str = "auto"
    api_allowed_hosts: tuple[str, ...] = ()
    api_allowed_origins: tuple[str, ...] = ()
    api_allow_remote: bool = False
    api_token_file: Path | None = None
    indicator_thresholds: tuple[float, ...] = (0.5, 0.8)
    layers: str = "threads"

    @property
    def ssdp_interop_wanted(self) -> bool | None:
        """`ssdp_interop` as the protocol takes it: on True, off False, auto None."""
        return {"on": True, "off": False}.get(self.ssdp_interop)

    @property
    def effective_ping_interval(self) -> float:
        return self.ping_interval if self.ping_interval is not None else self.beacon_interval

    def core_config(self) -> CoreConfig:
        """The protocol core's configuration: its fields of the same name, with the derived
        ones (the ping interval, SSDP interop) worked out.  Call it on a resolved Config."""
        derived: dict[str, Any] = {
            "ping_interval": self.effective_ping_interval,
            "ssdp_interop": self.ssdp_interop_wanted,
        }
        ours = {f.name for f in fields(Config)}
        kw = {
            f.name: derived[f.name] if f.name in derived else getattr(self, f.name)
            for f in fields(CoreConfig)
            if f.name in ours
        }
        return CoreConfig(**kw)

    def validate(self) -> Config:
        """Return self, or raise ConfigError naming the key that is wrong."""
        if not 0 <= self.fleet <= 255:
            raise ConfigError(
                f"fleet: must be 0-255 (it is the second octet of 10.<fleet>.x.y), got {self.fleet}"
            )
        api_host, _ = split_hostport("api", self.api)
        if not _loopback(api_host) and not (self.api_allow_remote and self.api_token_file):
            raise ConfigError(
                f"api: {api_host} is not a loopback address: the write API would be open to "
                "every machine that reaches this robot. Keep it on 127.0.0.1, or set both "
                "api_allow_remote = true and api_token_file = FILE (requests from other "
                "machines must then carry Authorization: Bearer <the file's token>)"
            )
        describe_address(self.describe)
        if not 0.05 <= self.beacon_interval <= 3600:
            raise ConfigError(
                f"beacon_interval: must be 0.05-3600 seconds, got {self.beacon_interval}"
            )
        if self.robot_id is not None and not ROBOT_ID_RE.fullmatch(self.robot_id):
            raise ConfigError(
                f"robot_id: {self.robot_id!r} must be 1-64 characters of A-Z a-z 0-9 . _ -"
            )
        try:
            group = ipaddress.IPv4Address(self.group)
        except ValueError as exc:
            raise ConfigError(f"group: {exc}") from None
        if not group.is_multicast:
            raise ConfigError(f"group: {self.group} is not an IPv4 multicast address")
        if not 1 <= self.port <= 65535:
            raise ConfigError(f"port: must be 1-65535, got {self.port}")
        if not 1 <= self.miss_limit <= 100:
            raise ConfigError(f"miss_limit: must be 1-100 beacon periods, got {self.miss_limit}")
        if self.ping_interval is not None and not 0.02 <= self.ping_interval <= 3600:
            raise ConfigError(f"ping_interval: must be 0.02-3600 seconds, got {self.ping_interval}")
        if not 1 <= self.ping_window <= 10000:
            raise ConfigError(f"ping_window: must be 1-10000 pings, got {self.ping_window}")
        if not 0 <= self.reply_delay_max <= 5:
            raise ConfigError(f"reply_delay_max: must be 0-5 seconds, got {self.reply_delay_max}")
        if not 1 <= self.ttl <= 255:
            raise ConfigError(f"ttl: must be 1-255, got {self.ttl}")
        if self.addressing not in ("manual", "auto"):
            raise ConfigError(f"addressing: must be auto or manual, got {self.addressing!r}")
        if self.layers not in LAYER_MODES:
            raise ConfigError(f"layers: must be processes or threads, got {self.layers!r}")
        if self.log_level not in ("debug", "info", "warning", "error"):
            raise ConfigError(
                f"log_level: must be debug, info, warning or error, got {self.log_level!r}"
            )
        if self.log_format not in ("text", "json"):
            raise ConfigError(f"log_format: must be text or json, got {self.log_format!r}")
        self._validate_wifi()
        if self.auth is not None and self.auth not in AUTH_MODES:
            raise ConfigError(
                f"auth: must be {', '.join(AUTH_MODES[:-1])} or {AUTH_MODES[-1]}, got {self.auth!r}"
            )
        if self.ssdp_interop not in ("auto", "on", "off"):
            raise ConfigError(f"ssdp_interop: must be auto, on or off, got {self.ssdp_interop!r}")
        for threshold in self.indicator_thresholds:
            if not 0 < threshold <= 1:
                raise ConfigError(
                    f"indicator_thresholds: each must be above 0 and at most 1 (a share of "
                    f"pings answered), got {threshold}"
                )
        for host in self.api_allowed_hosts:
            if not re.fullmatch(r"[A-Za-z0-9.:\[\]_-]{1,253}", host):
                raise ConfigError(f"api_allowed_hosts: {host!r} is not a host name or address")
        for origin in self.api_allowed_origins:
            if not re.fullmatch(r"https?://[A-Za-z0-9.\[\]:_-]+(:[0-9]{1,5})?", origin):
                raise ConfigError(
                    f"api_allowed_origins: {origin!r} is not an origin such as "
                    "http://dashboard.local:8080 (scheme, host and port, no path)"
                )
        return self

    def _validate_wifi(self) -> None:
        if self.wifi not in ("auto", "off"):
            raise ConfigError(f"wifi: must be auto or off, got {self.wifi!r}")
        if self.wifi_secret is not None and self.wifi_secret_file is not None:
            raise ConfigError(
                "wifi_secret: give wifi_secret or wifi_secret_file, not both "
                "(wifi_secret_file is recommended)"
            )
        if self.wifi_secret is not None and len(self.wifi_secret.strip()) < WIFI_SECRET_MIN:
            raise ConfigError(
                f"wifi_secret: must be at least {WIFI_SECRET_MIN} characters "
                "(surrounding spaces do not count)"
            )
        if self.wifi_mode not in ("ibss", "mesh"):
            raise ConfigError(
                f"wifi_mode: must be ibss (ad-hoc) or mesh (802.11s), got {self.wifi_mode!r}"
            )
        if self.wifi_freq not in WIFI_FREQS:
            raise ConfigError(
                f"wifi_freq: {self.wifi_freq} MHz is not a 2.4 GHz (2412-2472, 2484) or "
                "5 GHz (5180-5320, 5500-5720, 5745-5885) WiFi channel's centre frequency"
            )
        if self.wifi_country is not None and not re.fullmatch(r"[A-Za-z]{2}|00", self.wifi_country):
            raise ConfigError(
                f"wifi_country: must be an ISO 3166-1 two-letter code such as DE or US "
                f"(or 00 for the world domain), got {self.wifi_country!r}"
            )


WIFI_SECRET_MIN = 8
AUTH_MODES = ("accept", "sign", "enforce")
WIFI_FREQS: frozenset[int] = frozenset(
    # 2.4 GHz channels 1-13 and 14 (Japan).
    [2407 + 5 * ch for ch in range(1, 14)]
    + [2484]
    # 5 GHz: 36-64 (UNII-1/2), 100-144 (UNII-2e), 149-177 (UNII-3/4); 20 MHz centres.
    + [5000 + 5 * ch for ch in range(36, 65, 4)]
    + [5000 + 5 * ch for ch in range(100, 145, 4)]
    + [5000 + 5 * ch for ch in range(149, 178, 4)]
)


def split_hostport(key: str, value: str) -> tuple[str, int]:
    """Split `HOST:PORT`; raise ConfigError naming `key` when it is not one."""
    host, sep, port_s = value.rpartition(":")
    if not sep or not host or not port_s.isdigit() or not 0 <= int(port_s) <= 65535:
        raise ConfigError(f"{key}: expected HOST:PORT (e.g. 127.0.0.1:8700), got {value!r}")
    host = host.strip("[]")
    try:
        ipaddress.ip_address(host)
    except ValueError:
        if host != "localhost":
            raise ConfigError(f"{key}: {host!r} is not an IP address") from None
    return host, int(port_s)


_WILDCARD_HOSTS = ("0.0.0.0", "::", "", IFACE_HOST)


def _loopback(host: str) -> bool:
    return host == "localhost" or ipaddress.ip_address(host).is_loopback


def describe_address(describe: str) -> tuple[str, int]:
    """`describe` (HOST:PORT, HOST an address or `iface`) split; ConfigError if it is not."""
    host, sep, port = describe.rpartition(":")
    if sep and host == IFACE_HOST:
        return IFACE_HOST, split_hostport("describe", f"0.0.0.0:{port}")[1]
    try:
        return split_hostport("describe", describe)
    except ConfigError as exc:
        raise ConfigError(f"{exc} (or {IFACE_HOST}: the fleet interface's address)") from None


def location_url(describe: str, address: str) -> str:
    """The LOCATION a robot announces: its description server (`describe`, HOST:PORT), on
    `address` when the server listens on the fleet interface's address or on every one."""
    host, port = describe_address(describe)
    if host in _WILDCARD_HOSTS:
        host = address or "0.0.0.0"
    return f"http://{host}:{port}/description.json"


def location_max_len(describe: str) -> int:
    """The longest LOCATION `location_url` can give whatever the robot's IPv4 address."""
    return len(location_url(describe, "255.255.255.255"))


_HELP: dict[str, str] = {
    "iface": "network interface the fleet is on (default: the one with the default route, "
    "else the first non-loopback interface that is up)",
    "fleet": "fleet id 0-255; robots of other fleets are ignored (default 1)",
    "api": f"HOST:PORT of the local REST API (default {DEFAULT_API}); it also listens on "
    "STATE_DIR/api.sock",
    "describe": f"HOST:PORT of the read-only description server other robots and SSDP clients "
    f"fetch LOCATION from; HOST {IFACE_HOST} is the fleet interface's address, followed when it "
    f"changes (default {DEFAULT_DESCRIBE}); 0.0.0.0 listens on every address",
    "state_dir": "directory of the durable state: registrations, history map (default "
    "/var/lib/sdfr as root, else $XDG_STATE_HOME/sdfr)",
    "beacon_interval": f"seconds between Alive beacons (default {BEACON_INTERVAL:g})",
    "robot_id": "this robot's identity (default: derived from the interface's MAC; the host "
    "name on an interface without one, such as lo)",
    "group": f"IPv4 multicast group (default {wire.DEFAULT_GROUP})",
    "port": f"UDP port (default {wire.DEFAULT_PORT})",
    "miss_limit": "beacon periods of silence after which a peer is unreachable "
    f"(default {MISS_LIMIT})",
    "ping_interval": "seconds between unicast pings to each reachable peer (default: the beacon "
    "interval)",
    "ping_window": f"how many recent pings the connection indicator counts (default {PING_WINDOW})",
    "reply_delay_max": "longest random delay before answering a Discovery, bounded by its MX "
    f"(default {REPLY_DELAY_MAX:g})",
    "ttl": "multicast TTL (default 1: one radio hop)",
    "addressing": "auto: take 10.<fleet>.x.y derived from the MAC, checked with ARP probes and "
    "moved on conflict (set it on robots); manual: leave the interface's addresses alone "
    "(default, so a workstation's address is never touched)",
    "log_level": "debug, info, warning or error (default info)",
    "log_format": "text: one line a record, TIME COMPONENT LEVEL MESSAGE; json: one JSON object "
    "a line (time, level, component, logger, message, and the fields of a fleet change) "
    "(default text)",
    "wifi": "auto: when IFACE is wireless and a WiFi secret is configured, join the fleet's "
    "ad-hoc WiFi (wpa_supplicant + iw) before starting; off: never touch the radio "
    "(default auto)",
    "wifi_secret": "the fleet's WiFi secret (8 characters or more), the same on every robot; "
    "prefer wifi_secret_file: a flag is visible in the process list (default: none)",
    "wifi_secret_file": "file holding the fleet's WiFi secret (make it readable by root only: "
    "chmod 600; a world-readable file is used with a warning). Without key_file it keys the "
    "fleet's datagrams too: the keyring is seeded with a key derived from it (default: none)",
    "wifi_mode": "ibss (IEEE 802.11 ad-hoc, WPA2-PSK) or mesh (802.11s, SAE) (default ibss)",
    "wifi_freq": "WiFi channel centre frequency in MHz, 2.4 or 5 GHz (default 2412, channel 1)",
    "wifi_country": "regulatory domain, ISO 3166-1 code such as DE (default: leave the system's)",
    "key_file": "file holding the fleet key (`sdfr keys generate FILE`; readable by root only): "
    "every datagram is then signed and checked. It seeds the keyring in STATE_DIR on the "
    "first start; `sdfr keys` manages the keyring after that (default: none: a key derived "
    "from the WiFi secret when one is configured, else the fleet is open)",
    "auth": "with a key: accept (send unsigned, accept both), sign (send signed, accept both) or "
    "enforce (send signed, accept signed only) -- the steps of moving a fleet to a key without "
    "a flag day. It seeds a new keyring and can raise a keyring's mode, never lower it: "
    "`sdfr keys mode` does that on the running daemon (default: the keyring's mode; enforce "
    "for a new keyring)",
    "ssdp_interop": "answer plain SSDP clients' ssdp:all searches (read-only): auto (only while "
    "the fleet has no key), on or off (default auto)",
    "api_allowed_hosts": "more names the local API may be reached by (the Host header), comma "
    "separated; 127.0.0.1, localhost, ::1 and the --api host always are. Anything else is "
    "refused: a web page cannot reach the API through a name it controls (DNS rebinding) "
    "(default: none more)",
    "indicator_thresholds": "connection indicator levels (0-1, comma separated) whose crossing "
    "is a robot.indicator event of GET /events (default 0.5,0.8)",
    "layers": "threads: the API and discovery layers are two threads of one process, each with "
    "its own event loop, each restarted on its own when it fails while the other serves; a hung "
    "one restarts the whole daemon, state kept (default: half the memory of processes); "
    "processes: they are two processes forked by sdfrd's supervisor, so that a kill -9, a "
    "segfault or a hang of one leaves the other serving",
    "api_allow_remote": "true: let --api listen on an address other machines reach (refused "
    "otherwise); needs api_token_file, whose token every request from another machine must "
    "carry (Authorization: Bearer TOKEN) (default false: the write API stays on the robot)",
    "api_token_file": "file holding the token of api_allow_remote (one line, 16 characters "
    "or more; readable by root only) (default: none)",
    "api_allowed_origins": "web origins whose pages may call the local API (e.g. "
    "http://dashboard.local:8080), comma separated; default none: a request a browser sends "
    "for another site's page is refused",
}


def option_help(name: str) -> str:
    """The help text of the option `name` (a Config field), for other commands that take it."""
    return _HELP[name]


_LISTS = ("api_allowed_hosts", "api_allowed_origins")


def _coerce(name: str, raw: Any) -> Any:
    kinds: dict[str, type] = {
        "fleet": int,
        "port": int,
        "miss_limit": int,
        "ping_window": int,
        "ttl": int,
        "beacon_interval": float,
        "ping_interval": float,
        "reply_delay_max": float,
        "wifi_freq": int,
    }
    if name in ("state_dir", "wifi_secret_file", "key_file", "api_token_file"):
        return Path(str(raw))
    if name == "api_allow_remote":
        if isinstance(raw, bool) or str(raw).lower() in ("true", "false"):
            return raw if isinstance(raw, bool) else str(raw).lower() == "true"
        raise ConfigError(f"{name}: expected true or false, got {raw!r}")
    if name == "indicator_thresholds":
        items = raw.split(",") if isinstance(raw, str) else raw
        if not isinstance(items, list | tuple):
            raise ConfigError(f"{name}: expected a list of numbers, got {raw!r}")
        try:
            if any(isinstance(i, bool) for i in items):
                raise TypeError
            return tuple(float(i) for i in items if str(i).strip())
        except (TypeError, ValueError):
            raise ConfigError(f"{name}: expected a list of numbers, got {raw!r}") from None
    if name in _LISTS:
        items = raw.split(",") if isinstance(raw, str) else raw
        if not isinstance(items, list | tuple) or not all(isinstance(i, str) for i in items):
            raise ConfigError(f"{name}: expected a list of strings, got {raw!r}")
        return tuple(i.strip() for i in items if i.strip())
    kind = kinds.get(name)
    if kind is None:
        if not isinstance(raw, str):
            raise ConfigError(f"{name}: expected a string, got {raw!r}")
        return raw
    if isinstance(raw, bool) or (kind is int and not isinstance(raw, int | str)):
        raise ConfigError(f"{name}: expected {kind.__name__}, got {raw!r}")
    try:
        return kind(raw)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected {kind.__name__}, got {raw!r}") from None


def load_toml(path: Path) -> dict[str, object]:
    from sdfr._compat import tomllib  # (only a daemon given a file pays for the parser)

    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"config: {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config: {path} is not valid TOML: {exc}") from None
    names = {f.name for f in fields(Config)}
    if "sdfrd" in data:
        table = data["sdfrd"]
        if not isinstance(table, dict):
            raise ConfigError(f"config: [sdfrd] in {path} must be a table")
        for key, value in data.items():
            if key == "sdfrd":
                continue
            if isinstance(value, dict):
                raise ConfigError(
                    f"config: unknown section [{key}] in {path}{did_you_mean(key, ['sdfrd'])}; "
                    "sdfrd reads [sdfrd] only"
                )
            raise ConfigError(
                f"config: {key!r} is at the top level of {path}, which has an [sdfrd] table: "
                f"with one, sdfrd reads only [sdfrd]; move {key!r} into it"
            )
    else:
        table = data
    out: dict[str, Any] = {}
    for key, raw in table.items():
        name = key.replace("-", "_")
        if name not in names and isinstance(raw, dict):
            hint = did_you_mean(key, ["sdfrd"]).replace("'sdfrd'", "[sdfrd]")
            raise ConfigError(
                f"config: unknown section [{key}] in {path}{hint}; sdfrd reads [sdfrd] (or "
                "keys at the top level)"
            )
        if name not in names:
            raise ConfigError(
                f"config: unknown key {key!r} in {path}{did_you_mean(name, names)}; "
                f"known keys: {', '.join(sorted(names))}"
            )
        out[name] = _coerce(name, raw)
    return out


def build_parser() -> argparse.ArgumentParser:
    # (imported here: see _plain_flags)
    from sdfr.argparsing import HintingParser

    p = HintingParser(
        prog="sdfrd",
        description="SDfR daemon: discovers the reachable robots of a fleet and their services, "
        "and serves them to local programs over a REST API.",
        epilog="Every option is also a key of the TOML file given with --config (top level or "
        "under [sdfrd], same names with - or _); flags override the file.",
    )
    p.add_argument("--config", type=Path, metavar="FILE", help="TOML config file (default: none)")
    p.add_argument("--version", action="version", version=version_text("sdfrd"))
    for f in fields(Config):
        flag = "--" + f.name.replace("_", "-")
        meta = f.name.upper()
        p.add_argument(flag, dest=f.name, default=None, metavar=meta, help=_HELP[f.name])
    return p


def _plain_flags(argv: list[str]) -> dict[str, str] | None:
    """The flags of `argv` when every one is spelled in full as `--name VALUE` or
    `--name=VALUE`, by name; else None, and argparse reads them.

    Why: argparse (and the shutil its help formatter imports) cost a running daemon 0.57 MiB
    of its ~16 (measured), for reading a handful of flags once. A service manager's command
    line is plain; help, --version, abbreviations, a value that looks like a flag and every
    mistake still go to build_parser(), the one description of the flags, so they read and
    fail the same way.
    """
    names = {"--" + f.name.replace("_", "-"): f.name for f in fields(Config)}
    names["--config"] = "config"
    out: dict[str, str] = {}
    i = 0
    while i < len(argv):
        flag, eq, value = argv[i].partition("=")
        if flag not in names:
            return None
        if not eq:
            if i + 1 == len(argv) or argv[i + 1].startswith("-"):
                return None
            i += 1
            value = argv[i]
        out[names[flag]] = value
        i += 1
    return out


def from_args(argv: list[str] | None = None) -> Config:
    """Defaults, then the TOML file, then flags; validated."""
    if argv is None:
        argv = sys.argv[1:]
    flags = _plain_flags(argv)
    if flags is None:
        args = vars(build_parser().parse_args(argv))
        flags = {name: raw for name, raw in args.items() if raw is not None}
    values: dict[str, Any] = {}
    if "config" in flags:
        values.update(load_toml(Path(flags["config"])))
    for f in fields(Config):
        if f.name in flags:
            values[f.name] = _coerce(f.name, flags[f.name])
    return replace(Config(), **values).validate()


# Never put on a command line (other users can read /proc/PID/cmdline); the layers do not
# need it: the supervisor applies the WiFi set-up itself.
_NOT_PASSED = frozenset({"wifi_secret"})


def to_args(cfg: Config) -> list[str]:
    """The flags that rebuild `cfg` (the supervisor passes them to its layers), but secrets."""
    out: list[str] = []
    for f in fields(Config):
        if f.name in _NOT_PASSED:
            continue
        value = getattr(cfg, f.name)
        if isinstance(value, tuple):
            if value:
                out += ["--" + f.name.replace("_", "-"), ",".join(str(v) for v in value)]
        elif value is not None:
            out += ["--" + f.name.replace("_", "-"), str(value)]
    return out
