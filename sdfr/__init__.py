"""SDfR: Service Discovery for Robots."""

from __future__ import annotations

import platform

#: The one version source: the distribution's metadata is made from it (pyproject.toml).
__version__ = "0.2.0"
#: The name to `pip install` (the PyPI name `sdfr` is another project's).
DIST_NAME = "sdfr-robots"


def version_text(prog: str) -> str:
    """What `PROG --version` prints."""
    return f"{prog} {__version__} ({DIST_NAME}, Python {platform.python_version()})"


def need_extra(extra: str, feature: str, missing: str) -> str:
    """The message of a feature that needs an optional extra which is not installed."""
    return (
        f"{feature} needs the {extra!r} extra ({missing} is not installed): "
        f"pip install '{DIST_NAME}[{extra}]'"
    )
