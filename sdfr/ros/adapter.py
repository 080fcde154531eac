"""What the ROS 2 and ROS 1 nodes share, ROS-free: publishing what the bridge hands out,
and turning requests into bridge calls and responses.

An adapter (`sdfr.ros.ros2`, `sdfr.ros.ros1`) makes the version's publishers, subscriptions
and services, and gives this class its message classes (`m`), its three publishers and its
logger; the rest is here, once.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from sdfr.ros import messages as conv
from sdfr.ros.core import Bridge, Change, Diagnosis, ServiceRequest
from sdfr.ros.snapshot import BridgeError, Snapshot


class NodeAdapter:
    """A `Sink` of the bridge, and the handlers of ~publish, ~unpublish, ~search and ~list."""

    m: conv.Interfaces
    bridge: Bridge
    neighbors_pub: Any
    changes_pub: Any
    diag_pub: Any
    info: Callable[[str], object]
    error: Callable[[str], object]
    #: How the node's names are written in its log lines ("~/" in ROS 2, "~" in ROS 1).
    private: str = "~/"

    def announce(self) -> None:
        spawned = self.bridge.spawned
        self.info(
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

    def on_publish(self, msg: Any) -> None:
        sid = self._request(self.bridge.publish, "publish", msg)
        if sid is not None:
            self.info(f"published {msg.name!r} as {sid}")

    def on_unpublish(self, msg: Any) -> None:
        sid = self._request(self.bridge.unpublish, "unpublish", msg)
        if sid is not None:
            self.info(f"unpublished {sid}")

    def _request(self, call: Callable[[ServiceRequest], str], topic: str, msg: Any) -> str | None:
        """The service id `call` answers for `msg`; None, logged, if the bridge refused it."""
        try:
            return call(conv.request_from_msg(msg))
        except BridgeError as exc:
            self.error(f"{self.private}{topic}: {exc}")
            return None

    def search(self, request: Any, response: Any) -> Any:
        """Fill the version's Search response for `request`."""
        try:
            attrs = conv.attributes_from_msgs(request.attributes)
            response.robots = conv.robot_msgs(self.m, self.bridge.search(request.type, attrs))
            response.success = True
        except BridgeError as exc:
            response.success, response.message = False, str(exc)
        return response

    def list(self, request: Any, response: Any) -> Any:
        """Fill the version's List response for `request`."""
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


def not_importable(version: int, exc: ImportError) -> int:
    """Say that ROS `version` cannot be imported here, and which interpreter can; exit status 2."""
    print(
        f"sdfr-ros{version}: ROS {version} is not importable here ({exc}); run it with the "
        f"interpreter of the ROS {version} environment "
        f"(make ros{version}-setup: .venv/ros{version}/bin/python)",
        file=sys.stderr,
    )
    return 2
