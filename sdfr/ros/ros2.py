"""The ROS 2 node `sdfr` (rclpy): a thin adapter of `sdfr.ros.core.Bridge`.

    python -m sdfr.ros.ros2 --ros-args --params-file ros/config/sdfr.params.yaml -p fleet:=3

Graph (names relative to the node, `/sdfr/...` by default):
  ~/publish, ~/unpublish     sdfr_msgs/msg/Service        in
  ~/neighbors                sdfr_msgs/msg/NeighborList   out, reliable, transient-local
  ~/changes                  sdfr_msgs/msg/Change         out, reliable
  ~/search                   sdfr_msgs/srv/Search         service
  ~/list                     sdfr_msgs/srv/List           service
  /diagnostics               diagnostic_msgs/msg/DiagnosticArray
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
from sdfr.ros.params import DESCRIPTIONS, NodeParams
from sdfr.ros.spawn import SpawnError

NODE_NAME = "sdfr"
#: Parameters every rclpy node has; not the bridge's.
_ROS_OWN = {"use_sim_time", "start_type_description_service"}

try:
    import rclpy
    import sdfr_msgs.msg as sdfr_msg
    import sdfr_msgs.srv as sdfr_srv
    from builtin_interfaces.msg import Time
    from diagnostic_msgs import msg as diagnostic_msg
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs import msg as std_msg
except ImportError as exc:  # pragma: no cover - depends on the environment
    _MISSING: ImportError | None = exc
else:
    _MISSING = None


def _stamp(sec: int, nanosec: int) -> Any:
    return Time(sec=sec, nanosec=nanosec)


def interfaces() -> conv.Interfaces:
    return conv.Interfaces.of(
        sdfr_msg, diagnostic_msg, std_msg, stamp=_stamp, level=lambda level: bytes([level])
    )


class Ros2Node(NodeAdapter):
    """The node's publishers, subscriptions and services around a bridge."""

    def __init__(self, node: Any, params: NodeParams) -> None:
        self.node = node
        log = node.get_logger()
        self.info, self.error = log.info, log.error
        self.m = interfaces()
        latched = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.neighbors_pub = node.create_publisher(sdfr_msg.NeighborList, "~/neighbors", latched)
        self.changes_pub = node.create_publisher(sdfr_msg.Change, "~/changes", reliable)
        self.diag_pub = node.create_publisher(diagnostic_msg.DiagnosticArray, "/diagnostics", 10)
        self.bridge = Bridge(params, self)

    def open(self) -> None:
        """Start the bridge (and sdfrd if needed), then take requests."""
        self.bridge.start()
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        node = self.node
        node.create_subscription(sdfr_msg.Service, "~/publish", self.on_publish, reliable)
        node.create_subscription(sdfr_msg.Service, "~/unpublish", self.on_unpublish, reliable)
        node.create_service(sdfr_srv.Search, "~/search", self.search)
        node.create_service(sdfr_srv.List, "~/list", self.list)
        self.announce()


def read_params(node: Any) -> NodeParams:
    """The node's parameters: declared with their defaults and descriptions; any other
    parameter given to the node (a typo in the YAML file) is an error naming it."""
    defaults = NodeParams()
    for name, description in DESCRIPTIONS.items():
        if not node.has_parameter(name):
            node.declare_parameter(
                name, getattr(defaults, name), ParameterDescriptor(description=description)
            )
    names = set(node.list_parameters([], 0).names) - _ROS_OWN
    return NodeParams.from_mapping({n: node.get_parameter(n).value for n in names})


def main(argv: Sequence[str] | None = None) -> int:
    if _MISSING is not None:
        return not_importable(2, _MISSING)
    logging.basicConfig(level=logging.INFO, format="[sdfr.ros] %(levelname)s %(message)s")
    rclpy.init(args=list(argv) if argv is not None else None)
    node = rclpy.create_node(
        NODE_NAME,
        allow_undeclared_parameters=True,
        automatically_declare_parameters_from_overrides=True,
    )
    adapter: Ros2Node | None = None
    code = 0
    try:
        params = read_params(node)
        adapter = Ros2Node(node, params)
        adapter.open()
        rclpy.spin(node)
    except (ConfigError, SpawnError) as exc:
        node.get_logger().fatal(str(exc))
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if adapter is not None:
            adapter.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
