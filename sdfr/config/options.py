"""sdfrd's options: `Config`, one field an option, with its default, help text and how its
value is read (`option`); its validation; the addresses it names.  The flags, the TOML keys,
`config.to_args` and netlab's checks of a robot's options all follow from these fields."""

from __future__ import annotations

import ipaddress
import os
import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from sdfr import wire
from sdfr.endpoints import DEFAULT_API
from sdfr.errors import ConfigError
from sdfr.protocol import (
    BEACON_INTERVAL,
    MISS_LIMIT,
    PING_WINDOW,
    REPLY_DELAY_MAX,
    CoreConfig,
)
from sdfr.records.model import ROBOT_ID_RE

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


#: How an option's value is read from a flag or a TOML value (`sdfr.config.load`), by the type
#: of its field (``| None`` aside).
KINDS = {
    "str": "str",
    "int": "int",
    "float": "float",
    "bool": "bool",
    "Path": "path",
    "tuple[float, ...]": "numbers",
    "tuple[str, ...]": "names",
}


def option(text: str, *, passed: bool = True) -> dict[str, Any]:
    """The metadata of a `Config` field that is an sdfrd option: its help `text`, and whether
    `to_args` passes it on to the layers (`passed`).  Its name, type and default are the
    field's; the flag, the TOML key, how a value is read, `to_args` and netlab's checks all
    follow from these."""
    return {"help": text, "passed": passed}


