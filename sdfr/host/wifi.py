"""Joining the fleet's ad-hoc WiFi: IBSS (WPA2-PSK) or 802.11s mesh (SAE), via wpa_supplicant.

Planning has no I/O: `plan(cfg)` turns the configuration into a `WifiPlan` (SSID, key,
wpa_supplicant configuration text, command lines). `apply(plan)` writes the configuration
file and runs the commands. `setup(cfg)` is what `sdfrd` does at start.

Derivation (the same on every robot of a fleet, so nothing but the secret is shared):

- SSID (the mesh id in mesh mode): ``sdfr-fleet-<fleet id>``, e.g. ``sdfr-fleet-7``; fleets
  with different ids share the air on separate networks.
- key: ``PBKDF2-HMAC-SHA256(password=secret (UTF-8, surrounding whitespace removed),
  salt="sdfr-fleet-<fleet id>", iterations=100000, length=32 bytes)``, written as 64
  lowercase hex digits. In IBSS mode it is the raw WPA2 PSK (``psk=<hex>``, no further
  hashing by wpa_supplicant); in mesh mode the 64 hex digits are the SAE password. The
  same secret gives a different key in another fleet.
- datagram key (`datagram_key`, used when no ``key_file`` is configured): ``HKDF-SHA256``
  (RFC 5869) with the key above as input keying material (its 32 bytes), salt
  ``"sdfr-fleet-<fleet id>"`` and info ``"SDfR datagram key v1"``, 32 bytes: one secret
  protects the link and discovery. The input is the stretched key, never the bare secret, so a
  captured sealed datagram lets nobody test guesses of the secret faster than a captured WPA2
  handshake does; and the datagram key (stored in every robot's keyring) does not give the
  WiFi key.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import logging
import os
import shlex
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from sdfr.config.keystore import KeySource
from sdfr.config.load import WIFI_SECRET_MIN, Config
from sdfr.errors import ConfigError, SdfrError

log = logging.getLogger("sdfr.host.wifi")

SSID_PREFIX = "sdfr-fleet-"
KDF_ITERATIONS = 100_000
#: HKDF's info for the datagram key: a key for nothing else (RFC 5869 section 3.2).
DATAGRAM_KEY_INFO = b"SDfR datagram key v1"
_HASH_LEN = 32  # SHA-256
MASK = "*" * 16
_SYS_NET = Path("/sys/class/net")

#: 802.11s peering's timers, for robots' slow or busy CPUs and crowded air. wpa_supplicant's
#: defaults wait 40 ms for a peer's Confirm (re-sending the Open twice, then closing the link
#: and holding), and a peer whose SAE failed three times is blocked for `mesh_max_inactivity`
#: (300 s). A peer a moment slow to answer (an SAE exchange is a few elliptic-curve operations
#: each way) then stays unpeered for minutes. 1 s for a Confirm costs only when a frame is lost
#: (a retry comes later); a block of 60 s lets a robot that failed try again within a minute.
MESH_TIMERS = {
    "dot11MeshRetryTimeout": 1000,
    "dot11MeshConfirmTimeout": 1000,
    "dot11MeshMaxRetries": 3,
}
MESH_MAX_INACTIVITY = 60

# Where each program comes from on Debian, for the "not installed" message.
PACKAGES = {"ip": "iproute2", "iw": "iw", "wpa_supplicant": "wpasupplicant"}

Runner = Callable[..., "subprocess.CompletedProcess[str]"]


def ssid_for(fleet: int) -> str:
    return f"{SSID_PREFIX}{fleet}"


def bssid_for(fleet: int) -> str:
    """The fleet's IBSS cell id: a locally administered unicast MAC from the SSID's hash.
    Robots that start at once would otherwise each found a cell of their own, and IBSS cells
    merge slowly, if at all: with one fixed cell they all join the same one."""
    raw = bytearray(hashlib.sha256(ssid_for(fleet).encode()).digest()[:6])
    raw[0] = (raw[0] & 0xFC) | 0x02
    return ":".join(f"{b:02x}" for b in raw)


def derive_key(secret: str, fleet: int) -> str:
    """64 hex digits from the fleet secret and the fleet id (see the module's docstring)."""
    secret = secret.strip()
    if not secret:
        raise ConfigError("wifi_secret: is empty")
    return _stretched(secret, fleet)


@functools.lru_cache(maxsize=1)
def _stretched(secret: str, fleet: int) -> str:
    # A first start stretches the secret twice (the keyring's datagram key, then the WiFi
    # plan): 100,000 rounds of pure-Python HMAC each, seconds on a slow CPU. Once is enough.
    salt = ssid_for(fleet).encode("ascii")
    return pbkdf2_sha256(secret.encode("utf-8"), salt, KDF_ITERATIONS).hex()


def pbkdf2_sha256(password: bytes, salt: bytes, rounds: int) -> bytes:
    """PBKDF2-HMAC-SHA256, 32 bytes: OpenSSL's through hashlib when it is loaded; else
    (sdfrd keeps OpenSSL out of its processes, see sdfr.daemon) RFC 8018's single block
    with CPython's own SHA-256, about half a second for KDF_ITERATIONS, once at start."""
    if "_hashlib" in sys.modules and sys.modules["_hashlib"] is not None:
        return hashlib.pbkdf2_hmac("sha256", password, salt, rounds, 32)
    if len(password) > 64:
        password = hashlib.sha256(password).digest()
    key = password.ljust(64, b"\0")
    inner = hashlib.sha256(bytes(b ^ 0x36 for b in key))
    outer = hashlib.sha256(bytes(b ^ 0x5C for b in key))

    def prf(data: bytes) -> bytes:
        i, o = inner.copy(), outer.copy()
        i.update(data)
        o.update(i.digest())
        return o.digest()

    u = prf(salt + b"\0\0\0\1")
    acc = int.from_bytes(u, "big")
    for _ in range(rounds - 1):
        u = prf(u)
        acc ^= int.from_bytes(u, "big")
    return acc.to_bytes(32, "big")


def hkdf_extract(salt: bytes, ikm: bytes) -> bytes:
    """HKDF-Extract with SHA-256 (RFC 5869 section 2.2): the pseudorandom key; no salt is
    a string of zeros."""
    return hmac.new(salt or bytes(_HASH_LEN), ikm, hashlib.sha256).digest()


def hkdf_expand(prk: bytes, info: bytes, length: int) -> bytes:
    """HKDF-Expand with SHA-256 (RFC 5869 section 2.3): `length` bytes, 1 to 255 * 32."""
    if not 0 < length <= 255 * _HASH_LEN:
        raise ValueError(f"HKDF-SHA256 gives 1 to {255 * _HASH_LEN} bytes, not {length}")
    out = b""
    block = b""
    for counter in range(1, -(-length // _HASH_LEN) + 1):
        block = hmac.new(prk, block + info + bytes((counter,)), hashlib.sha256).digest()
        out += block
    return out[:length]


def hkdf_sha256(ikm: bytes, salt: bytes, info: bytes, length: int) -> bytes:
    """HKDF-SHA256 (RFC 5869): extract, then expand."""
    return hkdf_expand(hkdf_extract(salt, ikm), info, length)


def datagram_key(secret: str, fleet: int) -> bytes:
    """The fleet's datagram key from its WiFi secret (see the module's docstring)."""
    stretched = bytes.fromhex(derive_key(secret, fleet))
    return hkdf_sha256(stretched, ssid_for(fleet).encode("ascii"), DATAGRAM_KEY_INFO, _HASH_LEN)


def datagram_key_source(cfg: Config) -> KeySource | None:
    """Where a fleet with a WiFi secret and no key_file gets its datagram key: derived from
    the secret when the keyring is seeded (the secret is read then, and only then); None
    without a secret."""
    if cfg.wifi_secret is None and cfg.wifi_secret_file is None:
        return None
    where = "wifi_secret" if cfg.wifi_secret_file is None else str(cfg.wifi_secret_file)

    def make() -> bytes:
        secret, _ = load_secret(cfg)  # (its warnings are setup's to give)
        assert secret is not None
        return datagram_key(secret, cfg.fleet)

    return KeySource(f"the WiFi secret ({where})", make)


@dataclass(frozen=True, slots=True)
class WifiPlan:
    """Everything that joining the fleet's WiFi does, computed without touching the machine."""

    iface: str
    fleet: int
    mode: str  # "ibss" or "mesh"
    ssid: str
    frequency: int
    country: str | None
    config_path: Path
    pid_path: Path
    #: wpa_supplicant's control sockets: in sdfrd's state directory, not the shared
    #: /run/wpa_supplicant, where another manager's (or another robot's, in a lab) would clash
    ctrl_dir: Path
    key: str = field(repr=False)
    config_text: str = field(repr=False)
    commands: tuple[tuple[str, ...], ...]

    def config_shown(self, show_key: bool = False) -> str:
        """The configuration file's text, the key masked unless `show_key`."""
        return self.config_text if show_key else self.config_text.replace(self.key, MASK)

    def command_lines(self) -> list[str]:
        return [shlex.join(argv) for argv in self.commands]

    def to_json(self, show_key: bool = False) -> dict[str, object]:
        return {
            "iface": self.iface,
            "fleet": self.fleet,
            "mode": self.mode,
            "ssid": self.ssid,
            "frequency": self.frequency,
            "country": self.country,
            "key": self.key if show_key else None,
            "key_derivation": key_derivation_text(self.fleet),
            "config_path": str(self.config_path),
            "config_mode": "0600",
            "config": self.config_shown(show_key),
            "stop_previous": str(self.pid_path),
            "commands": [list(argv) for argv in self.commands],
        }

    def describe(self, show_key: bool = False) -> str:
        """What `apply` does, for humans: the file it writes and the commands it runs."""
        key_note = "" if show_key else " (key masked; --show-key prints it)"
        lines = [
            f"# WiFi set-up of fleet {self.fleet} on {self.iface}: "
            f"{'IBSS ad-hoc, WPA2-PSK' if self.mode == 'ibss' else '802.11s mesh, SAE'}, "
            f"{self.frequency} MHz",
            f"# ssid: {self.ssid}",
            f"# key: {key_derivation_text(self.fleet)}",
            f"# 1. write {self.config_path} (mode 0600){key_note}:",
            f"# ---- {self.config_path.name} ----",
            *self.config_shown(show_key).splitlines(),
            f"# ---- end of {self.config_path.name} ----",
            f"# 2. stop the wpa_supplicant whose pid is in {self.pid_path}, if it still runs",
            "# 3. run:",
            *self.command_lines(),
            f"# its state: wpa_cli -p {self.ctrl_dir} -i {self.iface} status",
        ]
        return "\n".join(lines)


def key_derivation_text(fleet: int) -> str:
    return (
        f'PBKDF2-HMAC-SHA256(secret, salt "{ssid_for(fleet)}", {KDF_ITERATIONS} iterations) '
        "as 64 hex digits"
    )


def supplicant_config(
    mode: str,
    ssid: str,
    frequency: int,
    key: str,
    country: str | None = None,
    ctrl_dir: Path = Path("/var/lib/sdfr/wpa_supplicant"),
    bssid: str | None = None,
) -> str:
    """The wpa_supplicant configuration text for the fleet's network."""
    head = [
        "# Generated by sdfr from sdfrd's configuration (wifi_* keys); rewritten at every start.",
        f"ctrl_interface={ctrl_dir}",
    ]
    if country is not None:
        head.append(f"country={country.upper()}")
    if mode == "ibss":
        head.append("ap_scan=2")
        net = [
            f'ssid="{ssid}"',
            "mode=1",
            *([f"bssid={bssid}"] if bssid is not None else []),
            f"frequency={frequency}",
            "proto=RSN",
            "key_mgmt=WPA-PSK",
            "pairwise=CCMP",
            "group=CCMP",
            f"psk={key}",
        ]
    elif mode == "mesh":
        head.append(f"mesh_max_inactivity={MESH_MAX_INACTIVITY}")
        net = [
            f'ssid="{ssid}"',
            "mode=5",
            f"frequency={frequency}",
            "key_mgmt=SAE",
            f'sae_password="{key}"',
            *(f"{name}={value}" for name, value in MESH_TIMERS.items()),
        ]
    else:
        raise ConfigError(f"wifi_mode: must be ibss or mesh, got {mode!r}")
    return "\n".join([*head, "", "network={", *(f"\t{line}" for line in net), "}", ""])


def plan(cfg: Config, secret: str | None = None) -> WifiPlan:
    """The WiFi set-up for `cfg` (iface resolved); `secret` defaults to cfg.wifi_secret."""
    if cfg.iface is None:
        raise ConfigError("iface: the WiFi set-up needs an interface; pass --iface")
    secret = secret if secret is not None else cfg.wifi_secret
    if secret is None:
        raise ConfigError(
            "wifi_secret: no WiFi secret configured; set wifi_secret_file (recommended) "
            "or wifi_secret"
        )
    iface = cfg.iface
    ssid = ssid_for(cfg.fleet)
    key = derive_key(secret, cfg.fleet)
    country = cfg.wifi_country.upper() if cfg.wifi_country is not None else None
    config_path = cfg.state_dir / f"wpa_supplicant-{iface}.conf"
    pid_path = cfg.state_dir / f"wpa_supplicant-{iface}.pid"
    ctrl_dir = cfg.state_dir / "wpa_supplicant"
    iftype = ("set", "type", "ibss") if cfg.wifi_mode == "ibss" else ("set", "type", "mesh")
    commands: list[tuple[str, ...]] = []
    if country is not None:
        commands.append(("iw", "reg", "set", country))
    commands += [
        ("ip", "link", "set", iface, "down"),
        ("iw", "dev", iface, *iftype),
        ("ip", "link", "set", iface, "up"),
        (
            "wpa_supplicant",
            "-B",
            "-D",
            "nl80211",
            "-i",
            iface,
            "-c",
            str(config_path),
            "-P",
            str(pid_path),
        ),
    ]
    return WifiPlan(
        iface=iface,
        fleet=cfg.fleet,
        mode=cfg.wifi_mode,
        ssid=ssid,
        frequency=cfg.wifi_freq,
        country=country,
        config_path=config_path,
        pid_path=pid_path,
        ctrl_dir=ctrl_dir,
        key=key,
        config_text=supplicant_config(
            cfg.wifi_mode, ssid, cfg.wifi_freq, key, country, ctrl_dir, bssid_for(cfg.fleet)
        ),
        commands=tuple(commands),
    )


# -- I/O ---------------------------------------------------------------------------------------


def is_wireless(iface: str, sys_net: Path | None = None) -> bool:
    """Whether the kernel calls `iface` a WiFi interface (cfg80211 / wireless extensions)."""
    base = (sys_net if sys_net is not None else _SYS_NET) / iface
    return (base / "wireless").exists() or (base / "phy80211").exists()


def load_secret(cfg: Config) -> tuple[str | None, list[str]]:
    """The configured secret (wifi_secret, else wifi_secret_file's content) and warnings."""
    if cfg.wifi_secret is not None:
        return cfg.wifi_secret, []
    path = cfg.wifi_secret_file
    if path is None:
        return None, []
    warnings: list[str] = []
    try:
        mode = path.stat().st_mode
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"wifi_secret_file: {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"wifi_secret_file: cannot read {path}: {exc}") from None
    if mode & stat.S_IROTH:
        warnings.append(
            f"wifi_secret_file: {path} is readable by every user (mode "
            f"{stat.S_IMODE(mode):04o}); make it readable by root only: chmod 600 {path}"
        )
    if len(text.strip()) < WIFI_SECRET_MIN:
        raise ConfigError(
            f"wifi_secret_file: the secret in {path} must be at least {WIFI_SECRET_MIN} "
            "characters (surrounding whitespace does not count)"
        )
    return text, warnings


def _write_private(path: Path, text: str) -> None:
    """Write `text` to `path` with mode 0600 from the first byte, atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.fchmod(fd, 0o600)  # whatever the umask
        os.write(fd, text.encode("utf-8"))
    finally:
        os.close(fd)
    tmp.replace(path)


def _stop_previous(pid_path: Path, timeout: float = 3.0) -> int | None:
    """Stop the wpa_supplicant we started last time on this interface, if it still runs."""
    try:
        pid = int(pid_path.read_text().strip())
    except (OSError, ValueError):
        return None
    try:
        comm = Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        comm = ""
    if comm != "wpa_supplicant":  # gone, or the pid was reused: leave it alone
        pid_path.unlink(missing_ok=True)
        return None
    try:
        os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        return None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and Path(f"/proc/{pid}").exists():
        time.sleep(0.05)
    pid_path.unlink(missing_ok=True)
    return pid


def _hint(argv: Sequence[str], plan: WifiPlan) -> str:
    prog = argv[0]
    if prog == "iw" and argv[1] == "reg":
        return "check wifi_country is a valid regulatory domain (`iw reg get`)"
    if prog == "iw":
        kind = "IBSS" if plan.mode == "ibss" else "mesh point"
        return (
            f"check that {plan.iface}'s driver supports {kind} "
            "(`iw list`: Supported interface modes) and that nothing else manages it "
            f"(NetworkManager: `nmcli device set {plan.iface} managed no`)"
        )
    if prog == "ip":
        return f"check that {plan.iface} exists (`ip link`) and is not blocked (`rfkill list`)"
    return (
        f"check that no other wpa_supplicant or NetworkManager manages {plan.iface} "
        f"(`systemctl stop wpa_supplicant`; `nmcli device set {plan.iface} managed no`), that "
        f"{plan.frequency} MHz is allowed for {plan.mode} here (`iw reg get`, `iw list`), and "
        "that this wpa_supplicant supports it (mesh needs CONFIG_MESH and SAE, 2.7 or later); "
        f"try `{shlex.join(argv)} -d` without -B to see why"
    )


def apply(plan: WifiPlan, runner: Runner | None = None, timeout: float = 30.0) -> None:
    """Write the configuration file (0600) and run the plan's commands, in order.

    `runner` is called like subprocess.run (the default). A failure raises SdfrError naming
    the command and what to check. Needs root.
    """
    run = runner if runner is not None else subprocess.run
    try:
        _write_private(plan.config_path, plan.config_text)
    except OSError as exc:
        raise SdfrError(f"wifi: cannot write {plan.config_path}: {exc}") from None
    stopped = _stop_previous(plan.pid_path)
    if stopped is not None:
        log.info("stopped the previous wpa_supplicant on %s (pid %d)", plan.iface, stopped)
    for argv in plan.commands:
        line = shlex.join(argv)
        try:
            done = run(list(argv), capture_output=True, text=True, timeout=timeout, check=False)
        except FileNotFoundError:
            package = PACKAGES.get(argv[0], argv[0])
            raise SdfrError(
                f"wifi: `{argv[0]}` is not installed (needed for `{line}`); "
                f"on Debian: apt install {package}"
            ) from None
        except subprocess.TimeoutExpired:
            raise SdfrError(f"wifi: `{line}` did not finish in {timeout:.0f} s") from None
        except PermissionError as exc:
            raise SdfrError(f"wifi: cannot run `{line}`: {exc}") from None
        if done.returncode != 0:
            why = said(done.stdout, done.stderr)
            if "not permitted" in why.lower() or "permission denied" in why.lower():
                raise SdfrError(f"wifi: `{line}` failed{why}; the WiFi set-up needs root")
            raise SdfrError(
                f"wifi: `{line}` failed (exit {done.returncode}){why}; {_hint(argv, plan)}"
            )
        log.debug("wifi: ran %s", line)


#: Lines a failing tool prints that say nothing of why (wpa_supplicant's tear-down).
_NOISE = ("nl80211: deinit", "Successfully initialized wpa_supplicant", "CTRL-EVENT-")


def said(stdout: str | None, stderr: str | None, most: int = 4) -> str:
    """ ": what a failed command said", its last `most` lines that mean something, or ""."""
    lines = [
        line.strip()
        for line in f"{stdout or ''}\n{stderr or ''}".splitlines()
        if line.strip() and not any(noise in line for noise in _NOISE)
    ]
    return f": {' / '.join(lines[-most:])}" if lines else ""


def check_root(geteuid: Callable[[], int] | None = None) -> None:
    if (geteuid or os.geteuid)() != 0:
        raise SdfrError(
            "wifi: changing the interface's mode and starting wpa_supplicant needs root "
            "(run as root, or use --dry-run to see what would be done)"
        )


def setup(
    cfg: Config,
    runner: Runner | None = None,
    sys_net: Path | None = None,
    geteuid: Callable[[], int] | None = None,
) -> WifiPlan | None:
    """What `sdfrd` does at start: apply the plan when wifi=auto, the interface is wireless and
    a secret is configured; otherwise leave the radio alone. Returns the applied plan."""
    if cfg.iface is None:
        raise ConfigError("iface: the WiFi set-up needs an interface; pass --iface")
    if cfg.wifi == "off":
        log.debug("wifi = off: the radio is left alone")
        return None
    if not is_wireless(cfg.iface, sys_net):
        log.debug("%s is not a wireless interface: no WiFi set-up", cfg.iface)
        return None
    secret, warnings = load_secret(cfg)
    for warning in warnings:
        log.warning("%s", warning)
    if secret is None:
        log.info(
            "%s is wireless but no wifi_secret/wifi_secret_file is configured: "
            "its WiFi settings are left as they are",
            cfg.iface,
        )
        return None
    the_plan = plan(cfg, secret)
    check_root(geteuid)
    apply(the_plan, runner)
    log.info(
        "wifi: %s joins %s (%s, %d MHz) with wpa_supplicant (config %s, pid file %s)",
        the_plan.iface,
        the_plan.ssid,
        the_plan.mode,
        the_plan.frequency,
        the_plan.config_path,
        the_plan.pid_path,
    )
    return the_plan
