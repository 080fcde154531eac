"""netlab: a fleet of robots on one Linux machine, each a network namespace running sdfrd.

The main names are importable from here (`from netlab import Lab`); they are
loaded on first use, so that `netlab.errors` and the analysis modules stay
cheap to import.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from netlab.errors import NetlabError, ShapingUnsupported
    from netlab.lab import Lab, Robot
    from netlab.mobility import RandomWaypoint
    from netlab.ranges import LossyDisc, RangeModel, UnitDisc
    from netlab.shaping import LinkShape

_EXPORTS = {
    "Lab": "netlab.lab",
    "Robot": "netlab.lab",
    "NetlabError": "netlab.errors",
    "ShapingUnsupported": "netlab.errors",
    "RandomWaypoint": "netlab.mobility",
    "UnitDisc": "netlab.ranges",
    "LossyDisc": "netlab.ranges",
    "RangeModel": "netlab.ranges",
    "LinkShape": "netlab.shaping",
}

__all__ = [
    "Lab",
    "LinkShape",
    "LossyDisc",
    "NetlabError",
    "RandomWaypoint",
    "RangeModel",
    "Robot",
    "ShapingUnsupported",
    "UnitDisc",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'netlab' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