@dataclass(frozen=True, slots=True)
class Config:
    """Everything `sdfrd` can be told; every field is a flag and a TOML key of the same name."""

    iface: str | None = field(
        default=None,
        metadata=option(
            "network interface the fleet is on (default: the one with the default route, "
            "else the first non-loopback interface that is up)"
        ),
    )
    fleet: int = field(
        default=1,
        metadata=option("fleet id 0-255; robots of other fleets are ignored (default 1)"),
    )
    api: str = field(
        default=DEFAULT_API,
        metadata=option(
            f"HOST:PORT of the local REST API (default {DEFAULT_API}); it also listens on "
            "STATE_DIR/api.sock"
        ),
    )
    describe: str = field(
        default=DEFAULT_DESCRIBE,
        metadata=option(
            "HOST:PORT of the read-only description server other robots and SSDP clients fetch "
            f"LOCATION from; HOST {IFACE_HOST} is the fleet interface's address, followed when it "
            f"changes (default {DEFAULT_DESCRIBE}); 0.0.0.0 listens on every address"
        ),
    )
    state_dir: Path = field(
        default_factory=default_state_dir,
        metadata=option(
            "directory of the durable state: registrations, history map (default "
            "/var/lib/sdfr as root, else $XDG_STATE_HOME/sdfr)"
        ),
    )
    beacon_interval: float = field(
        default=BEACON_INTERVAL,
        metadata=option(f"seconds between Alive beacons (default {BEACON_INTERVAL:g})"),
    )
    robot_id: str | None = field(
        default=None,
        metadata=option(
            "this robot's identity (default: derived from the interface's MAC; the host "
            "name on an interface without one, such as lo)"
        ),
    )
    group: str = field(
        default=wire.DEFAULT_GROUP,
        metadata=option(f"IPv4 multicast group (default {wire.DEFAULT_GROUP})"),
    )
    port: int = field(
        default=wire.DEFAULT_PORT,
        metadata=option(f"UDP port (default {wire.DEFAULT_PORT})"),
    )
    miss_limit: int = field(
        default=MISS_LIMIT,
        metadata=option(
            f"beacon periods of silence after which a peer is unreachable (default {MISS_LIMIT})"
        ),
    )
    ping_interval: float | None = field(
        default=None,
        metadata=option(
            "seconds between unicast pings to each reachable peer (default: the beacon interval)"
        ),
    )
    ping_window: int = field(
        default=PING_WINDOW,
        metadata=option(
            f"how many recent pings the connection indicator counts (default {PING_WINDOW})"
        ),
    )
    reply_delay_max: float = field(
        default=REPLY_DELAY_MAX,
        metadata=option(
            "longest random delay before answering a Discovery, bounded by its MX "
            f"(default {REPLY_DELAY_MAX:g})"
        ),
    )
    ttl: int = field(
        default=1,
        metadata=option("multicast TTL (default 1: one radio hop)"),
    )
    addressing: str = field(
        default="manual",
        metadata=option(
            "auto: take 10.<fleet>.x.y derived from the MAC, checked with ARP probes and "
            "moved on conflict (set it on robots); manual: leave the interface's addresses alone "
            "(default, so a workstation's address is never touched)"
        ),
    )
    log_level: str = field(
        default="info",
        metadata=option("debug, info, warning or error (default info)"),
    )
    log_format: str = field(
        default="text",
        metadata=option(
            "text: one line a record, TIME COMPONENT LEVEL MESSAGE; json: one JSON object "
            "a line (time, level, component, logger, message, and the fields of a fleet change) "
            "(default text)"
        ),
    )
    wifi: str = field(
        default="auto",
        metadata=option(
            "auto: when IFACE is wireless and a WiFi secret is configured, join the fleet's "
            "ad-hoc WiFi (wpa_supplicant + iw) before starting; off: never touch the radio "
            "(default auto)"
        ),
    )
    wifi_secret: str | None = field(
        default=None,
        repr=False,
        metadata=option(
            "the fleet's WiFi secret (8 characters or more), the same on every robot; "
            "prefer wifi_secret_file: a flag is visible in the process list (default: none)",
            passed=False,
        ),
    )
    wifi_secret_file: Path | None = field(
        default=None,
        metadata=option(
            "file holding the fleet's WiFi secret (make it readable by root only: chmod 600; a "
            "world-readable file is used with a warning). Without key_file it keys the fleet's "
            "datagrams too: the keyring is seeded with a key derived from it (default: none)"
        ),
    )
    wifi_mode: str = field(
        default="ibss",
        metadata=option(
            "ibss (IEEE 802.11 ad-hoc, WPA2-PSK) or mesh (802.11s, SAE) (default ibss)"
        ),
    )
    wifi_freq: int = field(
        default=2412,
        metadata=option(
            "WiFi channel centre frequency in MHz, 2.4 or 5 GHz (default 2412, channel 1)"
        ),
    )
    wifi_country: str | None = field(
        default=None,
        metadata=option(
            "regulatory domain, ISO 3166-1 code such as DE (default: leave the system's)"
        ),
    )
    key_file: Path | None = field(
        default=None,
        metadata=option(
            "file holding the fleet key (`sdfr keys generate FILE`; readable by root only): "
            "every datagram is then signed and checked. It seeds the keyring in STATE_DIR on the "
            "first start; `sdfr keys` manages the keyring after that (default: none: a key derived "
            "from the WiFi secret when one is configured, else the fleet is open)"
        ),
    )
    auth: str | None = field(
        default=None,
        metadata=option(
            "with a key: accept (send unsigned, accept both), sign (send signed, accept both) or "
            "enforce (send signed, accept signed only) -- the steps of moving a fleet to a key "
            "without a flag day. It seeds a new keyring and can raise a keyring's mode, never "
            "lower it: `sdfr keys mode` does that on the running daemon (default: the keyring's "
            "mode; enforce for a new keyring)"
        ),
    )
    ssdp_interop: str = field(
        default="auto",
        metadata=option(
            "answer plain SSDP clients' ssdp:all searches (read-only): auto (only while "
            "the fleet has no key), on or off (default auto)"
        ),
    )
    api_allowed_hosts: tuple[str, ...] = field(
        default=(),
        metadata=option(
            "more names the local API may be reached by (the Host header), comma "
            "separated; 127.0.0.1, localhost, ::1 and the --api host always are. Anything else is "
            "refused: a web page cannot reach the API through a name it controls (DNS rebinding) "
            "(default: none more)"
        ),
    )
    api_allowed_origins: tuple[str, ...] = field(
        default=(),
        metadata=option(
            "web origins whose pages may call the local API (e.g. http://dashboard.local:8080), "
            "comma separated; default none: a request a browser sends for another site's page is "
            "refused"
        ),
    )
    api_allow_remote: bool = field(
        default=False,
        metadata=option(
            "true: let --api listen on an address other machines reach (refused "
            "otherwise); needs api_token_file, whose token every request from another machine must "
            "carry (Authorization: Bearer TOKEN) (default false: the write API stays on the robot)"
        ),
    )
    api_token_file: Path | None = field(
        default=None,
        metadata=option(
            "file holding the token of api_allow_remote (one line, 16 characters "
            "or more; readable by root only) (default: none)"
        ),
    )
    indicator_thresholds: tuple[float, ...] = field(
        default=(0.5, 0.8),
        metadata=option(
            "connection indicator levels (0-1, comma separated) whose crossing "
            "is a robot.indicator event of GET /events (default 0.5,0.8)"
        ),
    )
    layers: str = field(
        default="threads",
        metadata=option(
            "threads: the API and discovery layers are two threads of one process, each with its "
            "own event loop, each restarted on its own when it fails while the other serves; a "
            "hung one restarts the whole daemon, state kept (default: half the memory of "
            "processes); processes: they are two processes forked by sdfrd's supervisor, so that "
            "a kill -9, a segfault or a hang of one leaves the other serving"
        ),
    )

    @property
    def ssdp_interop_wanted(self) -> bool | None:
        """`ssdp_interop` as the protocol takes it: on True, off False, auto None."""
        return {"on": True, "off": False}.get(self.ssdp_interop)

    @property
    def wifi_wanted(self) -> bool:
        """sdfrd joins the fleet's WiFi if its interface is wireless: wifi is not off and a
        secret is configured (`sdfr.host.wifi.setup`, `sdfr.host.wifiwatch.watch_for`)."""
        has_secret = self.wifi_secret is not None or self.wifi_secret_file is not None
        return self.wifi != "off" and has_secret

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


#: The options by name: the fields of Config and their metadata (see `option`).
OPTIONS = {f.name: f for f in fields(Config)}


def flag(name: str) -> str:
    """The command-line flag of option `name` (beacon_interval: --beacon-interval)."""
    return "--" + name.replace("_", "-")


def kind(name: str) -> str:
    """How option `name`'s value is read (a value of KINDS), by its field's type."""
    return KINDS[str(OPTIONS[name].type).removesuffix(" | None")]


def option_help(name: str) -> str:
    """The help text of the option `name` (a Config field), for other commands that take it."""
    return str(OPTIONS[name].metadata["help"])
