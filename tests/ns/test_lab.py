"""netlab against the real kernel: medium rules, loss, shaping, crash sweep, real daemons."""

from __future__ import annotations

import json
import os
import selectors
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from netlab import cleanup, kernel, manifest, naming
from netlab.cleanup import running
from netlab.doctor import capabilities, format_report
from netlab.errors import KernelError, LabExistsError, ShapingUnsupported
from netlab.lab import Lab
from netlab.mobility import RandomWaypoint
from netlab.ranges import Topology, UnitDisc
from tests.support.waiting import poll

pytestmark = pytest.mark.root

GROUP, PORT = "239.255.255.250", 1901  # not sdfrd's port: these tests send their own datagrams

# Joins the group, prints "ready", and once told "go" on stdin counts datagrams per sender
# address for `seconds`.
RECEIVER = r"""
import json, socket, struct, sys, time
group, port, seconds = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
s.bind(("0.0.0.0", port))
mreq = struct.pack("4s4si", socket.inet_aton(group), socket.inet_aton("0.0.0.0"),
                   socket.if_nametoindex("eth0"))
s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
print("ready", flush=True)
sys.stdin.readline()
counts, nbytes, first, last = {}, {}, {}, {}
end = time.monotonic() + seconds
while (left := end - time.monotonic()) > 0:
    s.settimeout(left)
    try:
        data, (host, _) = s.recvfrom(65535)
    except (socket.timeout, TimeoutError):
        break
    now = time.monotonic()
    counts[host] = counts.get(host, 0) + 1
    nbytes[host] = nbytes.get(host, 0) + len(data)
    first.setdefault(host, now)
    last[host] = now
span = {h: last[h] - first[h] for h in last}
print(json.dumps({"counts": counts, "bytes": nbytes, "span": span}), flush=True)
"""

# Sends `count` datagrams of `size` bytes to `dest`, `gap` seconds apart (0: as fast as it
# can), for at most `limit` seconds.
SENDER = r"""
import socket, sys, time
dest, port, count, size = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
gap, limit = float(sys.argv[5]), float(sys.argv[6])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
payload = b"x" * size
end = time.monotonic() + limit
for _ in range(count):
    if time.monotonic() > end:
        break
    try:
        s.sendto(payload, (dest, port))
    except OSError:
        pass  # a full qdisc (ENOBUFS) is a drop, like on a radio
    if gap:
        time.sleep(gap)
"""


def unique_lab_name() -> str:
    return naming.unique_lab_name("t")


@pytest.fixture
def make_lab(tmp_path: Path) -> Iterator[Callable[..., Lab]]:
    """`make_lab(n, **kw)`: an up lab with robots r1..rn at the origin; all taken down after."""
    labs: list[Lab] = []

    def make(n: int = 0, **kw: Any) -> Lab:
        name = unique_lab_name()
        kw.setdefault("workdir", tmp_path / name)
        lab = Lab(name, **kw).up()
        labs.append(lab)
        lab.add_robots([f"r{i + 1}" for i in range(n)])
        return lab

    yield make
    problems: list[str] = []
    for lab in labs:  # every lab goes down, even if one fails to
        try:
            lab.down()
        except Exception as exc:
            problems.append(f"{lab.name}: {exc}")
        if kernel.list_ns(naming.prefix(lab.name)):
            problems.append(f"{lab.name}: namespaces left behind")
        if manifest.load(lab.name) is not None:
            problems.append(f"{lab.name}: manifest left behind")
    assert not problems, problems


def _readline(proc: subprocess.Popen[str], timeout: float) -> str:
    assert proc.stdout is not None
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            raise AssertionError(f"no output from {proc.args} within {timeout} s")
    return proc.stdout.readline()


@dataclass(frozen=True)
class Got:
    """What one receiver got from the sender: datagrams, bytes, first-to-last arrival."""

    count: int
    nbytes: int
    span: float


