"""docs/scenarios.md documents every step, condition and key the scenario files take.

The reference is written by hand; this test reads the code's registries (`STEPS`,
`CONDITIONS`, the `Scenario` dataclass, the file's tables, `LinkShape`) so that a step, a
condition or a key added to the code without its documentation fails here.
"""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path

import pytest

from netlab.scenario.conditions import CONDITIONS
from netlab.scenario.files import TABLES, TOP_LEVEL
from netlab.scenario.model import Scenario
from netlab.scenario.spec import RESERVED_OPTIONS
from netlab.scenario.steps import STEPS, Check, Shape
from netlab.scenario.topology import LAYOUT_STEPS
from netlab.shaping import LinkShape

DOC = Path(__file__).resolve().parents[2] / "docs" / "scenarios.md"


def _sections(level: str) -> dict[str, str]:
    """The doc's sections of heading `level` ("##" or "###") by title, each with its text."""
    out: dict[str, str] = {}
    title = None
    for line in DOC.read_text().splitlines():
        m = re.match(r"^(#+) (.*)$", line)
        if m:
            title = m.group(2).strip() if m.group(1) == level else None
            if title is not None:
                out[title] = ""
            continue
        if title is not None:
            out[title] += line + "\n"
    return out


def _keys(cls: type, skip: tuple[str, ...] = ()) -> list[str]:
    return [f.name for f in fields(cls) if f.init and f.name not in ("label", *skip)]


def _missing(text: str, names: list[str]) -> list[str]:
    return [n for n in names if f"`{n}`" not in text]


def _subsections_of(part: str) -> dict[str, str]:
    """The `### `kind`` sections that follow the `## part` heading, up to the next `##`."""
    text = DOC.read_text()
    start = text.index(f"\n## {part}\n")
    end = text.find("\n## ", start + 1)
    body = text[start : end if end > 0 else None]
    chunks = re.split(r"^### `([\w-]+)`\s*$", body, flags=re.M)
    return dict(zip(chunks[1::2], chunks[2::2], strict=True))


@pytest.mark.parametrize("kind", sorted(STEPS))
def test_every_step_and_its_keys_are_documented(kind: str) -> None:
    sections = _subsections_of("Steps")
    assert kind in sections, f"docs/scenarios.md has no '### `{kind}`' under '## Steps'"
    cls = STEPS[kind]
    keys = _keys(cls, skip=("condition",) if issubclass(cls, Check) else ())
    if cls is Shape:
        keys = [kind, *_keys(LinkShape)]  # its parameters are keys beside `shape`
    elif not issubclass(cls, Check):
        keys = [kind, *keys[1:]]  # the first field is written as the action's value
    else:
        keys = [kind, *keys]
    missing = _missing(sections[kind], keys)
    assert not missing, f"step {kind}: keys missing from its section: {missing}"


@pytest.mark.parametrize("kind", sorted(CONDITIONS))
def test_every_condition_and_its_keys_are_documented(kind: str) -> None:
    sections = _subsections_of("Conditions")
    assert kind in sections, f"docs/scenarios.md has no '### `{kind}`' under '## Conditions'"
    missing = _missing(sections[kind], _keys(CONDITIONS[kind]))
    assert not missing, f"condition {kind}: keys missing from its section: {missing}"


def test_the_documented_steps_and_conditions_exist() -> None:
    """No section for a step or condition the code no longer has."""
    assert set(_subsections_of("Steps")) == set(STEPS)
    assert set(_subsections_of("Conditions")) == set(CONDITIONS)


def test_every_scenario_key_and_table_is_documented() -> None:
    sections = _sections("##")
    head = sections["The `[scenario]` table"]
    keys = _keys(Scenario, skip=("steps", "source", *TABLES))
    rows = re.findall(r"^\| `(\w+)` \|", head, flags=re.M)
    assert sorted(rows) == sorted(keys), "the [scenario] table's rows are not its keys"
    tables = sections["Tables of a file"]
    for name in TOP_LEVEL:
        written = "[[step]]" if name == "step" else f"[{name}]"
        assert f"`{written}`" in tables, f"table {written} is not documented"
    assert not _missing(tables, list(RESERVED_OPTIONS))


def test_the_topology_steps_are_documented() -> None:
    text = _sections("##")["Topology files"]
    missing = _missing(text, [cls.kind for cls in LAYOUT_STEPS])
    assert not missing, f"topology steps missing: {missing}"
    allowed = set(re.findall(r"may only be (.*?); any other", text, flags=re.S)[0].split("`")[1::2])
    assert allowed == {cls.kind for cls in LAYOUT_STEPS}


def test_the_examples_are_valid_files() -> None:
    """Each TOML example of the page loads; the topology example is a valid topology."""
    from netlab.scenario import check_layout, loads

    examples = re.findall(r"```toml\n(.*?)```", DOC.read_text(), flags=re.S)
    assert len(examples) == 2
    assert loads(examples[0]).steps
    check_layout(loads(examples[1]))
