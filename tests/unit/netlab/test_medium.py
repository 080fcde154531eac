"""netlab without the kernel: names, medium rules, range model, mobility, shaping plans."""

from __future__ import annotations

import errno
import json
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyroute2.netlink.exceptions import NetlinkError
from pyroute2.netlink.rtnl.tcmsg import sched_netem

from netlab import cli, hostlimits, manifest, naming
from netlab.doctor import Capabilities, format_report
from netlab.errors import (
    InvalidShapeError,
    KernelError,
    LabExistsError,
    LabNameError,
    ShapingUnsupported,
    UnknownRobotError,
    kernel_errors,
)
from netlab.medium import LOSS_SCALE, loss_units, ruleset
from netlab.mobility import HALL, RandomWaypoint
from netlab.ranges import LossyDisc, Topology, UnitDisc, combine, forwarded, with_link_loss
from netlab.shaping import LinkShape, netem_options, parse_rate, plan, tbf_options

HERE = Capabilities(root=True, netns=True, veth_bridge=True, nft_bridge=True, numgen=True, tbf=True)
WITH_NETEM = Capabilities(
    root=True, netns=True, veth_bridge=True, nft_bridge=True, numgen=True, tbf=True, netem=True,
    radio=True,
)  # fmt: skip


# -- names and addresses ---------------------------------------------------------------------


@pytest.mark.parametrize("name", ["a", "lab1", "12345678", "z0"])
def test_good_lab_names(name: str) -> None:
    assert naming.check_lab_name(name) == name
    assert naming.air_ns(name) == f"nl-{name}-air"


@pytest.mark.parametrize("name", ["", "123456789", "Lab", "a-b", "a_b", "a.b", "ü"])
def test_bad_lab_names_say_the_rule(name: str) -> None:
    with pytest.raises(LabNameError, match="1-8 characters of a-z and 0-9"):
        naming.check_lab_name(name)


def test_robot_names_fit_an_interface_name() -> None:
    assert naming.check_robot_name("r1") == "r1"
    longest = naming.check_robot_name("a" * 12)
    assert len(naming.port(longest)) <= 15
    for bad in ("air", "", "-r", "R1", "a" * 13, "r 1"):
        with pytest.raises(LabNameError):
            naming.check_robot_name(bad)


def test_macs_are_deterministic_unicast_and_local() -> None:
    macs = [naming.mac_for(7, i) for i in range(500)]
    assert macs == [naming.mac_for(7, i) for i in range(500)]
    assert len(set(macs)) == 500
    assert all(m.startswith("02:") for m in macs)
    assert naming.mac_for(8, 0) != naming.mac_for(7, 0)
    assert naming.check_mac("02:AA:00:00:00:01") == "02:aa:00:00:00:01"
    for bad in ("01:00:5e:00:00:01", "02:00:00:00:00", "00:00:00:00:00:00", "zz:00:00:00:00:00"):
        with pytest.raises(LabNameError):
            naming.check_mac(bad)


def test_address_scheme() -> None:
    assert str(naming.address_for(1, 0)) == "10.1.0.1/16"
    assert str(naming.address_for(1, 249)) == "10.1.0.250/16"
    assert str(naming.address_for(3, 250)) == "10.3.1.1/16"
    assert str(naming.address_for(0, naming.MAX_ROBOTS - 1)) == "10.0.255.250/16"
    with pytest.raises(LabNameError):
        naming.address_for(256, 0)
    with pytest.raises(LabNameError):
        naming.address_for(1, naming.MAX_ROBOTS)


# -- medium rules ----------------------------------------------------------------------------

PORTS = {"a": "va", "b": "vb", "c": "vc"}


def test_empty_ruleset_drops_everything_and_replaces_the_table() -> None:
    text = ruleset({}, PORTS)
    lines = text.splitlines()
    assert lines[:3] == [
        "table bridge netlab",
        "delete table bridge netlab",
        "table bridge netlab {",
    ]
    assert "policy drop;" in text
    assert "elements" not in text
    assert "numgen" not in text