def send_and_count(
    lab: Lab, sender: str, receivers: list[str], count: int = 20, gap: float = 0.002
) -> dict[str, int]:
    """How many of `count` multicast datagrams from `sender` each receiver got."""
    got = exchange(lab, sender, receivers, count, gap=gap)
    return {r: g.count for r, g in got.items()}


def exchange(
    lab: Lab,
    sender: str,
    receivers: list[str],
    count: int,
    *,
    size: int = 32,
    gap: float = 0.002,
    dest: str = GROUP,
    limit: float = 30.0,
    listen: float | None = None,
) -> dict[str, Got]:
    """Receivers listen (`listen` s), then `sender` sends to `dest` for at most `limit` s."""
    duration = listen if listen is not None else count * gap + 1.0
    procs = {
        r: lab.popen(
            r,
            [sys.executable, "-c", RECEIVER, GROUP, str(PORT), str(duration)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        for r in receivers
    }
    for r, p in procs.items():
        assert _readline(p, 10.0).strip() == "ready", f"receiver on {r} did not start"
    for p in procs.values():  # all listen from now on, however long they took to start
        assert p.stdin is not None
        p.stdin.write("go\n")
        p.stdin.close()
    argv = [SENDER, dest, str(PORT), str(count), str(size), str(gap), str(limit)]
    res = lab.exec(sender, [sys.executable, "-c", *argv], timeout=limit + 30)
    assert res.returncode == 0, res.stderr
    src = lab.robot(sender).ip
    out: dict[str, Got] = {}
    for r, p in procs.items():
        line = _readline(p, duration + 10.0)
        p.wait(10)
        got = json.loads(line)
        out[r] = Got(got["counts"].get(src, 0), got["bytes"].get(src, 0), got["span"].get(src, 0.0))
    return out


def pings(lab: Lab, a: str, b: str) -> bool:
    res = lab.exec(a, ["ping", "-c", "1", "-W", "1", lab.robot(b).ip])
    return res.returncode == 0


# -- the medium ------------------------------------------------------------------------------


def test_lab_objects_carry_its_name_and_a_second_lab_of_that_name_is_refused(
    make_lab: Callable[..., Lab],
) -> None:
    lab = make_lab(2)
    assert kernel.list_ns(naming.prefix(lab.name)) == sorted(
        [f"nl-{lab.name}-air", f"nl-{lab.name}-r1", f"nl-{lab.name}-r2"]
    )
    record = manifest.load(lab.name)
    assert record is not None and set(record.robots) == {"r1", "r2"}
    assert record.robots["r2"].address == "10.1.0.2/16"
    assert lab.robot("r1").mac == naming.mac_for(0, 0)
    with pytest.raises(LabExistsError, match="already up"):
        Lab(lab.name).up()
    assert manifest.load(lab.name) is not None  # the refused lab did not release the name
    out = lab.exec("r1", ["ip", "-o", "link", "show", "eth0"]).stdout
    assert naming.mac_for(0, 0) in out


def test_a_with_block_that_fails_keeps_the_lab_folder_and_says_where() -> None:
    """`with Lab(...)` in a user's test: when the block raises, the lab goes down but its folder
    (daemon logs, state) stays, and the error names it; a block that ends well leaves nothing."""
    with pytest.raises(RuntimeError, match="on purpose") as info, Lab(unique_lab_name()) as lab:
        lab.add_robot("r1")
        log = lab.robot("r1").log
        log.parent.mkdir(parents=True, exist_ok=True)  # (made when its sdfrd starts)
        log.write_text("what the daemon said\n")
        raise RuntimeError("on purpose")
    try:
        assert not kernel.list_ns(naming.prefix(lab.name))  # the lab itself is gone
        assert log.read_text() == "what the daemon said\n"
        notes = "\n".join(getattr(info.value, "__notes__", []))
        if sys.version_info >= (3, 11):
            assert (
                f"lab {lab.name}: its folder (daemon logs, state) is kept in {lab.workdir}" in notes
            )
    finally:
        shutil.rmtree(lab.workdir, ignore_errors=True)
    with Lab(unique_lab_name()) as fine:
        fine.add_robot("r1")
    assert not fine.workdir.exists()


def test_a_robot_that_fails_half_way_leaves_nothing_behind(
    make_lab: Callable[..., Lab], monkeypatch: pytest.MonkeyPatch
) -> None:
    lab = make_lab(1)

    def attach(robot_ns: str, port: str, mac: str) -> None:
        raise KernelError("linking failed on purpose")

    monkeypatch.setattr(lab.medium, "attach", attach)
    with pytest.raises(KernelError, match="on purpose"):
        lab.add_robot("r2")
    record = manifest.load(lab.name)
    assert record is not None and list(record.robots) == ["r1"]
    assert kernel.list_ns(naming.prefix(lab.name)) == [naming.air_ns(lab.name), f"nl-{lab.name}-r1"]
    monkeypatch.undo()
    assert str(lab.add_robot("r2").address) == "10.1.0.2/16"  # same index as the failed one
    assert pings(lab, "r1", "r2")


def test_multicast_reaches_linked_robots_only(make_lab: Callable[..., Lab]) -> None:
    lab = make_lab(range_model=UnitDisc(15.0))
    for i, x in enumerate((0.0, 10.0, 20.0, 100.0)):
        lab.add_robot(f"r{i + 1}", pos=(x, 0.0))
    assert lab.neighbours("r2") == {"r1", "r3"}
    got = send_and_count(lab, "r2", ["r1", "r3", "r4"])
    assert got == {"r1": 20, "r3": 20, "r4": 0}
    got = send_and_count(lab, "r1", ["r2", "r3", "r4"])
    assert got == {"r2": 20, "r3": 0, "r4": 0}
    # ARP and unicast obey the same per-pair rules.
    assert pings(lab, "r1", "r2")
    assert not pings(lab, "r1", "r3")


def test_partition_and_merge_take_effect(make_lab: Callable[..., Lab]) -> None:
    lab = make_lab(4)
    lab.partition([["r1", "r2"], ["r3", "r4"]])
    assert lab.neighbours("r1") == {"r2"}
    assert send_and_count(lab, "r1", ["r2", "r3", "r4"]) == {"r2": 20, "r3": 0, "r4": 0}
    assert not pings(lab, "r4", "r1")
    lab.merge()
    assert lab.neighbours("r1") == {"r2", "r3", "r4"}
    assert send_and_count(lab, "r1", ["r2", "r3", "r4"]) == {"r2": 20, "r3": 20, "r4": 20}
    assert pings(lab, "r4", "r1")


def test_moving_out_of_range_stops_traffic(make_lab: Callable[..., Lab]) -> None:
    lab = make_lab(2, range_model=UnitDisc(10.0))
    assert pings(lab, "r1", "r2")
    lab.move("r2", (10.5, 0.0))
    assert lab.links() == {}
    assert send_and_count(lab, "r1", ["r2"]) == {"r2": 0}
    assert not pings(lab, "r1", "r2")
    lab.move("r2", (0.0, 9.0))
    assert send_and_count(lab, "r1", ["r2"]) == {"r2": 20}


def test_per_pair_loss_is_about_right_and_one_way(make_lab: Callable[..., Lab]) -> None:
    lab = make_lab(3)
    lab.set_pair_quality("r1", "r2", loss=30, both=False)
    assert lab.links()[("r1", "r2")] == 30 and lab.links()[("r2", "r1")] == 0
    got = send_and_count(lab, "r1", ["r2", "r3"], 400, gap=0.001)
    lost = 1 - got["r2"] / 400
    assert 0.20 <= lost <= 0.40, f"{lost:.0%} lost with 30 % configured"
    assert got["r3"] == 400
    assert send_and_count(lab, "r2", ["r1"], 100, gap=0.001) == {"r1": 100}


def test_link_loss_without_netem_goes_through_the_medium(make_lab: Callable[..., Lab]) -> None:
    if capabilities().netem:
        pytest.skip("this kernel has netem: link loss is a qdisc, tested in the netem tier")
    lab = make_lab(3)
    lab.shape("r1", loss=30)
    assert lab.links()[("r1", "r2")] == pytest.approx(30) == lab.links()[("r3", "r1")]
    assert "jump loss_3000" in lab.medium.rules()
    got = send_and_count(lab, "r3", ["r1", "r2"], 400, gap=0.001)
    lost = 1 - got["r1"] / 400
    assert 0.20 <= lost <= 0.40, f"{lost:.0%} lost into r1 with 30 % configured"
    assert got["r2"] == 400
    lab.shape("r1")  # back to no shaping at all
    assert lab.links()[("r1", "r2")] == 0 and "numgen" not in lab.medium.rules()


def test_doctor_and_unsupported_shaping_name_the_module(make_lab: Callable[..., Lab]) -> None:
    caps = capabilities()
    assert caps.lab and caps.numgen and caps.tbf
    if caps.netem:
        pytest.skip("this kernel has netem: nothing is refused")
    assert "sch_netem" in caps.why["netem"]
    assert "tc netem (sch_netem)    NO" in format_report(caps)
    lab = make_lab(1)
    for params in ({"delay": 50}, {"delay": 50, "loss": 10}, {"corrupt": 1}):
        with pytest.raises(ShapingUnsupported, match="sch_netem"):
            lab.shape("r1", **params)
    # Refused before anything changed.
    assert lab.shape_of("r1").is_none and lab.links() == {}
    out = lab.exec("r1", ["tc", "qdisc", "show", "dev", "eth0"]).stdout
    assert "tbf" not in out and "netem" not in out


def test_tbf_limits_the_rate_and_resets(make_lab: Callable[..., Lab]) -> None:
    lab = make_lab(2)
    r2 = lab.robot("r2").ip

    def mbit_per_s(seconds: float) -> float:
        # Blast 1000-byte datagrams for `seconds`; the rate between first and last arrival.
        got = exchange(
            lab, "r1", ["r2"], 10**7, size=1000, gap=0, dest=r2, limit=seconds, listen=seconds + 1
        )["r2"]
        assert got.span > seconds / 2
        return got.nbytes * 8 / got.span / 1e6

    lab.shape("r1", rate="2mbit")
    out = lab.exec("r1", ["tc", "qdisc", "show", "dev", "eth0"]).stdout
    assert "tbf" in out and "2Mbit" in out
    # Both directions: what r1 receives passes the same limit on its air-side port.
    air = kernel.run_in_ns(lab.medium.ns, ["tc", "qdisc", "show", "dev", "vr1"], "tc")
    assert "tbf" in air and "2Mbit" in air
    shaped = mbit_per_s(1.0)
    assert 1.5 <= shaped <= 2.5, f"{shaped:.2f} Mbit/s through a 2 Mbit/s link"
    lab.shape("r1")
    assert "tbf" not in lab.exec("r1", ["tc", "qdisc", "show", "dev", "eth0"]).stdout
    assert "tbf" not in kernel.run_in_ns(lab.medium.ns, ["tc", "qdisc", "show", "dev", "vr1"], "tc")
    assert mbit_per_s(0.5) > 10 * shaped
    lab.shape("r1")  # resetting what is not shaped is fine


def test_mobility_drives_the_medium(make_lab: Callable[..., Lab]) -> None:
    lab = make_lab(4, range_model=UnitDisc(6.0))
    model = RandomWaypoint(list(lab.robots), seed=5, speed=(1.0, 2.0))
    now = [0.0]  # virtual time: the run does not sleep for real

    def sleep(seconds: float) -> None:
        now[0] += seconds

    timeline = lab.run_mobility(model, 30.0, 0.5, clock=lambda: now[0], sleep=sleep)
    assert [t for t, _ in timeline] == [k * 0.5 for k in range(61)]
    assert len({frozenset(links) for _, links in timeline}) > 1  # connectivity changed
    assert lab.positions() == model.positions_at(30.0)
    expected = Topology(UnitDisc(6.0))
    for name, pos in model.positions_at(30.0).items():
        expected.add(name, pos)
    assert lab.links() == expected.links() == timeline[-1][1]
    # The kernel holds exactly the final links.
    text = lab.medium.rules()
    for a in lab.robots:
        for b in lab.robots:
            if a != b:
                assert (f'"v{a}" . "v{b}"' in text) == ((a, b) in lab.links())


def test_leftover_namespaces_block_up_until_netlab_down(tmp_path: Path) -> None:
    name = unique_lab_name()
    stray = naming.robot_ns(name, "zz")
    kernel.create_ns(stray).close()
    try:
        with pytest.raises(LabExistsError, match=f"netlab down {name}"):
            Lab(name, workdir=tmp_path).up()
        assert manifest.load(name) is None
        assert kernel.list_ns(naming.prefix(name)) == [stray]  # not ours to remove silently
        down = netlab_cli("down", name)
        assert down.returncode == 0 and "1 namespaces" in down.stdout
        assert kernel.list_ns(naming.prefix(name)) == []
    finally:
        kernel.remove_ns(stray)


def test_cli_up_exec_status_down() -> None:
    name = unique_lab_name()
    try:
        up = netlab_cli("up", name, "--robots", "2", "--seed", "3")
        assert up.returncode == 0, up.stderr
        assert f"netlab down {name}" in up.stdout
        ex = netlab_cli("exec", name, "r2", "--", "ip", "-o", "-4", "addr", "show", "eth0")
        assert ex.returncode == 0 and "10.1.0.2/16" in ex.stdout
        assert netlab_cli("exec", name, "r9", "--", "true").returncode == 1
        st = netlab_cli("status", name)
        assert st.returncode == 0 and naming.mac_for(3, 1) in st.stdout
        again = netlab_cli("up", name, "--robots", "1")
        assert again.returncode == 1 and "already up" in again.stderr
    finally:
        down = netlab_cli("down", name, "--cleanup")
    assert down.returncode == 0 and "3 namespaces" in down.stdout
    assert netlab_cli("status", name).returncode == 1


def netlab_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "netlab.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )


def test_netlab_down_sweeps_a_lab_whose_runner_was_killed(tmp_path: Path) -> None:
    name = unique_lab_name()
    runner_code = f"""
import json, sys, time
from pathlib import Path
from netlab.lab import Lab
lab = Lab({name!r}).up()
lab.add_robots(["a", "b"])
sleeper = lab.popen("a", ["sleep", "600"])
lab.start("b", beacon_interval=0.5)
print(json.dumps({{"sleeper": sleeper.pid, "sdfrd": lab._daemons["b"].pid,
                   "workdir": str(lab.workdir)}}), flush=True)
time.sleep(600)
"""
    runner = subprocess.Popen(
        [sys.executable, "-c", runner_code],
        stdout=subprocess.PIPE,
        text=True,
        stdin=subprocess.DEVNULL,
    )
    stray: subprocess.Popen[bytes] | None = None
    try:
        info = json.loads(_readline(runner, 60.0))
        layers = json.loads((Path(info["workdir"]) / "b" / "state" / "layers.json").read_text())
        # Something started by hand in a robot, never recorded: still swept.
        stray = subprocess.Popen(kernel.ns_argv(f"nl-{name}-a", ["sleep", "600"]))
        os.kill(runner.pid, signal.SIGKILL)
        runner.wait(10)
        pids = [info["sleeper"], info["sdfrd"], *layers.values(), stray.pid]
        assert all(running(p) for p in pids)
        assert len(kernel.list_ns(naming.prefix(name))) == 3

        status = subprocess.run(
            [sys.executable, "-m", "netlab.cli", "status", name, "--json"],
            capture_output=True,
            text=True,
            timeout=30,
        )
        lab_state = json.loads(status.stdout)["labs"][0]
        assert lab_state["runner"]["alive"] is False
        assert lab_state["robots"]["b"]["sdfrd"] == info["sdfrd"]

        down = subprocess.run(
            [sys.executable, "-m", "netlab.cli", "down", name, "--cleanup"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert down.returncode == 0, down.stderr
        assert "3 namespaces" in down.stdout
        stray.wait(10)
        assert not any(running(p) for p in pids)
        assert kernel.list_ns(naming.prefix(name)) == []
        assert manifest.load(name) is None
        assert not Path(info["workdir"]).exists()
        again = subprocess.run(
            [sys.executable, "-m", "netlab.cli", "down", name],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert again.returncode == 0 and "nothing to remove" in again.stdout
    finally:
        for proc in (runner, stray):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
        subprocess.run(
            [sys.executable, "-m", "netlab.cli", "down", name, "--cleanup"],
            capture_output=True,
            timeout=60,
        )


# -- the real daemon -------------------------------------------------------------------------

BEACON = 0.5


def test_daemons_follow_partition_and_merge(make_lab: Callable[..., Lab]) -> None:
    lab = make_lab(3)
    lab.start_all(beacon_interval=BEACON)

    def listed(robot: str) -> set[str]:
        return {n["robot_id"] for n in lab.client(robot).neighbors()}

    def agree() -> bool:
        return all(listed(r) == lab.neighbours(r) for r in lab.robots)

    poll("all see all", agree, 5.0)
    assert listed("r1") == {"r2", "r3"}

    lab.partition([["r1"], ["r2", "r3"]])
    took = poll("each side drops the other", agree, 3 * BEACON + 1.0)
    assert listed("r1") == set() and listed("r2") == {"r3"}
    assert took <= 3 * BEACON + 1.0

    lab.merge()
    poll("all see all again", agree, 5.0)

    # Silent death vs. graceful stop, and a restart on the same state.
    lab.kill("r3")
    poll("r3 dropped after its silence", lambda: "r3" not in listed("r1"), 3 * BEACON + 1.0)
    lab.restart("r3")
    poll("r3 back", lambda: "r3" in listed("r1"), 5.0)
    assert lab.stop("r3") == 0
    # Byebye: well before the 3 silent beacon periods a kill needs.
    took = poll("r3 gone at once (Byebye)", lambda: "r3" not in listed("r1"), 1.0)
    assert took < 2 * BEACON


def test_a_daemon_that_ends_unasked_is_named_with_its_signal_and_its_stack(
    make_lab: Callable[..., Lab],
) -> None:
    """The lab tells a daemon that crashed or was killed from elsewhere from one it stopped
    or killed itself; a native crash leaves every thread's Python stack in the robot's log."""
    lab = make_lab(4)
    lab.start_all(beacon_interval=BEACON)
    assert lab.daemons_ended() == {}
    lab.stop("r1")
    lab.kill("r2")
    pid3, pid4 = lab.daemon_pid("r3"), lab.daemon_pid("r4")
    assert pid3 is not None and pid4 is not None
    os.kill(pid3, signal.SIGKILL)  # not the lab's doing
    os.kill(pid4, signal.SIGSEGV)  # as a crash in native code would
    poll("both ended", lambda: len(lab.daemons_ended()) == 2 or str(lab.daemons_ended()), 10)
    assert lab.daemons_ended() == {"r3": "signal 9 (SIGKILL)", "r4": "signal 11 (SIGSEGV)"}
    log = lab.robot("r4").log.read_text(errors="replace")
    assert "Fatal Python error: Segmentation fault" in log
    assert log.count("(most recent call first)") >= 3, log[-2000:]  # main, api, discovery
    lab.restart("r3")
    assert lab.daemons_ended() == {"r4": "signal 11 (SIGSEGV)"}


def test_leftovers_name_what_is_left_of_a_lab(lab: Lab) -> None:
    left = cleanup.leftovers(lab.name)
    assert f"namespace {naming.air_ns(lab.name)}" in left
    assert f"manifest {manifest.path_of(lab.name)}" in left
    lab.down()
    assert cleanup.leftovers(lab.name) == []
