"""Stamps read from, and moved in, a message's CDR bytes without decoding it: what the bag
tools need to order, retime and match messages of any type."""

from __future__ import annotations

import struct
from typing import Callable

from sensing_nodes.bags.storage import message_class

# sequence of stamped messages first (MarkerArray, TFMessage): its length, then the first
# element's Header.
SEQUENCE_OF_STAMPED = frozenset({'visualization_msgs/msg/MarkerArray', 'tf2_msgs/msg/TFMessage'})


def _byte_order(raw: bytes) -> str:
    return '<' if raw[1] == 1 else '>'


def leading_stamp_ns(raw: bytes) -> int:
    """Stamp of a CDR message whose first field is a Header or a Time."""
    sec, nanosec = struct.unpack_from(_byte_order(raw) + 'iI', raw, 4)
    return sec * 1_000_000_000 + nanosec


def first_element_stamp_ns(raw: bytes, fallback_ns: int) -> int:
    """Stamp of a CDR message that is a sequence of stamped messages (MarkerArray, TFMessage):
    its first element's header, or fallback_ns when the sequence is empty."""
    (count,) = struct.unpack_from(_byte_order(raw) + 'I', raw, 4)
    if count == 0:
        return fallback_ns
    sec, nanosec = struct.unpack_from(_byte_order(raw) + 'iI', raw, 8)
    return sec * 1_000_000_000 + nanosec


def shifted_stamp(raw: bytes, offset_ns: int) -> bytes:
    """A CDR message whose first field is a Header, with its stamp moved by offset_ns."""
    order = _byte_order(raw)
    sec, nanosec = divmod(leading_stamp_ns(raw) + offset_ns, 1_000_000_000)
    out = bytearray(raw)
    struct.pack_into(order + 'iI', out, 4, sec, nanosec)
    return bytes(out)


def first_field_type(msgtype: str) -> str:
    """Type of a 'pkg/msg/Name' message's first field ('std_msgs/Header', ...; '' if none)."""
    return next(iter(message_class(msgtype).get_fields_and_field_types().values()), '')


def stamp_reader(msgtype: str) -> Callable[[bytes, int], int]:
    """(CDR bytes, a fallback stamp) -> the stamp a message of this type carries: its header's,
    a sequence's first element's, else the fallback (the stamp of the input that caused it)."""
    if msgtype in SEQUENCE_OF_STAMPED:
        return first_element_stamp_ns
    if first_field_type(msgtype) == 'std_msgs/Header':
        return lambda raw, fallback_ns: leading_stamp_ns(raw)
    return lambda raw, fallback_ns: fallback_ns