def test_ruleset_accepts_linked_pairs_and_drops_with_loss() -> None:
    text = ruleset({("a", "b"): 0.0, ("b", "a"): 30.0, ("a", "c"): 12.345}, PORTS)
    assert '"va" . "vb" : accept,' in text
    assert '"vb" . "va" : jump loss_3000,' in text
    assert '"va" . "vc" : jump loss_1234,' in text  # 0.01 % resolution
    assert f"numgen random mod {LOSS_SCALE} < 3000 drop" in text
    assert f"numgen random mod {LOSS_SCALE} < 1234 drop" in text
    assert '"vc"' not in text.split('"va" . "vc"')[0]  # c sends to nobody
    assert text.count("chain loss_") == 2


def test_ruleset_leaves_out_total_loss_and_is_deterministic() -> None:
    links = {("a", "b"): 100.0, ("b", "c"): 99.999, ("c", "a"): 0.004}
    text = ruleset(links, PORTS)
    assert '"va" . "vb"' not in text and '"vb" . "vc"' not in text  # both round to 100 %
    assert '"vc" . "va" : accept' in text  # rounds to 0
    assert ruleset(dict(reversed(list(links.items()))), PORTS) == text


@given(st.floats(min_value=0, max_value=100))
def test_loss_units_are_within_scale(loss: float) -> None:
    units = loss_units(loss)
    assert 0 <= units <= LOSS_SCALE
    assert abs(units / LOSS_SCALE * 100 - loss) <= 0.005 + 1e-9


# -- range model and topology ----------------------------------------------------------------


def line(*xs: float, model: UnitDisc | LossyDisc | None = None) -> Topology:
    topo = Topology(model or UnitDisc(15.0))
    for i, x in enumerate(xs):
        topo.add(f"r{i + 1}", (x, 0.0))
    return topo


def test_unit_disc_links_pairs_within_radius_both_ways() -> None:
    topo = line(0, 10, 20, 100)
    assert topo.links() == {
        ("r1", "r2"): 0.0,
        ("r2", "r1"): 0.0,
        ("r2", "r3"): 0.0,
        ("r3", "r2"): 0.0,
    }
    assert UnitDisc(5).loss(5.0) == 0.0 and UnitDisc(5).loss(5.01) is None


def test_moving_out_of_range_cuts_and_back_restores() -> None:
    topo = line(0, 10)
    topo.move("r2", (16, 0))
    assert topo.links() == {}
    topo.move("r2", (0, 14.9))
    assert set(topo.links()) == {("r1", "r2"), ("r2", "r1")}
    with pytest.raises(UnknownRobotError):
        topo.move("r9", (0, 0))
    with pytest.raises(ValueError):
        topo.move("r1", (math.nan, 0))


def test_lossy_disc() -> None:
    model = LossyDisc(radius=20, clean=10, edge_loss=40)
    assert model.loss(5) == 0.0
    assert model.loss(15) == pytest.approx(20.0)
    assert model.loss(20) == pytest.approx(40.0)
    assert model.loss(20.1) is None
    topo = line(0, 15, model=model)
    assert topo.links() == {("r1", "r2"): pytest.approx(20.0), ("r2", "r1"): pytest.approx(20.0)}
    with pytest.raises(ValueError):
        LossyDisc(radius=5, clean=10)


def test_partition_overrides_ranges_and_merge_restores() -> None:
    topo = line(0, 0, 0, 0, 50)
    everyone = set(topo.links())
    topo.partition([["r1", "r2"], ["r3"]])
    links = set(topo.links())
    assert links == {("r1", "r2"), ("r2", "r1")}  # r4 alone in "the rest"; r5 out of range
    topo.partition([["r1"], ["r2", "r3"]])
    # r4 and r5 form the rest; r5 is still out of r4's range: ranges apply inside a group.
    assert set(topo.links()) == {("r2", "r3"), ("r3", "r2")}
    topo.merge()
    assert set(topo.links()) == everyone
    with pytest.raises(ValueError, match="more than one group"):
        topo.partition([["r1", "r2"], ["r2"]])
    with pytest.raises(UnknownRobotError):
        topo.partition([["r1", "nobody"]])


