"""The `sdfr` actions that do not talk to sdfrd: `wifi-config` (from sdfrd's configuration) and
`example` (files installed with the package)."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from importlib import resources

from sdfr.cli.args import WIFI_CONFIG_OPTIONS
from sdfr.config.load import from_args, option_flags
from sdfr.errors import ConfigError, SdfrError
from sdfr.host import netif, wifi


def example_text(name: str) -> str:
    """A file installed with the package (sdfr/deploy/NAME)."""
    return (resources.files("sdfr") / "deploy" / name).read_text()


def wifi_config(args: argparse.Namespace) -> int:
    """`sdfr wifi-config`: plan from sdfrd's configuration; print it; apply unless --dry-run."""
    as_json = getattr(args, "json", False)
    sdfrd_argv: list[str] = [] if args.config is None else ["--config", str(args.config)]
    sdfrd_argv += option_flags({name: getattr(args, name, None) for name in WIFI_CONFIG_OPTIONS})
    try:
        cfg = from_args(sdfrd_argv)
        cfg = replace(cfg, iface=cfg.iface or netif.default_iface())
        assert cfg.iface is not None
        secret, warnings = wifi.load_secret(cfg)
        the_plan = wifi.plan(cfg, secret)
    except ConfigError as exc:
        print(f"sdfr: {exc}", file=sys.stderr)
        return 2
    for warning in warnings:
        print(f"sdfr: warning: {warning}", file=sys.stderr)
    wireless = wifi.is_wireless(cfg.iface)
    notes: list[str] = []
    if cfg.wifi == "off":
        notes.append("wifi = off: sdfrd does not touch the radio")
    if not wireless:
        notes.append(
            f"{cfg.iface} is not a wireless interface: sdfrd leaves it alone"
            + ("" if netif.exists(cfg.iface) else f" ({cfg.iface} does not exist here)")
        )
    applied = False
    if not args.dry_run:
        try:
            if cfg.wifi == "off":
                raise SdfrError("wifi: is off in the configuration; pass --wifi auto to apply")
            if not wireless:
                raise SdfrError(f"wifi: {cfg.iface} is not a wireless interface; not touching it")
            wifi.check_root()
            wifi.apply(the_plan)
        except SdfrError as exc:
            print(f"sdfr: {exc}", file=sys.stderr)
            return 1
        applied = True
    if as_json:
        answer = the_plan.to_json(args.show_key)
        answer.update(
            dry_run=args.dry_run,
            applied=applied,
            wireless=wireless,
            sdfrd_applies=cfg.wifi == "auto" and wireless,
            notes=notes,
        )
        print(json.dumps(answer, indent=2))
    else:
        print(the_plan.describe(args.show_key))
        for note in notes:
            print(f"# note: {note}")
        if applied:
            print(f"# done: {cfg.iface} is joining {the_plan.ssid}")
    return 0
