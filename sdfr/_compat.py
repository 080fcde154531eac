"""What differs between the Python versions SDfR runs on (3.10, for Ubuntu 22.04, ROS 2 Humble
and Jetson images, and 3.11+)."""

from __future__ import annotations

import sys

if sys.version_info >= (3, 11):
    import tomllib
else:  # the same parser, from PyPI (a dependency on 3.10 only)
    import tomli as tomllib

__all__ = ["tomllib"]
