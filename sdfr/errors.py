"""The package's exception hierarchy: every error a user can act on derives from SdfrError."""

from __future__ import annotations


class SdfrError(Exception):
    """Base of every error SDfR raises on purpose."""


class ConfigError(SdfrError):
    """A flag, config key or environment value is wrong; the message says which and why."""


class ValidationError(SdfrError):
    """A request or record is invalid; `field` names the offending field."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


class NotFoundError(SdfrError):
    """A resource named by the caller does not exist."""


class ApiError(SdfrError):
    """The daemon's API answered with an error, or could not be reached (client side)."""

    def __init__(self, status: int, message: str, field: str | None = None) -> None:
        super().__init__(message if field is None else f"{field}: {message}")
        self.status = status
        self.message = message
        self.field = field
