"""What the daemon asks of the robot it runs on: its network interfaces (`netif`), /proc
(`procfs`) and joining the fleet's ad-hoc WiFi (`wifi`)."""
