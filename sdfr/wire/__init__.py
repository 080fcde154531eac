"""The wire codec: SSDP-style UDP datagrams to typed messages and back.

No I/O and no clock: `encode` turns a message into the bytes of one datagram, `decode` turns the
bytes of one datagram into a message or a `Reject` saying why not.  The format follows UPnP Device
Architecture 2.0 section 1.3 (SSDP): an HTTP-style start line, `NAME: value` header lines, a blank
line and, for `Update` only, a JSON body.  SDfR's own fields travel in `X-SDFR-*` headers, so
standard SSDP clients see an SDfR robot as an ordinary root device answering their searches.

The package: `messages` (the message types, the limits, what both sides share), `encode`
(the entry point, the full form, what fits in an Update), `compact` (the compact form),
`fields` (the checks and bodies both forms share) and `decode`.
"""

from __future__ import annotations

from sdfr.wire.compact import last_step
from sdfr.wire.decode import decode, read_step, unpack_delta
from sdfr.wire.encode import (
    check_service_fits,
    encode,
    encode_update_parts,
    max_service_json_bytes,
    parts_needed,
    service_json_size,
)
from sdfr.wire.messages import (
    CONFIGID_MODULUS,
    DEFAULT_GROUP,
    DEFAULT_PORT,
    DEVICE_TYPE,
    MAX_BOOT_ID,
    MAX_DATAGRAM,
    MAX_ENCODED,
    MAX_FLEET,
    MAX_HOST,
    MAX_LOCATION,
    MAX_MAX_AGE,
    MAX_MX,
    MAX_MX_ACCEPTED,
    MAX_PARTS,
    MAX_SEQ,
    MAX_STEPS,
    MAX_TURNS,
    MAX_UNPACKED,
    MAX_VERSION,
    MESSAGE_TYPES,
    PACKED,
    REJECT_REASONS,
    SEAL_RESERVE,
    SERVER,
    WANT_ALL,
    WIRE_COMPACT,
    WIRE_FULL,
    Alive,
    Byebye,
    Discovery,
    Message,
    Origin,
    Reject,
    Response,
    Update,
    Want,
    delta_dictionary,
    fleet_target,
    usn,
)

__all__ = [
    "CONFIGID_MODULUS",
    "DEFAULT_GROUP",
    "DEFAULT_PORT",
    "DEVICE_TYPE",
    "MAX_BOOT_ID",
    "MAX_DATAGRAM",
    "MAX_ENCODED",
    "MAX_FLEET",
    "MAX_HOST",
    "MAX_LOCATION",
    "MAX_MAX_AGE",
    "MAX_MX",
    "MAX_MX_ACCEPTED",
    "MAX_PARTS",
    "MAX_SEQ",
    "MAX_STEPS",
    "MAX_TURNS",
    "MAX_UNPACKED",
    "MAX_VERSION",
    "MESSAGE_TYPES",
    "PACKED",
    "REJECT_REASONS",
    "SEAL_RESERVE",
    "SERVER",
    "WANT_ALL",
    "WIRE_COMPACT",
    "WIRE_FULL",
    "Alive",
    "Byebye",
    "Discovery",
    "Message",
    "Origin",
    "Reject",
    "Response",
    "Update",
    "Want",
    "check_service_fits",
    "decode",
    "delta_dictionary",
    "encode",
    "encode_update_parts",
    "fleet_target",
    "last_step",
    "max_service_json_bytes",
    "parts_needed",
    "read_step",
    "service_json_size",
    "unpack_delta",
    "usn",
]
