"""Test fixtures shipped with the package, for the tests and the benchmarks alike.

* `simnet`: a fleet of protocol cores (`sdfr.protocol.Core`) on an in-memory lossy medium,
  run in virtual time; the protocol's tests and `bench.auth` drive it.
* `ros`: the ROS node and a JSON-lines probe run inside netlab robots; the ROS tests and
  `bench.ros_latency` drive them.
* `outsider`: a command run in a lab's namespace that speaks only the public wire format
  (sends, spoofs, floods, records, replays); the security tests and `bench.flood` run it.

Nothing here imports pytest, and nothing the daemon runs imports this package.
"""
