"""A robot of the side-by-side bench done with ROS 2's own discovery (rclpy on Fast DDS) instead
of SDfR.

Run inside a robot's namespace with the ROS 2 interpreter (.venv/ros2, scripts/ros2-setup.sh),
the way a ROS 2 team shares what each robot offers: one node per robot (one DDS participant,
found by the SPDP/SEDP multicast discovery every ROS 2 fleet runs) and one latched topic,
``/sdfrbench/services`` (std_msgs/String; reliable, transient local, keep last 1: a late
joiner gets each robot's last message), on which each robot publishes the JSON of all its
services with their attributes whenever one comes or goes.  A service of another robot is
*listed* once a message of that robot's lists it, and gone when a later one does not.

A robot's departure is DDS's to notice: a graceful leave destroys the node (its participant
says it goes); a silent one (kill -9, a cut link) ends its writer's match when its
participant's lease expires (Fast DDS's default: 20 s; `--lease-s` sets it through a Fast
DDS XML profile, announcing three times a lease).  On every lost match the node asks the ROS
graph which writers are left and drops the robots whose writer is gone (the graph can lag the
event, so it asks again for up to `RECHECK_S`).

Only UDPv4 (``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``): Fast DDS would otherwise pass data between
robots through shared memory, around the lab's medium.  `--domain` (ROS_DOMAIN_ID, default 0)
lets a second DDS fleet run apart in the same lab: domain d uses UDP ports 7400 + 250 d
(multicast discovery), + 10 and + 11 (a participant's own).  Its command line, churn, signals
and event log are `bench.peer_node`'s.
"""

from __future__ import annotations

import asyncio
import contextlib
import faulthandler
import json
import os
import sys
import threading
import time
from typing import Any

from bench.peer_node import PeerNode, arguments, attributes

TOPIC = "/sdfrbench/services"
RECHECK_S = (0.0, 0.2, 0.5, 1.0, 2.0, 5.0)  # when to ask the graph again after a lost match
READER_DEPTH = 256  # one message per robot may wait at once: more than a lab's robots

LEASE_PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <participant profile_name="sdfrbench_lease" is_default_profile="true">
      <rtps>
        <builtin>
          <discovery_config>
            <leaseDuration><sec>{sec}</sec><nanosec>{nsec}</nanosec></leaseDuration>
            <leaseAnnouncement><sec>{asec}</sec><nanosec>{ansec}</nanosec></leaseAnnouncement>
          </discovery_config>
        </builtin>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def duration(seconds: float) -> tuple[int, int]:
    whole = int(seconds)
    return whole, round((seconds - whole) * 1e9)


def lease_profile(lease_s: float) -> str:
    """A Fast DDS XML profile giving every participant a lease of `lease_s`, announced three
    times a lease (Fast DDS's defaults: 20 s and 3 s)."""
    sec, nsec = duration(lease_s)
    asec, ansec = duration(lease_s / 3)
    return LEASE_PROFILE.format(sec=sec, nsec=nsec, asec=asec, ansec=ansec)


def environment(domain: int, lease_s: float | None, profile: str) -> dict[str, str]:
    """What Fast DDS and rclpy must find in the environment before they start (with a lease,
    its profile is written to the file `profile`)."""
    env = {
        "ROS_DOMAIN_ID": str(domain),
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
    }
    if lease_s is not None:
        with open(profile, "w") as f:
            f.write(lease_profile(lease_s))
        env["FASTDDS_DEFAULT_PROFILES_FILE"] = profile
    return env


def robot_of(msg: str) -> tuple[str, dict[str, Any]] | None:
    """(robot, its services) of one message on the topic, or None if it is not one."""
    try:
        body = json.loads(msg)
        return str(body["robot"]), dict(body["services"])
    except (ValueError, KeyError, TypeError):
        return None


