"""The ROS 2 probe (rclpy): see probe_common.  Run with .venv/ros2/bin/python."""

from __future__ import annotations

import threading
import time
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sdfr_msgs.msg import Change, NeighborList, Service
from sdfr_msgs.srv import List, Search

from sdfr.ros import messages as conv
from sdfr.ros.ros2 import interfaces
from tests.ros.probe_common import Recorded, has_service, serve, to_py


class Probe:
    def __init__(self, prefix: str) -> None:
        rclpy.init()
        self.m = interfaces()
        self.node = rclpy.create_node("sdfr_probe")
        latched = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.neighbors, self.changes, self.diagnostics = Recorded(), Recorded(), Recorded()
        n = self.node
        n.create_subscription(NeighborList, f"{prefix}/neighbors", self.neighbors.add, latched)
        self.changes_topic = f"{prefix}/changes"
        n.create_subscription(Change, self.changes_topic, self.changes.add, reliable)
        n.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.add, 10)
        self.pub = n.create_publisher(Service, f"{prefix}/publish", reliable)
        self.unpub = n.create_publisher(Service, f"{prefix}/unpublish", reliable)
        self.search = n.create_client(Search, f"{prefix}/search")
        self.list = n.create_client(List, f"{prefix}/list")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(n)
        threading.Thread(target=self.executor.spin, daemon=True).start()

    def _call(self, client: Any, request: Any, timeout: float) -> Any:
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"service {client.srv_name} not available within {timeout} s")
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout):
            raise TimeoutError(f"no answer from {client.srv_name} within {timeout} s")
        return to_py(future.result())

    def _service(self, service: dict[str, Any]) -> Any:
        return Service(
            id=service.get("id", ""),
            name=service["name"],
            type=service["type"],
            url=service.get("url", ""),
            attributes=[self._attribute(a) for a in service.get("attributes", [])],
        )

    def _attribute(self, a: Any) -> Any:
        if isinstance(a, list):  # [key, value]: typed from the JSON value
            return conv.attribute_msg(self.m, a[0], a[1])
        return self.m.Attribute(**a)  # the message's fields as they are (bad input too)

    # -- commands --------------------------------------------------------------------------

    def op_ready(self, timeout: float = 30.0) -> dict[str, Any]:
        """The node's services answer, it subscribes to our topics, and its latched list came."""
        deadline = time.monotonic() + timeout
        for pub in (self.pub, self.unpub):
            while pub.get_subscription_count() == 0:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"nobody subscribes to {pub.topic_name}")
                time.sleep(0.05)
        for client in (self.search, self.list):
            if not client.wait_for_service(timeout_sec=max(0.1, deadline - time.monotonic())):
                raise TimeoutError(f"service {client.srv_name} not available")
        # ~/changes keeps nothing for a late subscriber: the node's publisher must be known.
        while self.node.count_publishers(self.changes_topic) == 0:
            if time.monotonic() > deadline:
                raise TimeoutError(f"nobody publishes {self.changes_topic}")
            time.sleep(0.05)
        _t, first = self.neighbors.first(lambda _: True, 0.0, max(0.1, deadline - time.monotonic()))
        return {"neighbors": first}

    def op_publish(self, service: dict[str, Any]) -> dict[str, Any]:
        msg = self._service(service)
        t = time.time()
        self.pub.publish(msg)
        return {"t": t}

    def op_unpublish(self, service: dict[str, Any]) -> dict[str, Any]:
        msg = self._service(service)
        t = time.time()
        self.unpub.publish(msg)
        return {"t": t}

    def op_wait_neighbors(
        self, robot: str, name: str | None = None, present: bool = True, since: float = 0.0,
        timeout: float = 30.0,
    ) -> dict[str, Any]:  # fmt: skip
        t, nl = self.neighbors.first(has_service(robot, name, present), since, timeout)
        return {"t": t, "msg": nl}

    def op_search(self, type: str, attributes: list[Any], timeout: float = 10.0) -> dict[str, Any]:
        request = Search.Request(type=type, attributes=[self._attribute(a) for a in attributes])
        return {"response": self._call(self.search, request, timeout)}

    def op_list(self, include_unreachable: bool = False, timeout: float = 10.0) -> dict[str, Any]:
        request = List.Request(include_unreachable=include_unreachable)
        return {"response": self._call(self.list, request, timeout)}

    def op_changes(self) -> dict[str, Any]:
        with self.changes.cond:
            return {"changes": [c for _, c in self.changes.items]}

    def op_diagnostics(self, since: float = 0.0, timeout: float = 10.0) -> dict[str, Any]:
        t, d = self.diagnostics.first(lambda _: True, since, timeout)
        return {"t": t, "msg": d}


if __name__ == "__main__":
    import sys

    probe = Probe(sys.argv[1] if len(sys.argv) > 1 else "/sdfr")
    try:
        serve(probe)
    finally:
        probe.executor.shutdown()
        probe.node.destroy_node()
        rclpy.try_shutdown()
