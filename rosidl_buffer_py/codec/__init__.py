"""The wire format of messages with ``uint8[]`` fields: every one, at any depth, any number.

Two encodings of a ``uint8[]`` field share one layout, as in upstream's native buffer feature
(XCDR1, the bytes ``rclpy.serialization.serialize_message`` produces, 4-byte encapsulation header
included). Each ``uint8[]`` field of a message is encoded on its own, in one of two forms:

* **CPU** (legacy): exactly the bytes of a stock ``uint8[]``: ``uint32 length`` + the bytes. Every
  ROS 2 node, ``ros2 bag`` and this package read it; a vendor Buffer that cannot be described to a
  peer falls back to it. A message all of whose fields are in this form is byte for byte what
  ``serialize_message`` gives (padding aside, see below).
* **Descriptor**: where the field's ``uint32 length`` would be (4-aligned), the marker
  ``0xFFFFFFFF``, the backend name as a CDR string (``uint32`` length counting the NUL, the
  UTF-8 bytes, NUL), then (aligned to 4) ``uint32 length`` + the descriptor bytes (at most
  :data:`~rosidl_buffer_py.MAX_DESCRIPTOR_SIZE`). The payload bytes stay in the backend's memory;
  the receiver resolves the descriptor with that backend. Every field after it is aligned from
  where the descriptor ends, as XCDR1 aligns everything relative to the origin.

A decoder peeks each ``uint8[]`` field's first ``uint32``: the marker selects the descriptor path,
any other value is a legacy length (a 4 GiB payload cannot be sent anyway).

Fields are named by :class:`~rosidl_buffer_py.field_path.FieldPath` (a tuple of field names and
element indices): ``('data',)``, ``('image', 'data')``, ``('images', 3, 'data')``.

The general API:

* :func:`buffer_paths` ``(msg_type) -> Tuple[FieldPath, ...]``: the ``uint8[]`` fields of a type,
  with :data:`EACH` for the elements of a sequence or array of messages (never raises);
* :func:`field_paths` ``(msg) -> Tuple[FieldPath, ...]``: those of one message (indices resolved);
* :func:`buffers_of` ``(msg) -> List[BufferAt]``: the fields that hold a Buffer now;
* :func:`encode` ``(msg, descriptors: Mapping[path, (backend, descriptor)]) -> bytearray``: the
  descriptor form for those fields, CPU bytes for every other one;
* :func:`decode` ``(raw, msg_type, known_backends) -> Decoded``: the message, and
  ``Decoded.descriptors: Dict[FieldPath, FieldDescriptor]``; a receiver turns each into a Buffer
  with its backend and puts it in place with :func:`set_at`.

An endpoint uses it so::

    # publisher, per peer: describe what the peer's backends can take, the rest goes as bytes
    described = {}
    for path, buffer in codec.buffers_of(msg):
        descriptor = backends[buffer.backend_type].create_descriptor_with_endpoint(buffer, peer)
        if descriptor is not None:
            described[path] = (buffer.backend_type, descriptor)
    raw = codec.encode(msg, described)

    # subscription
    decoded = codec.decode(raw, msg_type, known_backends=backends)
    for path, (backend_type, descriptor) in decoded.descriptors.items():
        codec.set_at(decoded.msg, path,
                     backends[backend_type].from_descriptor_with_endpoint(descriptor, peer))

The single-payload API that the endpoints use stays: :func:`payload_field` (the last top-level
``uint8[]``), ``encode(msg, (backend, descriptor))`` for that field, ``Decoded.backend_type`` /
``Decoded.descriptor`` of that field, :func:`encode_parts`, :func:`split_payload`.

How: rclpy's C serializer does the non-payload part of every message (it serializes a shallow
copy whose ``uint8[]`` fields are empty); a per-type walker, compiled once from the message's
``SLOT_TYPES``, then copies those bytes realigned around each field's payload or descriptor, so
encode and decode cost about one ``memcpy`` of the payloads plus a small walk. Decode runs the
walker over the input first: every length is checked against the end of the input before
anything is read, so malformed input raises :class:`CodecError` and never reads out of bounds.
For the common shape (one top-level ``uint8[]`` followed only by fixed-size alignment-1 fields:
Image, CompressedImage, PointCloud2...) a shorter path splices the payload in directly, and the
descriptor form runs in C (``src/native/codec_fast.cpp``).

Unlike ``serialize_message``, which leaves its alignment padding uninitialized (it carries stale
heap bytes), :func:`encode` writes zero padding; every other byte is the same.

The package's modules, one job each, each importing only those before it: :mod:`.wire` (the
constants of the format, the errors and the result types), :mod:`.walker` (the per-type ops and
the walk that checks and copies CDR bytes), :mod:`.plans` (what is compiled once per type, and
:func:`payload_field`, :func:`buffer_paths`, :func:`field_paths`, :func:`buffers_of`),
:mod:`.encoder` (:func:`encode`, :func:`encode_parts`) and :mod:`.decoder` (:func:`decode`,
:func:`split_payload`, :func:`deserialize`).
"""
from rosidl_buffer_py.codec import wire
from rosidl_buffer_py.codec.decoder import (
    decode, DescriptorReading, descriptor_reading, deserialize, split_payload)
from rosidl_buffer_py.codec.encoder import encode, encode_parts
from rosidl_buffer_py.codec.plans import (
    buffer_paths, buffers_of, descriptor_program, field_paths, payload_field, program_of)
from rosidl_buffer_py.codec.wire import (
    BufferAt, CodecError, DESCRIPTOR_MARKER, Decoded, EncodedParts, FieldDescriptor,
    UnsupportedMessageTypeError)
from rosidl_buffer_py.field_path import EACH, FieldPath, get_at, set_at

__all__ = [
    'BufferAt',
    'CodecError',
    'DESCRIPTOR_MARKER',
    'Decoded',
    'DescriptorReading',
    'EACH',
    'EncodedParts',
    'FieldDescriptor',
    'FieldPath',
    'UnsupportedMessageTypeError',
    'buffer_paths',
    'buffers_of',
    'decode',
    'descriptor_program',
    'descriptor_reading',
    'deserialize',
    'encode',
    'encode_parts',
    'field_paths',
    'get_at',
    'payload_field',
    'program_of',
    'set_at',
    'split_payload',
]

#: CDR encapsulation identifiers (the first two bytes, big endian) this codec reads.
ENCAPSULATION_CDR_BE = wire.ENCAPSULATION_CDR_BE
ENCAPSULATION_CDR_LE = wire.ENCAPSULATION_CDR_LE
