"""SDfR: Service Discovery for Robots."""

__version__ = "0.1.0"
