"""The ROS 1 node `sdfr` (rospy): a thin adapter of `sdfr.ros.core.Bridge`.

    roslaunch sdfr_ros sdfr.launch fleet:=3          (ros/sdfr_ros/launch/sdfr.launch)
    .venv/ros1/bin/python -m sdfr.ros.ros1 _fleet:=3

The graph is the ROS 2 node's (`sdfr.ros.ros2`): ~publish, ~unpublish (sdfr_msgs/Service,
in), ~neighbors (sdfr_msgs/NeighborList, latched), ~changes (sdfr_msgs/Change), services
~search and ~list, and /diagnostics.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Sequence
from typing import Any

from sdfr.errors import ConfigError
from sdfr.ros import messages as conv
from sdfr.ros.core import Bridge, BridgeError, Change, Diagnosis, Snapshot
from sdfr.ros.params import NodeParams
from sdfr.ros.spawn import SpawnError

NODE_NAME = "sdfr"

try:
    import rospy
    import sdfr_msgs.msg as sdfr_msg
    import sdfr_msgs.srv as sdfr_srv
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from std_msgs.msg import Header
except ImportError as exc:  # pragma: no cover - depends on the environment
    _MISSING: ImportError | None = exc
else:
    _MISSING = None


def _time(t: float) -> Any:
    sec, nsec = conv.split_time(t)
    return rospy.Time(sec, nsec)


def interfaces() -> conv.Interfaces:
    return conv.Interfaces(
        Attribute=sdfr_msg.Attribute,
        Service=sdfr_msg.Service,
        Robot=sdfr_msg.Robot,
        NeighborList=sdfr_msg.NeighborList,
        Change=sdfr_msg.Change,
        DiagnosticArray=DiagnosticArray,
        DiagnosticStatus=DiagnosticStatus,
        KeyValue=KeyValue,
        Header=Header,
        time=_time,
        level=int,
    )


class Ros1Node:
    """The node's publishers, subscribers and services around a bridge."""

    def __init__(self, params: NodeParams) -> None:
        self.m = interfaces()
        self.neighbors_pub = rospy.Publisher(
            "~neighbors", sdfr_msg.NeighborList, queue_size=1, latch=True
        )
        self.changes_pub = rospy.Publisher("~changes", sdfr_msg.Change, queue_size=100)
        self.diag_pub = rospy.Publisher("/diagnostics", DiagnosticArray, queue_size=10)
        self.bridge = Bridge(params, self)

    def open(self) -> None:
        self.bridge.start()
        rospy.Subscriber("~publish", sdfr_msg.Service, self._on_publish, queue_size=100)
        rospy.Subscriber("~unpublish", sdfr_msg.Service, self._on_unpublish, queue_size=100)
        rospy.Service("~search", sdfr_srv.Search, self._on_search)
        rospy.Service("~list", sdfr_srv.List, self._on_list)
        spawned = self.bridge.spawned
        rospy.loginfo(
            f"bridging sdfrd at {self.bridge.params.api} (robot {self.bridge.robot_id or '?'})"
            + (f"; started it: {' '.join(spawned.argv)}" if spawned else "")
        )

    def close(self) -> None:
        self.bridge.close()

    # -- Sink ----------------------------------------------------------------------------------

    def neighbors(self, snapshot: Snapshot, robot_id: str) -> None:
        self.neighbors_pub.publish(conv.neighbor_list_msg(self.m, snapshot, robot_id))

    def changes(self, changes: Sequence[Change]) -> None:
        for change in changes:
            self.changes_pub.publish(conv.change_msg(self.m, change))

    def diagnostics(self, diagnosis: Diagnosis) -> None:
        self.diag_pub.publish(conv.diagnostic_msg(self.m, diagnosis, time.time()))

    # -- requests ------------------------------------------------------------------------------

    def _on_publish(self, msg: Any) -> None:
        try:
            sid = self.bridge.publish(conv.request_from_msg(msg))
        except BridgeError as exc:
            rospy.logerr(f"~publish: {exc}")
        else:
            rospy.loginfo(f"published {msg.name!r} as {sid}")

    def _on_unpublish(self, msg: Any) -> None:
        try:
            sid = self.bridge.unpublish(conv.request_from_msg(msg))
        except BridgeError as exc:
            rospy.logerr(f"~unpublish: {exc}")
        else:
            rospy.loginfo(f"unpublished {sid}")

    def _on_search(self, request: Any) -> Any:
        response = sdfr_srv.SearchResponse()
        try:
            attrs = conv.attributes_from_msgs(request.attributes)
            response.robots = conv.robot_msgs(self.m, self.bridge.search(request.type, attrs))
            response.success = True
        except BridgeError as exc:
            response.success, response.message = False, str(exc)
        return response

    def _on_list(self, request: Any) -> Any:
        response = sdfr_srv.ListResponse()
        try:
            listing = self.bridge.listing(bool(request.include_unreachable))
        except BridgeError as exc:
            response.success, response.message = False, str(exc)
            return response
        response.success = True
        response.robot_id = listing.robot_id
        response.services = [conv.service_msg(self.m, s) for s in listing.services]
        response.robots = conv.robot_msgs(self.m, listing.robots)
        return response


def read_params() -> NodeParams:
    """The node's private parameters (~name); an unknown one is an error naming it."""
    given = rospy.get_param("~", {})
    if not isinstance(given, dict):
        raise ConfigError(f"the node's parameters are not a mapping: {given!r}")
    return NodeParams.from_mapping(given)


def main(argv: Sequence[str] | None = None) -> int:
    if _MISSING is not None:
        print(
            f"sdfr-ros1: ROS 1 is not importable here ({_MISSING}); run it with the "
            "interpreter of the ROS 1 environment (make ros1-setup: .venv/ros1/bin/python)",
            file=sys.stderr,
        )
        return 2
    rospy.init_node(NODE_NAME, argv=list(argv) if argv is not None else sys.argv)
    # rospy takes over the root logger's handlers; the core's records go to rosout with it.
    logging.getLogger("sdfr.ros").setLevel(logging.INFO)
    node: Ros1Node | None = None
    try:
        node = Ros1Node(read_params())
        node.open()
        rospy.spin()
    except (ConfigError, SpawnError) as exc:
        rospy.logfatal(str(exc))
        return 1
    finally:
        if node is not None:
            node.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
