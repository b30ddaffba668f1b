"""Control messages on a channel: the wire form of probes and route fences.

A channel carries the topic's messages (CDR bytes, or the descriptor form) and, from the
publisher's route protocol (:mod:`rosidl_buffer_py.routes`), two control messages: *probes*,
written until the subscription's channel reader acknowledges them, and the *route fence* before
the first channel message. They are their own encoding, which no message can be taken for:

    bytes 0-1  0x00 0x01   the CDR little-endian encapsulation identifier, as every sample
    bytes 2-3  'R' 'B'     encapsulation options: 0x0000 in every CDR message rmw or the codec
                           writes, so these two bytes alone tell a control message apart
    byte  4    kind        1: probe, 2: route fence
    byte  5    flags       fence: bit 0 set when its message had reached every reader
                           (``Fence.delivered``); 0 otherwise
    bytes 6-7  0
    bytes 8-15 value       uint64 little endian: the fence's last main-topic timestamp (probe: 0)

A sample with those options that is not exactly this is malformed (rejected, never delivered).
"""
import enum
import struct
from typing import NamedTuple, Optional, Union

from rosidl_buffer_py.routes import Fence

_HEADER = b'\x00\x01RB'
_FORM = struct.Struct('<4sBB2xQ')
#: Fence flags (byte 5).
DELIVERED = 0x01
SIZE = _FORM.size


class ControlError(ValueError):
    """A sample marked as a control message that is not a valid one."""


class Kind(enum.IntEnum):
    PROBE = 1
    FENCE = 2


class Probe(NamedTuple):
    """Written on a channel until its reader acknowledges: the reader matched the writer."""


#: The only probe there is.
PROBE = Probe()
PROBE_BYTES = _FORM.pack(_HEADER, Kind.PROBE, 0, 0)


def encode(message: Union[Probe, Fence]) -> bytes:
    """The wire form of a probe or a route fence."""
    if isinstance(message, Fence):
        if not 0 <= message.last_main < 1 << 64:
            raise ValueError(f'a fence names a uint64 timestamp, got {message.last_main!r}')
        return _FORM.pack(_HEADER, Kind.FENCE, DELIVERED if message.delivered else 0,
                          message.last_main)
    if isinstance(message, Probe):
        return PROBE_BYTES
    raise TypeError(f'expected a Probe or a Fence, got {type(message).__name__}')


def is_control(raw) -> bool:
    """Whether a channel sample is marked as a control message (cheap: two bytes)."""
    return raw[2:4] == b'RB' and raw[:2] == b'\x00\x01'


def decode(raw) -> Union[Probe, Fence]:
    """The control message ``raw`` holds; :class:`ControlError` if it is not a valid one."""
    if len(raw) != SIZE:
        raise ControlError(f'a control message is {SIZE} bytes, got {len(raw)}')
    header, kind, flags, value = _FORM.unpack(bytes(raw))
    if header != _HEADER or bytes(raw[6:8]) != b'\0\0' or \
            flags & ~(DELIVERED if kind == Kind.FENCE else 0):
        raise ControlError(f'malformed control message header {bytes(raw[:8]).hex()}')
    if kind == Kind.FENCE:
        return Fence(value, bool(flags & DELIVERED))
    if kind == Kind.PROBE and value == 0:
        return PROBE
    raise ControlError(f'unknown control message kind {kind} (value {value}); known: '
                       f'{", ".join(f"{k.value} ({k.name.lower()})" for k in Kind)}')


def parse(raw) -> Optional[Union[Probe, Fence]]:
    """The control message in a channel sample, or None for a message sample."""
    return decode(raw) if is_control(raw) else None
