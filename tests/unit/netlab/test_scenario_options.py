"""A scenario file's sdfrd options are checked as sdfrd's `Config` when the file loads: a typo
or a value sdfrd would refuse is an error at the file's line, with the closest option."""

from __future__ import annotations

from pathlib import Path

import pytest

from netlab.scenario import ScenarioError, from_dict, load, loads

HEAD = '[scenario]\nname = "x"\nrobots = 2\n'


@pytest.mark.parametrize(
    ("text", "says"),
    [
        (
            HEAD + "[sdfrd]\nping_window = 50\nmis_limit = 3\n",
            r"^f\.toml:6: \[sdfrd\]: mis_limit: not an sdfrd option "
            r"\(did you mean 'miss_limit'\?\)$",
        ),
        (
            HEAD + '[sdfrd]\nmiss_limit = "three"\n',
            r"^f\.toml:5: \[sdfrd\]: miss_limit: expected int",
        ),
        (
            HEAD + '[[step]]\nsleep = 1\n[[step]]\nstart = "all"\noptions = { ping_windw = 9 }\n',
            r"^f\.toml:8: step 2 \(start\): options: ping_windw: .*did you mean 'ping_window'",
        ),
        (
            HEAD + '[[step]]\nstart = "all"\n[step.options]\nttl = 1\nping_window = 0\n',
            r"^f\.toml:8: step 1 \(start\): options: ping_window: must be 1-10000",
        ),
        (  # options that only fail together: the step is the line
            HEAD + '[sdfrd]\nwifi_secret = "12345678"\n'
            '[[step]]\nstart = "all"\noptions = { wifi_secret_file = "/k" }\n',
            r"^f\.toml:6: step 1 \(start\): options: wifi_secret: give wifi_secret or",
        ),
    ],
)
def test_a_bad_daemon_option_is_an_error_at_its_line(text: str, says: str) -> None:
    with pytest.raises(ScenarioError, match=says):
        loads(text, "f.toml")


def test_good_options_load_and_a_parsed_dict_says_no_line(tmp_path: Path) -> None:
    path = tmp_path / "ok.toml"
    path.write_text(HEAD + '[sdfrd]\nping_window = 50\n[[step]]\nstart = "all"\n')
    assert dict(load(path).sdfrd) == {"ping_window": 50}
    data = {"scenario": {"name": "x"}, "sdfrd": {"mis_limit": 3}}
    with pytest.raises(ScenarioError, match=r"^d: \[sdfrd\]: mis_limit: not an sdfrd option"):
        from_dict(data, "d")


def test_every_bundled_scenario_has_options_sdfrd_takes() -> None:
    from netlab.scenario import bundled

    for path in bundled().values():
        load(path)