def test_pair_quality_replaces_range_loss_but_never_creates_a_link() -> None:
    topo = line(0, 0, 100)
    topo.set_pair_quality("r1", "r2", 20.0, both=False)
    assert topo.links()[("r1", "r2")] == 20.0
    assert topo.links()[("r2", "r1")] == 0.0
    topo.set_pair_quality("r1", "r3", 0.0)
    assert ("r1", "r3") not in topo.links()  # out of range stays out of range
    topo.set_pair_quality("r1", "r2", 100.0)
    assert ("r1", "r2") not in topo.links() and ("r2", "r1") not in topo.links()
    topo.set_pair_quality("r1", "r2", None)
    assert topo.links()[("r1", "r2")] == 0.0
    topo.partition([["r1"], ["r2"]])
    topo.set_pair_quality("r1", "r2", 5.0)
    assert topo.links() == {}  # the partition wins
    with pytest.raises(ValueError):
        topo.set_pair_quality("r1", "r2", 101.0)
    with pytest.raises(ValueError):
        topo.set_pair_quality("r1", "r1", 1.0)


def test_link_loss_combines_with_pair_loss_on_both_directions() -> None:
    links = {("a", "b"): 50.0, ("b", "a"): 0.0, ("b", "c"): 0.0}
    out = with_link_loss(links, {"a": 50.0})
    assert out == {("a", "b"): 75.0, ("b", "a"): 50.0, ("b", "c"): 0.0}
    assert combine() == 0.0 and combine(100.0, 3.0) == 100.0


def test_a_mesh_forwards_between_its_radios_by_the_best_chain() -> None:
    """A line r1 - r2 - r3 (r1 and r3 out of each other's range) and r4 beside r3 only:
    among mesh radios r1..r3, r1 and r3 reach each other through r2, the hops' losses in
    series; r4 (not in the mesh) neither relays nor is reached through it."""
    topo = Topology(UnitDisc(10.0))
    for i, name in enumerate(["r1", "r2", "r3", "r4"]):
        topo.add(name, (8.0 * i, 0.0))
    topo.set_pair_quality("r1", "r2", 50.0, both=False)
    direct = topo.links()
    assert ("r1", "r3") not in direct and ("r3", "r4") in direct
    mesh = forwarded(direct, ["r1", "r2", "r3"])
    assert mesh[("r1", "r3")] == pytest.approx(50.0) and mesh[("r3", "r1")] == 0.0
    assert mesh[("r1", "r2")] == 50.0  # a direct link keeps its own loss
    assert ("r2", "r4") not in mesh and ("r4", "r2") not in mesh  # r4 relays nothing
    assert {p: v for p, v in mesh.items() if p in direct} == direct
    # a chain that delivers more than a lossy direct link wins: r1 -> r2 -> r3 at 0 % vs 90 %
    lossy = {("r1", "r3"): 90.0, ("r1", "r2"): 0.0, ("r2", "r3"): 20.0}
    assert forwarded(lossy, ["r1", "r2", "r3"])[("r1", "r3")] == pytest.approx(20.0)
    # a partition is a partition in the mesh too: no chain crosses it
    topo.partition([["r1"], ["r2", "r3"]])
    assert ("r1", "r3") not in forwarded(topo.links(), ["r1", "r2", "r3"])
    assert forwarded(direct, []) == direct


# -- mobility --------------------------------------------------------------------------------

ROBOTS = ["r1", "r2", "r3", "r4"]


def test_random_waypoint_is_deterministic_and_order_independent() -> None:
    a = RandomWaypoint(ROBOTS, seed=3)
    b = RandomWaypoint(ROBOTS, seed=3)
    late = a.positions_at(120.0)
    early = a.positions_at(5.0)  # asked after a later time: same answer as a fresh model
    assert early == b.positions_at(5.0)
    assert late == b.positions_at(120.0)
    assert RandomWaypoint(ROBOTS, seed=4).positions_at(5.0) != early


def test_random_waypoint_adding_a_robot_keeps_the_others_paths() -> None:
    small = RandomWaypoint(["r1", "r2"], seed=1)
    big = RandomWaypoint(["r1", "r2", "r9"], seed=1)
    for t in (0.0, 3.3, 40.0):
        assert {k: big.positions_at(t)[k] for k in ("r1", "r2")} == small.positions_at(t)


