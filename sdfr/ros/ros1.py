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
from collections.abc import Sequence
from typing import Any

from sdfr.errors import ConfigError
from sdfr.ros import messages as conv
from sdfr.ros.adapter import NodeAdapter, not_importable
from sdfr.ros.core import Bridge
from sdfr.ros.params import NodeParams
from sdfr.ros.spawn import SpawnError

NODE_NAME = "sdfr"

try:
    import rospy
    import sdfr_msgs.msg as sdfr_msg
    import sdfr_msgs.srv as sdfr_srv
    from diagnostic_msgs import msg as diagnostic_msg
    from std_msgs import msg as std_msg
except ImportError as exc:  # pragma: no cover - depends on the environment
    _MISSING: ImportError | None = exc
else:
    _MISSING = None


def interfaces() -> conv.Interfaces:
    return conv.Interfaces.of(sdfr_msg, diagnostic_msg, std_msg, stamp=rospy.Time, level=int)


class Ros1Node(NodeAdapter):
    """The node's publishers, subscribers and services around a bridge."""

    private = "~"

    def __init__(self, params: NodeParams) -> None:
        self.m = interfaces()
        self.info, self.error = rospy.loginfo, rospy.logerr
        self.neighbors_pub = rospy.Publisher(
            "~neighbors", sdfr_msg.NeighborList, queue_size=1, latch=True
        )
        self.changes_pub = rospy.Publisher("~changes", sdfr_msg.Change, queue_size=100)
        self.diag_pub = rospy.Publisher(
            "/diagnostics", diagnostic_msg.DiagnosticArray, queue_size=10
        )
        self.bridge = Bridge(params, self)

    def open(self) -> None:
        self.bridge.start()
        rospy.Subscriber("~publish", sdfr_msg.Service, self.on_publish, queue_size=100)
        rospy.Subscriber("~unpublish", sdfr_msg.Service, self.on_unpublish, queue_size=100)
        rospy.Service("~search", sdfr_srv.Search, self._on_search)
        rospy.Service("~list", sdfr_srv.List, self._on_list)
        self.announce()

    def _on_search(self, request: Any) -> Any:
        return self.search(request, sdfr_srv.SearchResponse())

    def _on_list(self, request: Any) -> Any:
        return self.list(request, sdfr_srv.ListResponse())


def read_params() -> NodeParams:
    """The node's private parameters (~name); an unknown one is an error naming it."""
    given = rospy.get_param("~", {})
    if not isinstance(given, dict):
        raise ConfigError(f"the node's parameters are not a mapping: {given!r}")
    return NodeParams.from_mapping(given)


def main(argv: Sequence[str] | None = None) -> int:
    if _MISSING is not None:
        return not_importable(1, _MISSING)
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
