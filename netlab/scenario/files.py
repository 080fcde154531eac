"""Scenario files (TOML): read by the dataclasses' own fields.

A ``[[step]]`` table has one action key (a `STEPS` kind) whose value is the step's first
field; its other keys are the step's other fields, with the defaults the dataclass gives.
A check's value is a `CONDITIONS` kind, and the condition's fields sit in the same table.
Each field's value is read by its type (`BY_TYPE`) or by the converter its metadata names.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, Field, fields
from pathlib import Path
from typing import Any

from netlab.scenario.conditions import CONDITIONS
from netlab.scenario.model import Scenario
from netlab.scenario.spec import (
    TOML,
    Bad,
    Conv,
    Duration,
    ScenarioError,
    Spread,
    boolean,
    to_float,
    to_groups,
    to_int,
    to_names,
    to_pair,
    to_placed,
    to_robots,
    to_str,
    to_table,
    to_true,
)
from netlab.scenario.steps import STEPS, Check, Start, Step
from sdfr._compat import tomllib  # (tomllib is 3.11+; SDfR runs on 3.10 too)
from sdfr.config.load import options_config
from sdfr.errors import ConfigError
from sdfr.hints import did_you_mean

BUNDLED_DIR = Path(__file__).parent.parent / "scenarios"
TOP_LEVEL = ("scenario", "groups", "positions", "kinds", "hosts", "sdfrd", "step")
#: Scenario fields written as tables of their own, not keys of [scenario].
TABLES = ("groups", "positions", "kinds", "hosts", "sdfrd")

#: How a field's value is read, by its declared type (``| None`` aside).
BY_TYPE: dict[str, Conv] = {
    "str": to_str,
    "bool": boolean,
    "int": to_int,
    "float": to_float,
    "Robots": to_robots,
    "Sequence[Robots]": to_groups,
    "Sequence[str]": to_names,
    "Span": Duration.of,
    "Pos": to_pair,
    "tuple[float, float]": to_pair,
    "Mapping[str, Any]": to_table,
}


class _Fields:
    """A TOML table's keys taken one by one, with errors naming the field; `done()` rejects the
    rest."""

    def __init__(self, table: Mapping[str, Any], where: str) -> None:
        self.rest = dict(table)
        self.where = where
        self.known: list[str] = []

    def take(self, key: str, conv: Conv, default: Any = ...) -> Any:
        self.known.append(key)
        if key not in self.rest:
            if default is ...:
                raise ScenarioError(f"{self.where}: {key}: missing")
            return default
        value = self.rest.pop(key)
        try:
            return conv(value)
        except Bad as exc:
            raise ScenarioError(f"{self.where}: {key}: {exc}") from None

    def gather(self, keys: list[str]) -> dict[str, Any]:
        self.known.extend(keys)
        return {k: self.rest.pop(k) for k in keys if k in self.rest}

    def done(self) -> None:
        if self.rest:
            extra = sorted(self.rest)
            hint = did_you_mean(extra[0], self.known)
            raise ScenarioError(
                f"{self.where}: unknown field{'s' if len(extra) > 1 else ''} {', '.join(extra)}"
                f"{hint} (this takes: {', '.join(self.known)})"
            )


def converter(f: Field[Any]) -> Conv | Spread:
    given = f.metadata.get(TOML)
    if given is not None:
        return given  # type: ignore[no-any-return]
    declared = str(f.type).removesuffix(" | None")
    try:
        return BY_TYPE[declared]
    except KeyError:
        raise AssertionError(
            f"no way to read field {f.name} ({f.type}): add it to BY_TYPE"
        ) from None


def _default(f: Field[Any]) -> Any:
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:
        return f.default_factory()
    return ...  # required


def read_fields(cls: type, f: _Fields, skip: tuple[str, ...] = ()) -> dict[str, Any]:
    """The keyword arguments for `cls` from the table's keys, by the class's own fields."""
    kw: dict[str, Any] = {}
    for fld in fields(cls):
        if not fld.init or fld.name in skip:
            continue
        conv = converter(fld)
        if isinstance(conv, Spread):
            kw[fld.name] = f.gather(list(conv.keys()))
        else:
            kw[fld.name] = f.take(fld.name, conv, _default(fld))
    return kw


def _parse_step(table: Any, where: str) -> Step:
    if not isinstance(table, dict):
        raise ScenarioError(f"{where}: expected a table ([[step]]), got {table!r}")
    actions = [k for k in table if k in STEPS]
    if not actions:
        hint = next((h for k in table if (h := did_you_mean(k, STEPS))), "")
        raise ScenarioError(
            f"{where}: no action{hint}; a step has one of: {', '.join(STEPS)} "
            f"(it has: {', '.join(table) or 'nothing'})"
        )
    if len(actions) > 1:
        raise ScenarioError(f"{where}: more than one action ({', '.join(actions)}); one per step")
    kind = actions[0]
    label = table.get("label")
    where = f"{where} ({kind}{f' {label!r}' if isinstance(label, str) else ''})"
    f = _Fields(table, where)
    cls = STEPS[kind]
    step: Step
    if issubclass(cls, Check):
        cond_kind = f.take(kind, to_str)
        cond_cls = CONDITIONS.get(cond_kind)
        if cond_cls is None:
            known = ", ".join(CONDITIONS)
            raise ScenarioError(
                f"{where}: {kind}: unknown condition {cond_kind!r}"
                f"{did_you_mean(cond_kind, CONDITIONS)} (one of {known})"
            )
        kw = read_fields(cls, f, skip=("condition",))
        step = cls(cond_cls(**read_fields(cond_cls, f)), **kw)
    else:
        main = next((fld for fld in fields(cls) if fld.init and fld.name != "label"), None)
        if main is None:
            f.take(kind, to_true)
            step = cls(**read_fields(cls, f))
        else:
            conv = converter(main)
            assert not isinstance(conv, Spread), f"{kind}: the first field is the action's value"
            first = f.take(kind, conv)
            step = cls(**{main.name: first, **read_fields(cls, f, skip=(main.name,))})
    f.done()
    return step


def _table(data: Mapping[str, Any], key: str, source: str) -> dict[str, Any]:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise ScenarioError(f"{source}: [{key}] must be a table")
    return value


def _entries(table: Mapping[str, Any], conv: Conv, where: str) -> dict[str, Any]:
    out = {}
    for key, value in table.items():
        try:
            out[key] = conv(value)
        except Bad as exc:
            raise ScenarioError(f"{where}: {key}: {exc}") from None
    return out


_HEADER_RE = re.compile(r"\s*\[(\[?)\s*([A-Za-z0-9_.-]+)\s*\]\]?\s*(#.*)?$")


def _key_line(lines: Sequence[str], table: str, nth: int, key: str | None) -> int | None:
    """The line (from 1) that sets `key` in the `nth` table `table` of a TOML file's `lines`
    (its sub-tables, such as [step.options], included); the table's own line if none does
    (or `key` is None); None if the file has no such table."""
    seen, start, inside = 0, None, False
    key_re = re.compile(rf"(^|[{{,\s])[\"']?{re.escape(key or '')}[\"']?\s*=")
    for no, line in enumerate(lines, 1):
        header = _HEADER_RE.match(line)
        if header is not None:
            name = header[2]
            if name == table:
                seen += 1
                inside = seen == nth
                start = no if inside else start
            elif not name.startswith(f"{table}."):
                inside = False
        elif inside and key is not None and key_re.search(line.split("#")[0]):
            return no
    return start


def _check_daemon_options(sc: Scenario, source: str, lines: Sequence[str]) -> None:
    """ScenarioError, with the file's line, unless sdfrd takes the [sdfrd] options, and each
    start step's on top of them, as a Config: a mistyped option is found when the file
    loads (with the closest one), not when a daemon starts."""
    checks = [("[sdfrd]", "sdfrd", 1, dict(sc.sdfrd), dict(sc.sdfrd))]
    for i, step in enumerate(sc.steps, 1):
        if isinstance(step, Start) and step.options:
            own = dict(step.options)
            checks.append((f"step {i} (start): options", "step", i, own, {**sc.sdfrd, **own}))
    for where, table, nth, own, options in checks:
        try:
            options_config(options)
        except ConfigError as exc:
            key = str(exc).partition(":")[0]
            line = _key_line(lines, table, nth, key if key in own else None)
            at = f"{source}:{line}" if line is not None else source
            raise ScenarioError(f"{at}: {where}: {exc}") from None


def from_dict(
    data: Mapping[str, Any],
    source: str = "<scenario>",
    name: str | None = None,
    *,
    lines: Sequence[str] = (),
) -> Scenario:
    """A Scenario from a parsed scenario file (see the package's documentation); `lines`, the
    file's, let an error say its line."""
    extra = [k for k in data if k not in TOP_LEVEL]
    if extra:
        hint = did_you_mean(extra[0], TOP_LEVEL)
        raise ScenarioError(
            f"{source}: unknown table or key {', '.join(map(repr, extra))}{hint} (a scenario file "
            "has [scenario], [groups], [positions], [kinds], [hosts], [sdfrd] and [[step]])"
        )
    f = _Fields(_table(data, "scenario", source), f"{source}: [scenario]")
    head = {"name": f.take("name", to_str, ... if name is None else name)}
    head |= read_fields(Scenario, f, skip=("name", "steps", "source", *TABLES))
    f.done()
    raw_steps = data.get("step", [])
    if not isinstance(raw_steps, list):
        raise ScenarioError(f"{source}: steps are written as [[step]] tables")
    sc = Scenario(
        steps=[_parse_step(t, f"{source}: step {i}") for i, t in enumerate(raw_steps, 1)],
        groups=_entries(_table(data, "groups", source), to_names, f"{source}: [groups]"),
        positions=_entries(_table(data, "positions", source), to_pair, f"{source}: [positions]"),
        kinds=_entries(_table(data, "kinds", source), to_str, f"{source}: [kinds]"),
        hosts=_entries(_table(data, "hosts", source), to_placed, f"{source}: [hosts]"),
        sdfrd=_table(data, "sdfrd", source),
        source=source,
        **head,
    )
    _check_daemon_options(sc, source, lines)
    return sc


def loads(text: str, source: str = "<scenario>", name: str | None = None) -> Scenario:
    """A Scenario from TOML text; ScenarioError names the line, step or field that is wrong."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: not valid TOML: {exc}") from None
    return from_dict(data, source, name, lines=text.splitlines())


def load(path: Path | str) -> Scenario:
    """A Scenario from a TOML file (its name defaults to the file's stem)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ScenarioError(f"cannot read scenario file {path}: {exc.strerror or exc}") from None
    return loads(text, str(path), name=path.stem)


def bundled() -> dict[str, Path]:
    """The bundled scenario files, by name."""
    return {p.stem: p for p in sorted(BUNDLED_DIR.glob("*.toml"))}


def find(ref: str) -> Path:
    """A scenario file: `ref` itself if it is a file, else the bundled scenario of that name."""
    path = Path(ref)
    if path.is_file():
        return path
    found = bundled().get(ref)
    if found is not None:
        return found
    raise ScenarioError(
        f"no scenario file {ref!r} and no bundled scenario of that name"
        f"{did_you_mean(ref, bundled())} (bundled: {', '.join(bundled())})"
    )
