"""Lab manifests: a name is claimed whole, and readers never see half a record."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from netlab import manifest
from netlab.errors import LabExistsError, NetlabError
from netlab.manifest import Manifest, RobotRecord


@pytest.fixture(autouse=True)
def run_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("NETLAB_RUN_DIR", str(tmp_path))
    return tmp_path


def test_a_taken_name_is_refused_and_no_private_file_is_left(run_dir: Path) -> None:
    manifest.claim(Manifest("a", seed=3))
    with pytest.raises(LabExistsError, match="already up"):
        manifest.claim(Manifest("a", seed=4))
    loaded = manifest.load("a")
    assert loaded is not None and loaded.seed == 3  # the refused claim changed nothing
    assert sorted(p.name for p in run_dir.iterdir()) == ["a.json"]


def test_a_reader_never_sees_a_claim_half_written() -> None:
    # A second lab coming up reads every other lab's record (to size the neighbour
    # table) while the first is still claiming its name: it used to read an empty file.
    big = Manifest(
        "writer", robots={f"r{i}": RobotRecord(i, f"ns{i}", f"p{i}", "m", "a") for i in range(300)}
    )
    stop = threading.Event()
    seen: list[int] = []
    errors: list[Exception] = []

    def read() -> None:
        while not stop.is_set():
            try:
                record = manifest.load("writer")
                if record is not None:
                    seen.append(len(record.robots))
            except Exception as exc:
                errors.append(exc)

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for _ in range(300):
            manifest.claim(big)
            manifest.remove("writer")
        # The reader must have read it whole at least once (on a loaded machine it may have
        # found no record at all in 300 claims): claim until it has, sleeping between.
        deadline = time.monotonic() + 10.0
        while not seen and time.monotonic() < deadline:
            manifest.claim(big)
            time.sleep(0.002)
            manifest.remove("writer")
    finally:
        stop.set()
        reader.join()
    assert errors == []
    assert seen and set(seen) == {300}


def test_others_leaves_out_a_damaged_record_that_is_not_ours(run_dir: Path) -> None:
    manifest.claim(Manifest("mine"))
    manifest.claim(Manifest("fine", robots={"r1": RobotRecord(0, "n", "p", "m", "a")}))
    (run_dir / "broken.json").write_text("")
    assert [m.name for m in manifest.others("mine")] == ["fine"]
    with pytest.raises(NetlabError, match="is not JSON"):
        manifest.load("broken")  # asked for by name, it is still named as damaged


def test_a_record_keeps_robot_kinds_and_containers_and_an_older_one_still_loads(
    run_dir: Path,
) -> None:
    record = Manifest("c", containers=["nl-c-r1", "nl-c-r1.sdfrd"])
    mac = "02:00:00:00:00:01"
    record.robots["r1"] = RobotRecord(0, "nl-c-r1", "vr1", mac, "10.1.0.1/16", "docker")
    manifest.claim(record)
    loaded = manifest.load("c")
    assert loaded == record
    # A manifest written before robot kinds existed: namespace robots, no containers.
    (run_dir / "old.json").write_text(
        '{"version": 1, "name": "old", "robots": {"r1": {"index": 0, "ns": "nl-old-r1", '
        '"port": "vr1", "mac": "02:00:00:00:00:01", "address": "10.1.0.1/16"}}}'
    )
    old = manifest.load("old")
    assert old is not None and old.containers == [] and old.robots["r1"].runtime == "namespace"
