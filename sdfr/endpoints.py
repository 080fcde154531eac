"""What a client needs to find and address sdfrd, without the daemon's code: the API's
default address and the header that carries a client's owner token. `sdfr.config.load` takes its
default from here, so that importing a client loads neither the wire codec nor the protocol."""

from __future__ import annotations

#: Where the local REST API listens unless configured otherwise (HOST:PORT).
DEFAULT_API = "127.0.0.1:8700"

#: The header a client sends its owner token in: what it publishes is its own, and only
#: a request with the same token (or, on the unix socket, by the same user) may unpublish,
#: renew, hold or publish it again.
OWNER_HEADER = "X-SDFR-Owner"
