"""The ROS 1 probe (rospy): see probe_common.  Run with .venv/ros1/bin/python."""

from __future__ import annotations

import sys
import time
from typing import Any

import rospy
from diagnostic_msgs.msg import DiagnosticArray
from sdfr_msgs.msg import Change, NeighborList, Service
from sdfr_msgs.srv import List, Search

from sdfr.ros import messages as conv
from sdfr.ros.ros1 import interfaces
from tests.ros.probe_common import Recorded, has_service, serve, to_py


class Probe:
    def __init__(self, prefix: str) -> None:
        rospy.init_node("sdfr_probe", anonymous=True, disable_signals=True)
        self.m = interfaces()
        self.neighbors, self.changes, self.diagnostics = Recorded(), Recorded(), Recorded()
        rospy.Subscriber(f"{prefix}/neighbors", NeighborList, self.neighbors.add)
        self.changes_sub = rospy.Subscriber(
            f"{prefix}/changes", Change, self.changes.add, queue_size=100
        )
        rospy.Subscriber("/diagnostics", DiagnosticArray, self.diagnostics.add)
        self.pub = rospy.Publisher(f"{prefix}/publish", Service, queue_size=100)
        self.unpub = rospy.Publisher(f"{prefix}/unpublish", Service, queue_size=100)
        self.search_name, self.list_name = f"{prefix}/search", f"{prefix}/list"

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
        return self.m.Attribute(**a)

    def _call(self, name: str, kind: Any, request: Any, timeout: float) -> Any:
        rospy.wait_for_service(name, timeout)
        return to_py(rospy.ServiceProxy(name, kind)(request))

    # -- commands --------------------------------------------------------------------------

    def op_ready(self, timeout: float = 30.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        for pub in (self.pub, self.unpub):
            while pub.get_num_connections() == 0:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"nobody subscribes to {pub.resolved_name}")
                time.sleep(0.05)
        for name in (self.search_name, self.list_name):
            rospy.wait_for_service(name, max(0.1, deadline - time.monotonic()))
        # ~/changes keeps nothing for a late subscriber: connected to the node's publisher.
        while self.changes_sub.get_num_connections() == 0:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no publisher of {self.changes_sub.resolved_name} connected")
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
        attrs = [self._attribute(a) for a in attributes]
        request = Search._request_class(type=type, attributes=attrs)
        return {"response": self._call(self.search_name, Search, request, timeout)}

    def op_list(self, include_unreachable: bool = False, timeout: float = 10.0) -> dict[str, Any]:
        request = List._request_class(include_unreachable=include_unreachable)
        return {"response": self._call(self.list_name, List, request, timeout)}

    def op_changes(self) -> dict[str, Any]:
        with self.changes.cond:
            return {"changes": [c for _, c in self.changes.items]}

    def op_diagnostics(self, since: float = 0.0, timeout: float = 10.0) -> dict[str, Any]:
        t, d = self.diagnostics.first(lambda _: True, since, timeout)
        return {"t": t, "msg": d}


if __name__ == "__main__":
    probe = Probe(sys.argv[1] if len(sys.argv) > 1 else "/sdfr")
    try:
        serve(probe)
    finally:
        rospy.signal_shutdown("probe done")