class Node(PeerNode):
    def __init__(self, args: Any, events: Any) -> None:
        super().__init__(args, events)
        self.loop: asyncio.AbstractEventLoop
        self.attrs: dict[str, dict[str, str]] = {}  # my services: sid -> attributes
        self.theirs: dict[str, set[str]] = {}  # robot -> the sids its last message listed
        self.writer_of: dict[str, bytes] = {}  # robot -> its writer's gid
        self.lock = threading.Lock()  # rclpy's thread publishes too (on a new match)
        self.rclpy: Any
        self.node: Any
        self.pub: Any
        self.msg_type: Any
        self.spinner: threading.Thread
        self.executor: Any

    # -- what it publishes --------------------------------------------------------------------

    def send(self) -> None:
        with self.lock:
            body = {"robot": self.robot, "services": self.attrs}
            self.pub.publish(self.msg_type(data=json.dumps(body, separators=(",", ":"))))

    async def register(self, index: int, sid: str) -> Any:
        with self.lock:
            self.attrs[sid] = attributes(self.robot, index)
        self.send()
        return sid

    async def unregister(self, handle: Any) -> None:
        with self.lock:
            self.attrs.pop(handle, None)
        self.send()

    async def leave(self) -> None:
        """Stop spinning, then destroy the node and the context: its participant is deleted
        and says it goes (an SPDP dispose), as when a ROS 2 node ends."""
        t0 = time.perf_counter()
        self.rclpy.try_shutdown(context=self.node.context)
        await self.loop.run_in_executor(None, self.spinner.join, 5.0)
        self.node.destroy_node()
        self.node.context.destroy()
        self.left((time.perf_counter() - t0) * 1000)

    # -- what it lists: rclpy's thread hands over to the loop ---------------------------------

    def on_message(self, msg: Any, info: Any) -> None:
        got = robot_of(msg.data)
        if got is not None and got[0] != self.robot:
            gid = bytes(info.get("publisher_gid", {}).get("data", b"")) if info else b""
            self.loop.call_soon_threadsafe(self.listing, got[0], set(got[1]), gid)

    def listing(self, robot: str, sids: set[str], gid: bytes) -> None:
        if gid:
            self.writer_of[robot] = gid
        before = self.theirs.get(robot, set())
        self.theirs[robot] = sids
        for sid in sorted(before - sids):
            self.gone((robot, sid))
        for sid in sorted(sids):
            self.seen((robot, sid))

    def drop(self, robot: str) -> None:
        for sid in sorted(self.theirs.pop(robot, set())):
            self.gone((robot, sid))
        self.writer_of.pop(robot, None)

    def on_reader_matched(self, info: Any) -> None:
        self.note(f"reader matched: {info.current_count} writers ({info.current_count_change:+d})")
        if info.current_count_change < 0:
            self.loop.call_soon_threadsafe(self.spawn, self.recheck())

    def on_liveliness(self, info: Any) -> None:
        if info.not_alive_count_change > 0 or info.alive_count_change < 0:
            self.loop.call_soon_threadsafe(self.spawn, self.recheck())

    def on_writer_matched(self, info: Any) -> None:
        self.note(f"writer matched: {info.current_count} readers ({info.current_count_change:+d})")
        if info.current_count_change > 0:
            # A reader that matched late may miss the latched message in Fast DDS
            # (eProsima/Fast-DDS#3822): say it again.
            self.send()

    async def writers_left(self) -> set[bytes]:
        """The writers the ROS graph shows on the topic, asked in rclpy's own thread (the
        graph is not asked from two threads at once)."""
        answer: asyncio.Future[set[bytes]] = self.loop.create_future()

        def ask() -> None:
            try:
                infos = self.node.get_publishers_info_by_topic(TOPIC)
                got = {bytes(i.endpoint_gid) for i in infos}
                self.loop.call_soon_threadsafe(answer.set_result, got)
            except Exception as exc:  # (handed over to the loop, whatever it is)
                self.loop.call_soon_threadsafe(answer.set_exception, exc)

        self.executor.create_task(ask)
        return await answer

    async def recheck(self) -> None:
        """Drop the robots whose writer the graph no longer shows (asking again while it
        may lag the lost match)."""
        started = time.monotonic()
        for at in RECHECK_S:
            await asyncio.sleep(max(0.0, started + at - time.monotonic()))
            left = await self.writers_left()
            for robot, gid in list(self.writer_of.items()):
                if gid not in left:
                    self.drop(robot)

    def note(self, what: str) -> None:
        print(f"{time.time():.3f} {self.robot}: {what}", file=sys.stderr, flush=True)

    async def run(self) -> None:
        self.loop = asyncio.get_running_loop()
        import rclpy
        from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
        from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from std_msgs.msg import String

        self.rclpy, self.msg_type = rclpy, String
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f"sdfrbench_{self.robot}")

        def qos(depth: int) -> QoSProfile:
            return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                              reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL)  # fmt: skip

        self.pub = self.node.create_publisher(
            String, TOPIC, qos(1),
            event_callbacks=PublisherEventCallbacks(matched=self.on_writer_matched),
        )  # fmt: skip
        self.node.create_subscription(
            String, TOPIC, self.on_message, qos(READER_DEPTH),
            event_callbacks=SubscriptionEventCallbacks(
                matched=self.on_reader_matched, liveliness=self.on_liveliness),
        )  # fmt: skip
        self.executor = executor = SingleThreadedExecutor()
        executor.add_node(self.node)

        def spin() -> None:
            with contextlib.suppress(ExternalShutdownException):  # (a graceful leave)
                executor.spin()

        self.spinner = threading.Thread(target=spin, name="rclpy", daemon=True)
        self.spinner.start()
        self.send()  # (an empty list: this robot is here)
        await self.serve()


def main(argv: list[str] | None = None) -> int:
    p = arguments(__doc__ or "")
    p.add_argument("--lease-s", type=float, default=None,
                   help="the participants' lease (Fast DDS's default: 20 s), through an XML "
                        "profile announcing three times a lease")  # fmt: skip
    p.add_argument("--domain", type=int, default=0, help="ROS_DOMAIN_ID (default 0)")
    args = p.parse_args(argv)
    if args.lease_s is not None and args.lease_s <= 0:
        p.error(f"--lease-s must be more than 0, not {args.lease_s}")
    if not 0 <= args.domain <= 101:
        p.error(f"--domain must be 0-101 (ROS 2's domain ids over UDP), not {args.domain}")
    faulthandler.enable()  # (a crash in rclpy or Fast DDS leaves its stacks on stderr)
    # (The lease's profile beside the event log: the run folder says how DDS ran.)
    os.environ.update(environment(args.domain, args.lease_s, f"{args.events}.fastdds.xml"))
    with open(args.events, "w", buffering=1) as events:
        asyncio.run(Node(args, events).run())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