@settings(max_examples=25, deadline=None)
@given(st.integers(min_value=0, max_value=2**32), st.floats(min_value=0.1, max_value=3.0))
def test_random_waypoint_stays_in_the_hall_and_under_max_speed(seed: int, vmax: float) -> None:
    model = RandomWaypoint(ROBOTS, seed=seed, speed=(0.1, vmax), pause=(0.0, 1.0))
    dt = 0.25
    prev = model.positions_at(0.0)
    for k in range(1, 240):
        now = model.positions_at(k * dt)
        for r in ROBOTS:
            x, y = now[r]
            assert 0 <= x <= HALL[0] and 0 <= y <= HALL[1]
            moved = math.dist(now[r], prev[r])
            assert moved <= vmax * dt + 1e-9
        prev = now


def test_random_waypoint_moves_pauses_and_honours_start() -> None:
    model = RandomWaypoint(["r1"], seed=2, speed=(1.0, 1.0), pause=5.0, start={"r1": (0.0, 0.0)})
    assert model.positions_at(0.0) == {"r1": (0.0, 0.0)}
    path = [model.positions_at(t / 10)["r1"] for t in range(0, 600)]
    assert len(set(path)) > 100  # it moves
    # after each arrival it holds still for 5 s: some run of 50 samples stays put
    still = max(sum(1 for _ in group) for group in _runs(path))
    assert still >= 49
    with pytest.raises(ValueError):
        RandomWaypoint(["r1"], speed=(0.0, 1.0))
    with pytest.raises(ValueError):
        RandomWaypoint(["r1", "r1"])
    with pytest.raises(ValueError):
        model.positions_at(-1.0)


def _runs(path: list[tuple[float, float]]) -> list[list[tuple[float, float]]]:
    runs: list[list[tuple[float, float]]] = []
    for p in path:
        if runs and runs[-1][-1] == p:
            runs[-1].append(p)
        else:
            runs.append([p])
    return runs


# -- shaping ---------------------------------------------------------------------------------


def test_shape_parameters_are_checked() -> None:
    assert LinkShape().is_none
    assert LinkShape.of(delay=None, rate=None).is_none
    with pytest.raises(InvalidShapeError, match="unknown shaping parameter"):
        LinkShape.of(latency=5)
    with pytest.raises(InvalidShapeError, match="loss"):
        LinkShape(loss=120)
    with pytest.raises(InvalidShapeError, match="jitter"):
        LinkShape(jitter=5)
    with pytest.raises(InvalidShapeError, match="reorder"):
        LinkShape(reorder=5)
    with pytest.raises(InvalidShapeError, match="rate"):
        LinkShape.of(rate="fast")


def test_parse_rate() -> None:
    assert parse_rate(1_000_000) == 1_000_000
    assert parse_rate("1mbit") == 1_000_000
    assert parse_rate("500kbit") == 500_000
    assert parse_rate("2Mbps") == 16_000_000
    assert parse_rate("64") == 64
    with pytest.raises(InvalidShapeError):
        parse_rate(True)
    with pytest.raises(InvalidShapeError):
        parse_rate(0)


def test_netem_translation_units_and_pyroute2_accepts_them() -> None:
    shape = LinkShape(
        delay=50, jitter=5.5, loss=30, duplicate=1, reorder=25, corrupt=0.5, rate=8_000_000
    )
    opts = netem_options(shape)
    assert opts["delay"] == 50_000 and opts["jitter"] == 5_500  # microseconds
    assert opts["loss"] == 30 and opts["duplicate"] == 1
    assert opts["prob_reorder"] == 25 and opts["prob_corrupt"] == 0.5
    assert opts["rate"] == 1_000_000  # bytes per second
    # pyroute2 turns them into the kernel's struct: percentages as u32 fractions.
    params = sched_netem.get_parameters(opts)
    assert params["loss"] == int((2**32 - 1) * 0.30)
    assert params["gap"] == 1  # reordering needs a gap; pyroute2 sets it
    attrs = dict(params["attrs"])
    assert attrs["TCA_NETEM_RATE"]["rate"] == 1_000_000
    assert attrs["TCA_NETEM_REORDER"]["prob_reorder"] == int((2**32 - 1) * 0.25)
    assert attrs["TCA_NETEM_CORRUPT"]["prob_corrupt"] == int((2**32 - 1) * 0.005)
    assert netem_options(LinkShape(delay=10))["delay"] == 10_000
    assert "prob_reorder" not in netem_options(LinkShape(delay=10))


