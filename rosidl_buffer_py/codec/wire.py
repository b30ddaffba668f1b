"""The constants of the codec's wire format, its errors and its result types.

Every other module of :mod:`rosidl_buffer_py.codec` builds on these; this one imports none of
them.
"""
import array
import struct
from dataclasses import dataclass, field as dataclass_field
from typing import Any, Dict, NamedTuple, Optional

from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.field_path import FieldPath

#: First ``uint32`` of a descriptor-encoded payload (upstream's ``kBufferDescriptorMarker``).
DESCRIPTOR_MARKER = 0xFFFFFFFF

#: CDR encapsulation identifiers (the first two bytes, big endian) this codec reads.
ENCAPSULATION_CDR_BE = 0x0000
ENCAPSULATION_CDR_LE = 0x0001

HEADER_SIZE = 4
ZERO_LENGTH = b'\x00\x00\x00\x00'
ZEROS = bytes(8)
U32 = {True: struct.Struct('<I'), False: struct.Struct('>I')}
MARKER_BYTES = b'\xff\xff\xff\xff'
#: The payload of the clones that encode serializes (read, never modified).
EMPTY_PAYLOAD = array.array('B')
#: Payloads at least this long are kept apart (not copied) while a message is assembled.
BIG_PAYLOAD = 4096


class CodecError(ValueError):
    """Input that cannot be encoded or decoded; the message names the bad value."""


class UnsupportedMessageTypeError(CodecError, TypeError):
    """A message type this codec cannot handle (not a message class, unsupported field
    types...)."""


class FieldDescriptor(NamedTuple):
    """The descriptor form of one ``uint8[]`` field: which backend, and its descriptor bytes."""

    backend_type: str
    descriptor: bytes


class BufferAt(NamedTuple):
    """A ``uint8[]`` field that holds a :class:`~rosidl_buffer_py.Buffer` (see
    :func:`buffers_of`)."""

    path: FieldPath
    buffer: Buffer


@dataclass
class Decoded:
    """The result of :func:`decode`.

    :ivar msg: The message. A field that came as CPU bytes holds them as ``array.array('B')``
        (as ``deserialize_message`` gives); a field that came as a descriptor holds an empty
        ``array.array('B')``, until the receiver sets the Buffer there.
    :ivar backend_type: Backend named by the descriptor of the :func:`payload_field`, or ``None``
        (CPU bytes, or the type has no top-level payload field).
    :ivar descriptor: That descriptor's bytes, or ``None``.
    :ivar descriptors: Every field that came as a descriptor, by path (the payload field's too).
    """

    msg: Any
    backend_type: Optional[str] = None
    descriptor: Optional[bytes] = None
    descriptors: Dict[FieldPath, FieldDescriptor] = dataclass_field(default_factory=dict)

    @property
    def is_descriptor(self) -> bool:
        """True when some field travelled as a descriptor."""
        return self.backend_type is not None or bool(self.descriptors)


class EncodedParts(NamedTuple):
    """The legacy CDR bytes of a message in three pieces: ``head + payload + suffix``.

    :ivar head: Encapsulation header, the fields before the payload (zero padding) and the
        payload's ``uint32`` length.
    :ivar payload: The payload bytes, a flat memoryview of the message's own memory (for a
        host-addressable Buffer: the backend's memory itself, no copy).
    :ivar suffix: The fields after the payload.
    """

    head: bytearray
    payload: memoryview
    suffix: bytes

    @property
    def nbytes(self) -> int:
        """Length of the whole CDR message."""
        return len(self.head) + self.payload.nbytes + len(self.suffix)
