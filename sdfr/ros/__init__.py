"""SDfR's ROS node: one ROS-free bridge core and two thin adapters.

* `params`: the node's parameters (one table for both ROS versions), validated.
* `core`: the bridge. It talks to sdfrd only through its REST API (`sdfr.client.Client`):
  publish/unpublish, search, list, health as a diagnosis, the neighbour list turned into
  change events; `spawn` starts sdfrd when none answers and stops it only if it started it.
* `snapshot`: the neighbour list as the bridge reads it (`Snapshot` of `Robot`s), decoded
  from the API's records (`sdfr.records.schema`); `core` and `source` both take it from here.
* `source`: where the bridge learns that the neighbour list may have changed -- the seam.
  `EventStreamSource` follows the daemon's event stream (`GET /events`), `PollingSource`
  polls `GET /neighbors` with a bounded interval.
* `messages`: the bridge's values to and from `sdfr_msgs` messages (the same field names in
  ROS 1 and ROS 2; only the time type differs).
* `ros2` (rclpy) and `ros1` (rospy): the adapters. Only they import ROS.
"""