def test_plan_with_netem_uses_it_for_everything() -> None:
    p = plan(LinkShape(delay=50, loss=30), WITH_NETEM)
    assert p.kind == "netem" and p.nft_loss == 0.0 and p.options["delay"] == 50_000
    assert plan(LinkShape(), WITH_NETEM).kind is None


def test_plan_without_netem_falls_back_or_refuses_naming_the_module() -> None:
    assert plan(LinkShape(loss=30), HERE) == plan(LinkShape(loss=30), HERE)
    p = plan(LinkShape(loss=30), HERE)
    assert p.kind is None and p.nft_loss == 30.0
    p = plan(LinkShape(rate=1_000_000, loss=5), HERE)
    assert p.kind == "tbf" and p.nft_loss == 5.0
    assert p.options == tbf_options(1_000_000)
    for params in ({"delay": 50}, {"delay": 5, "jitter": 1}, {"duplicate": 1}, {"corrupt": 1}):
        with pytest.raises(ShapingUnsupported, match="sch_netem") as err:
            plan(LinkShape(**params), HERE)
        assert "VM" in str(err.value)
        assert next(iter(params)) in str(err.value)
    no_tbf = Capabilities(root=True, netns=True, veth_bridge=True, nft_bridge=True, numgen=True)
    with pytest.raises(ShapingUnsupported, match="sch_tbf"):
        plan(LinkShape(rate=1000), no_tbf)


def test_tbf_bucket_holds_whole_frames() -> None:
    assert tbf_options(8_000)["burst"] >= 2 * 1514
    assert tbf_options(800_000_000)["burst"] == 1_000_000
    assert tbf_options(8_000)["rate"] == 1_000


# -- errors, manifest, doctor report, CLI parsing --------------------------------------------


def test_kernel_errors_are_translated_with_a_hint() -> None:
    needs_root = r"creating x failed: .*needs root"
    with pytest.raises(KernelError, match=needs_root) as err, kernel_errors("creating x"):
        raise NetlinkError(errno.EPERM)
    assert err.value.errno == errno.EPERM
    with pytest.raises(KernelError, match="already exists"), kernel_errors("adding y"):
        raise FileExistsError(errno.EEXIST, "File exists")
    # not a library error: left alone
    with pytest.raises(ZeroDivisionError), kernel_errors("dividing"):
        _ = 1 / 0


