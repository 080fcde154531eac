"""Daemon configuration read: defaults, TOML file and command-line flags into one validated
`Config` (its fields, the options, are in `sdfr.config.options`), and the flags that give it
back."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sdfr import version_text
from sdfr.config.options import (
    AUTH_MODES,
    DEFAULT_DESCRIBE,
    IFACE_HOST,
    LAYER_MODES,
    OPTIONS,
    WIFI_FREQS,
    WIFI_SECRET_MIN,
    Config,
    default_state_dir,
    describe_address,
    flag,
    location_max_len,
    location_url,
    option_help,
    split_hostport,
)
from sdfr.config.options import (
    kind as option_kind,
)
from sdfr.endpoints import DEFAULT_API
from sdfr.errors import ConfigError
from sdfr.hints import did_you_mean

if TYPE_CHECKING:
    import argparse

__all__ = [
    "AUTH_MODES",
    "DEFAULT_API",
    "DEFAULT_DESCRIBE",
    "IFACE_HOST",
    "LAYER_MODES",
    "OPTIONS",
    "WIFI_FREQS",
    "WIFI_SECRET_MIN",
    "Config",
    "build_parser",
    "default_state_dir",
    "describe_address",
    "flag",
    "from_args",
    "load_toml",
    "location_max_len",
    "location_url",
    "option_flags",
    "option_help",
    "options_config",
    "split_hostport",
    "to_args",
]


def option_flags(options: Mapping[str, Any]) -> list[str]:
    """The flags that give sdfrd `options` (by name; None and an empty list are left out)."""
    out: list[str] = []
    for name, value in options.items():
        if isinstance(value, tuple | list):
            if value:
                out += [flag(name), ",".join(str(v) for v in value)]
        elif value is not None:
            out += [flag(name), str(value)]
    return out


def options_config(options: Mapping[str, Any]) -> Config:
    """The validated Config that sdfrd given `options` (by name, as flags or TOML values; None
    is not given) would run with; ConfigError names a mistyped option with the closest one."""
    values: dict[str, Any] = {}
    for name, raw in options.items():
        if name not in OPTIONS:
            hint = did_you_mean(name, OPTIONS) or f" (options: {', '.join(OPTIONS)})"
            raise ConfigError(f"{name}: not an sdfrd option{hint}")
        if raw is not None:
            values[name] = _coerce(name, raw)
    return replace(Config(), **values).validate()


_SCALARS: dict[str, type] = {"int": int, "float": float}


def _coerce(name: str, raw: Any) -> Any:
    kind = option_kind(name)
    if kind == "path":
        return Path(str(raw))
    if kind == "bool":
        if isinstance(raw, bool) or str(raw).lower() in ("true", "false"):
            return raw if isinstance(raw, bool) else str(raw).lower() == "true"
        raise ConfigError(f"{name}: expected true or false, got {raw!r}")
    if kind == "numbers":
        items = raw.split(",") if isinstance(raw, str) else raw
        if not isinstance(items, list | tuple):
            raise ConfigError(f"{name}: expected a list of numbers, got {raw!r}")
        try:
            if any(isinstance(i, bool) for i in items):
                raise TypeError
            return tuple(float(i) for i in items if str(i).strip())
        except (TypeError, ValueError):
            raise ConfigError(f"{name}: expected a list of numbers, got {raw!r}") from None
    if kind == "names":
        items = raw.split(",") if isinstance(raw, str) else raw
        if not isinstance(items, list | tuple) or not all(isinstance(i, str) for i in items):
            raise ConfigError(f"{name}: expected a list of strings, got {raw!r}")
        return tuple(i.strip() for i in items if i.strip())
    scalar = _SCALARS.get(kind)
    if scalar is None:
        if not isinstance(raw, str):
            raise ConfigError(f"{name}: expected a string, got {raw!r}")
        return raw
    if isinstance(raw, bool) or (scalar is int and not isinstance(raw, int | str)):
        raise ConfigError(f"{name}: expected {scalar.__name__}, got {raw!r}")
    try:
        return scalar(raw)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected {scalar.__name__}, got {raw!r}") from None


def load_toml(path: Path) -> dict[str, object]:
    from sdfr._compat import tomllib  # (only a daemon given a file pays for the parser)

    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"config: {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config: {path} is not valid TOML: {exc}") from None
    names = OPTIONS
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
    for name in OPTIONS:
        p.add_argument(
            flag(name), dest=name, default=None, metavar=name.upper(), help=option_help(name)
        )
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
    names = {flag(name): name for name in OPTIONS}
    names["--config"] = "config"
    out: dict[str, str] = {}
    i = 0
    while i < len(argv):
        given, eq, value = argv[i].partition("=")
        if given not in names:
            return None
        if not eq:
            if i + 1 == len(argv) or argv[i + 1].startswith("-"):
                return None
            i += 1
            value = argv[i]
        out[names[given]] = value
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
    for name in OPTIONS:
        if name in flags:
            values[name] = _coerce(name, flags[name])
    return replace(Config(), **values).validate()


def to_args(cfg: Config) -> list[str]:
    """The flags that rebuild `cfg` (the supervisor passes them to its layers), but the
    options marked not `passed`: secrets, never put on a command line (other users can read
    /proc/PID/cmdline); the layers do not need them (the supervisor applies the WiFi set-up)."""
    passed = [f.name for f in OPTIONS.values() if f.metadata["passed"]]
    return option_flags({name: getattr(cfg, name) for name in passed})