def test_manifest_claim_save_load_remove(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NETLAB_RUN_DIR", str(tmp_path / "run"))
    rec = manifest.Manifest("m1", seed=4, workdir="/tmp/x", namespaces=["nl-m1-air"])
    manifest.claim(rec)
    with pytest.raises(LabExistsError, match="netlab down m1"):
        manifest.claim(manifest.Manifest("m1"))
    rec.robots["r1"] = manifest.RobotRecord(
        0, "nl-m1-r1", "vr1", "02:00:00:00:00:01", "10.1.0.1/16"
    )
    rec.processes.append(manifest.ProcRecord(123, 456, "r1", "sdfrd", ["sdfrd"]))
    manifest.save(rec)
    loaded = manifest.load("m1")
    assert loaded == rec
    assert json.loads((tmp_path / "run" / "m1.json").read_text())["version"] == 1
    assert manifest.names() == ["m1"]
    assert manifest.remove("m1") and manifest.load("m1") is None and manifest.names() == []


def test_arp_table_limits_are_raised_for_big_labs_and_restored_by_the_last(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NETLAB_RUN_DIR", str(tmp_path / "run"))
    neigh = tmp_path / "neigh"
    neigh.mkdir()
    (neigh / "gc_thresh2").write_text("512")
    (neigh / "gc_thresh3").write_text("1024")
    assert hostlimits.max_mesh(1024) == 27
    assert not hostlimits.ensure(hostlimits.mesh_entries(27), neigh)
    assert hostlimits.ensure(hostlimits.mesh_entries(50), neigh)
    raised = hostlimits.current(neigh)
    assert hostlimits.max_mesh(raised["gc_thresh3"]) >= 50
    assert raised["gc_thresh2"] <= raised["gc_thresh3"]
    assert hostlimits.ensure(hostlimits.mesh_entries(80), neigh)  # raised again
    manifest.claim(manifest.Manifest("other"))
    assert not hostlimits.restore_if_last(neigh)  # another lab is still up
    manifest.remove("other")
    assert hostlimits.restore_if_last(neigh)
    assert hostlimits.current(neigh) == {"gc_thresh2": 512, "gc_thresh3": 1024}
    assert not (tmp_path / "run" / ".host.json").exists()
    # Changed by someone else meanwhile: left as they set it.
    hostlimits.ensure(hostlimits.mesh_entries(50), neigh)
    (neigh / "gc_thresh3").write_text("100000")
    assert hostlimits.restore_if_last(neigh)
    assert hostlimits.current(neigh)["gc_thresh3"] == 100000


def test_doctor_report_names_consequences() -> None:
    text = format_report(HERE)
    assert "tc netem (sch_netem)    NO" in text
    assert "refuses delay" in text and "modprobe sch_netem" in text and "tbf" in text
    assert "ShapingUnsupported" not in text  # errors in words, not class names
    assert "802.11 radios (hwsim)   NO" in text and "make test-radio" in text
    assert "NO" not in format_report(WITH_NETEM)


def test_cli_rejects_bad_names_and_missing_robots(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        cli.main(["up", "Bad-Name", "--robots", "2"])
    assert exit_.value.code == 2
    assert "1-8 characters" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["up", "ok"])
    with pytest.raises(SystemExit):
        cli.main(["up", "ok", "--robots", "0"])
    for argv in (["--", "ip", "-br", "a"], ["ip", "-br", "a"]):
        args = cli.build_parser().parse_args(["exec", "lab", "r1", *argv])
        assert args.cmd[-3:] == ["ip", "-br", "a"]


def test_a_topology_written_down_comes_back_with_the_same_links() -> None:
    topo = Topology(LossyDisc(30.0, clean=10.0, edge_loss=40.0))
    for name, pos in {
        "a": (0.0, 0.0),
        "b": (20.0, 0.0),
        "c": (5.0, 5.0),
        "d": (100.0, 0.0),
    }.items():
        topo.add(name, pos)
    topo.partition([["a", "b"]])
    topo.set_pair_quality("a", "b", 12.5, both=False)
    data = json.loads(json.dumps(topo.to_json()))
    again = Topology.from_json(data)
    assert again.links() == topo.links() and again.positions == topo.positions
    assert again.model == topo.model

    class Custom:
        def loss(self, distance: float) -> float | None:
            return 0.0

    assert Topology(Custom()).to_json() is None  # a model netlab cannot write down


def test_arp_table_limits_out_of_sight_are_left_to_the_machine(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """In a namespace other than the initial one (a simulated host's ssh session) the
    limits are not visible: a lab there leaves them to the machine (`SimHosts(robots=...)`
    raises them from the initial namespace), and its going down neither restores them nor
    forgets what the machine found (a 300-robot lab across simulated hosts once went deaf
    past the default 1024 entries, and the record of the originals was lost)."""
    monkeypatch.setenv("NETLAB_RUN_DIR", str(tmp_path / "run"))
    neigh = tmp_path / "neigh"
    neigh.mkdir()
    (neigh / "gc_thresh2").write_text("512")
    (neigh / "gc_thresh3").write_text("1024")
    assert hostlimits.ensure(hostlimits.mesh_entries(300), neigh)  # the machine's side
    assert not hostlimits.ensure(hostlimits.mesh_entries(300), tmp_path / "absent")
    assert not hostlimits.restore_if_last(tmp_path / "absent")  # a host's last lab went
    assert (tmp_path / "run" / ".host.json").exists()
    assert hostlimits.restore_if_last(neigh)  # the machine's side, once all are down
    assert hostlimits.current(neigh) == {"gc_thresh2": 512, "gc_thresh3": 1024}
