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
"""
import array
import importlib
import struct
import threading
from dataclasses import dataclass, field as dataclass_field
from typing import (Any, Callable, Container, Dict, Iterator, List, Mapping, NamedTuple,
                    Optional, Tuple, Type, Union)

from rclpy.serialization import deserialize_message, serialize_message
from rosidl_parser import definition

from rosidl_buffer_py import _native
from rosidl_buffer_py.backend import MAX_DESCRIPTOR_SIZE
from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.field_path import EACH, FieldPath, get_at, set_at
from rosidl_buffer_py.message_support import enable_buffer_fields

__all__ = [
    'BufferAt',
    'CodecError',
    'DESCRIPTOR_MARKER',
    'Decoded',
    'EACH',
    'EncodedParts',
    'FieldDescriptor',
    'FieldPath',
    'UnsupportedMessageTypeError',
    'buffer_paths',
    'buffers_of',
    'decode',
    'encode',
    'encode_parts',
    'field_paths',
    'get_at',
    'payload_field',
    'set_at',
    'split_payload',
]

#: First ``uint32`` of a descriptor-encoded payload (upstream's ``kBufferDescriptorMarker``).
DESCRIPTOR_MARKER = 0xFFFFFFFF

#: CDR encapsulation identifiers (the first two bytes, big endian) this codec reads.
ENCAPSULATION_CDR_BE = 0x0000
ENCAPSULATION_CDR_LE = 0x0001

_UINT8_SEQUENCE = 'sequence<uint8>'
_HEADER_SIZE = 4
_ZERO_LENGTH = b'\x00\x00\x00\x00'
_ZEROS = bytes(8)
_U32 = {True: struct.Struct('<I'), False: struct.Struct('>I')}
_MARKER_BYTES = b'\xff\xff\xff\xff'
#: The payload of the clones that encode serializes (read, never modified).
_EMPTY_PAYLOAD = array.array('B')
#: Payloads at least this long are kept apart (not copied) while a message is assembled.
_BIG_PAYLOAD = 4096

# Wire size (= XCDR1 alignment) of each supported basic type.
_BASIC_SIZES = {
    'boolean': 1, 'octet': 1, 'char': 1, 'int8': 1, 'uint8': 1,
    'short': 2, 'unsigned short': 2, 'int16': 2, 'uint16': 2,
    'long': 4, 'unsigned long': 4, 'int32': 4, 'uint32': 4, 'float': 4,
    'long long': 8, 'unsigned long long': 8, 'int64': 8, 'uint64': 8, 'double': 8,
}


class CodecError(ValueError):
    """Input that cannot be encoded or decoded; the message names the bad value."""


class UnsupportedMessageTypeError(CodecError, TypeError):
    """A message type this codec cannot handle (not a message class, unsupported field types...)."""


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


# --- the compiled walker -----------------------------------------------------------------------
#
# Positions are relative to the CDR origin (just after the encapsulation header): XCDR1 aligns
# every primitive to its size relative to that origin. Ops:
#   (_FIXED, align, size, inner_pads, label)      fixed-size run; its first item aligns to `align`
#                                                 and every later item's alignment divides it
#   (_STRING, bound, label)                       uint32 length (incl. NUL) + chars + NUL
#   (_PSEQ, align, itemsize, bound, label)        uint32 count + primitives (aligned if count > 0)
#   (_SEQ, sub_ops, min_size, bound, label, path) uint32 count + elements walked with sub_ops
#   (_ARRAY, sub_ops, count, label, path)         count elements walked with sub_ops
#   (_BLOB, path, label)                          an unbounded uint8[] field: CPU bytes (uint32
#                                                 length + bytes) or a descriptor
#   (_WSTRING, bound, label)                      uint32 length (characters) + 4 bytes each
# `path` is the field's path relative to the element (or message) the ops belong to; nested
# messages are flattened into their parent's ops. src/native/codec_fast.cpp walks the first five.
_FIXED, _STRING, _PSEQ, _SEQ, _ARRAY, _BLOB, _WSTRING = range(7)


class _Builder:
    """Accumulates ops, merging runs of fixed-size fields into one op."""

    def __init__(self) -> None:
        self.ops: List[list] = []

    def fixed(self, align: int, size: int, label: str, inner_pads: Tuple = ()) -> None:
        last = self.ops[-1] if self.ops else None
        if last is not None and last[0] == _FIXED and last[1] >= align:
            # The run starts aligned to last[1], a multiple of `align`: the layout is static.
            offset = (last[2] + align - 1) & -align
            if offset != last[2]:
                last[3].append((last[2], offset))
            last[3].extend((offset + s, offset + e) for s, e in inner_pads)
            last[2] = offset + size
        else:
            self.ops.append([_FIXED, align, size, list(inner_pads), label])

    def add(self, op: list) -> None:
        if op[0] == _FIXED:
            self.fixed(op[1], op[2], op[4], op[3])
        else:
            self.ops.append(op)

    def freeze(self) -> Tuple[tuple, ...]:
        return tuple(tuple(op[:3]) + (tuple(op[3]), op[4]) if op[0] == _FIXED else tuple(op)
                     for op in self.ops)


def _min_size(ops: Tuple[tuple, ...]) -> int:
    """A lower bound of the wire size of ``ops`` (padding not counted)."""
    total = 0
    for op in ops:
        kind = op[0]
        if kind == _FIXED:
            total += op[2]
        elif kind == _STRING:
            total += 5
        elif kind in (_PSEQ, _SEQ, _BLOB, _WSTRING):
            total += 4
        else:
            total += op[2] * _min_size(op[1])
    return total


def _fields(msg_type: Type) -> List[Tuple[str, Any]]:
    """(name, rosidl_parser type) of every field of a generated message class."""
    try:
        names = list(msg_type.get_fields_and_field_types())
        slot_types = list(msg_type.SLOT_TYPES)
    except (AttributeError, TypeError):
        raise UnsupportedMessageTypeError(
            f'{msg_type!r:.200} is not a generated ROS message class') from None
    if len(names) != len(slot_types):
        raise UnsupportedMessageTypeError(
            f'{msg_type.__name__} has {len(names)} fields but {len(slot_types)} SLOT_TYPES')
    return list(zip(names, slot_types))


def _nested_class(ns_type: definition.NamespacedType) -> Type:
    module_name = '.'.join(ns_type.namespaces)
    try:
        return getattr(importlib.import_module(module_name), ns_type.name)
    except (ImportError, AttributeError) as exc:
        raise UnsupportedMessageTypeError(
            f'cannot import the nested message type {module_name}.{ns_type.name}: {exc}') from None


def _is_blob(slot_type: Any) -> bool:
    """True for an unbounded ``uint8[]``: the fields that may hold a Buffer."""
    return (isinstance(slot_type, definition.UnboundedSequence)
            and isinstance(slot_type.value_type, definition.BasicType)
            and slot_type.value_type.typename == 'uint8')


def _add_type(builder: _Builder, slot_type: Any, label: str, stack: Tuple[Type, ...],
              path: Tuple = (), blobs: bool = False) -> None:
    """Append the ops of one value of ``slot_type`` (a rosidl_parser.definition type).

    With ``blobs``, an unbounded ``uint8[]`` is a ``_BLOB`` op (it may be a descriptor);
    otherwise a plain sequence.
    """
    if blobs and _is_blob(slot_type):
        builder.add([_BLOB, path, label])
    elif isinstance(slot_type, definition.BasicType):
        size = _BASIC_SIZES.get(slot_type.typename)
        if size is None:
            raise UnsupportedMessageTypeError(
                f'field {label!r} has type {slot_type.typename!r}, which this codec does not '
                f'support (supported basic types: {", ".join(sorted(_BASIC_SIZES))})')
        builder.fixed(size, size, label)
    elif isinstance(slot_type, definition.AbstractWString):
        builder.add([_WSTRING, getattr(slot_type, 'maximum_size', None), label])
    elif isinstance(slot_type, definition.AbstractString):
        builder.add([_STRING, getattr(slot_type, 'maximum_size', None), label])
    elif isinstance(slot_type, definition.NamespacedType):
        nested = _nested_class(slot_type)
        if nested in stack:
            raise UnsupportedMessageTypeError(f'{nested.__name__} contains itself ({label!r})')
        fields = _fields(nested)
        if not fields:
            # rosidl gives an empty structure one member, structure_needs_at_least_one_member
            # (uint8): Python does not show it, the wire carries it.
            builder.fixed(1, 1, f'{label}.structure_needs_at_least_one_member')
        for name, field_type in fields:
            _add_type(builder, field_type, f'{label}.{name}', stack + (nested,), path + (name,),
                      blobs)
    elif isinstance(slot_type, (definition.Array, definition.AbstractSequence)):
        value_type = slot_type.value_type
        basic = (isinstance(value_type, definition.BasicType)
                 and value_type.typename in _BASIC_SIZES)
        if isinstance(slot_type, definition.Array):
            if basic:
                size = _BASIC_SIZES[value_type.typename]
                if slot_type.size:  # Fast CDR aligns an array only when it is not empty
                    builder.fixed(size, size * slot_type.size, label)
                return
            sub = _element_ops(value_type, label + '[]', stack, blobs)
            if slot_type.size:
                builder.add([_ARRAY, sub, slot_type.size, label, path])
            return
        bound = getattr(slot_type, 'maximum_size', None)
        if basic:
            size = _BASIC_SIZES[value_type.typename]
            builder.add([_PSEQ, size, size, bound, label])
            return
        sub = _element_ops(value_type, label + '[]', stack, blobs)
        min_size = _min_size(sub)
        if min_size <= 0:
            raise UnsupportedMessageTypeError(
                f'field {label!r}: sequences of zero-size elements are not supported')
        builder.add([_SEQ, sub, min_size, bound, label, path])
    else:
        raise UnsupportedMessageTypeError(
            f'field {label!r} has a type this codec does not support: {slot_type!r}')


def _element_ops(value_type: Any, label: str, stack: Tuple[Type, ...],
                 blobs: bool = False) -> Tuple[tuple, ...]:
    builder = _Builder()
    _add_type(builder, value_type, label, stack, (), blobs)
    return builder.freeze()


def _truncated(label: str, offset: int, needed: int, end: int) -> CodecError:
    return CodecError(
        f'truncated message: {label} needs {needed} bytes at offset {offset + _HEADER_SIZE} but '
        f'the message ends at offset {end + _HEADER_SIZE}')


def _read_u32(buf: memoryview, pos: int, end: int, unpack, label: str) -> Tuple[int, int]:
    """Return (value, position after) of the 4-aligned uint32 at or after ``pos``."""
    start = (pos + 3) & -4
    if start + 4 > end:
        raise _truncated(label, start, 4, end)
    return unpack(buf, start)[0], start + 4


class _Out:
    """The bytes a walk writes: small pieces copied into ``cur``, large payloads kept apart.

    Its position (relative to the CDR origin) drives the alignment of what comes next.
    """

    __slots__ = ('parts', 'cur', 'base', 'apart')

    def __init__(self, header) -> None:
        self.parts: List[Any] = []
        self.apart: Optional[int] = None  # the index in parts of the payload kept `apart`
        self.cur = bytearray(header)
        self.base = -_HEADER_SIZE  # the origin is after the encapsulation header

    def pad(self, align: int) -> None:
        gap = -(self.base + len(self.cur)) % align
        if gap:
            self.cur += _ZEROS[:gap]

    def payload(self, view: memoryview, apart: bool = False) -> None:
        """Append ``view``; a large one (or ``apart``) is not copied but kept as its own part."""
        if apart or view.nbytes >= _BIG_PAYLOAD:
            if apart:
                self.apart = len(self.parts) + 1
            self.parts.append(self.cur)
            self.parts.append(view)
            self.base += len(self.cur) + view.nbytes
            self.cur = bytearray()
        else:
            self.cur += view

    def finish(self) -> List[Any]:
        self.parts.append(self.cur)
        return self.parts

    def joined(self) -> bytearray:
        if not self.parts:
            return self.cur
        return bytearray().join(self.finish())


#: A walk's handler of a ``_BLOB`` op: (path, label, position) -> position after the field.
_BlobHandler = Callable[[Tuple, str, int], int]


def _walk(ops: Tuple[tuple, ...], buf: memoryview, pos: int, end: int, unpack,
          out: Optional[_Out] = None, prefix: Tuple = (),
          blob: Optional[_BlobHandler] = None) -> int:
    """Walk ``ops`` over ``buf`` from ``pos``; return the position after them.

    ``buf`` starts at the CDR origin. Every length is checked against ``end`` before it is used.
    When ``out`` is given, the walked bytes are copied to it, realigned to its position, with
    zero padding. A ``_BLOB`` op is handed to ``blob`` (which also writes it to ``out``) with its
    path below ``prefix``; without ``blob`` it is walked (and copied) as a plain ``uint8[]``.
    """
    for op in ops:
        kind = op[0]
        if kind == _FIXED:
            align = op[1]
            start = (pos + align - 1) & -align
            if start + op[2] > end:
                raise _truncated(op[4], start, op[2], end)
            pos = start + op[2]
            if out is not None:
                out.pad(align)
                cur = out.cur
                at = len(cur)
                cur += buf[start:pos]
                for s, e in op[3]:
                    cur[at + s:at + e] = _ZEROS[:e - s]
        elif kind == _STRING or kind == _WSTRING:
            label = op[2]
            length, pos = _read_u32(buf, pos, end, unpack, f'the length of string {label}')
            at = pos - 4 + _HEADER_SIZE
            if kind == _STRING:
                if length == 0:
                    raise CodecError(f'string {label} at offset {at} has length 0; a CDR string '
                                     'length counts its terminating NUL')
                if length > end - pos:
                    raise CodecError(f'string {label} at offset {at} claims {length} bytes but '
                                     f'only {end - pos} are left')
                if buf[pos + length - 1] != 0:
                    raise CodecError(f'string {label} at offset {at} is not NUL-terminated')
                nbytes = length
            else:
                nbytes = 4 * length
                if nbytes > end - pos:
                    raise CodecError(f'wstring {label} at offset {at} claims {length} characters '
                                     f'({nbytes} bytes) but only {end - pos} bytes are left')
            # No check of a bounded string's bound: it counts characters, the wire bytes (or
            # UTF-16 units), and rclpy's serializer does not check it either.
            if out is not None:
                out.pad(4)
                out.cur += buf[pos - 4:pos + nbytes]
            pos += nbytes
        elif kind == _PSEQ or (kind == _BLOB and blob is None):
            if kind == _BLOB:
                op = (_PSEQ, 1, 1, None, op[2])
            label = op[4]
            count, pos = _read_u32(buf, pos, end, unpack, f'the count of sequence {label}')
            if op[3] is not None and count > op[3]:
                raise CodecError(f'sequence {label} has {count} elements, more than its bound '
                                 f'{op[3]}')
            if out is not None:
                out.pad(4)
                out.cur += buf[pos - 4:pos]
            if count:  # Fast CDR aligns the elements only when there are some
                align = op[1]
                start = (pos + align - 1) & -align
                nbytes = count * op[2]
                if nbytes > end - start:
                    raise CodecError(
                        f'sequence {label} at offset {pos - 4 + _HEADER_SIZE} claims {count} '
                        f'elements ({nbytes} bytes) but only {max(end - start, 0)} bytes are left')
                pos = start + nbytes
                if out is not None:
                    out.pad(align)
                    out.payload(buf[start:pos])
        elif kind == _SEQ:
            label = op[4]
            count, pos = _read_u32(buf, pos, end, unpack, f'the count of sequence {label}')
            if op[3] is not None and count > op[3]:
                raise CodecError(f'sequence {label} has {count} elements, more than its bound '
                                 f'{op[3]}')
            if count * op[2] > end - pos:
                raise CodecError(
                    f'sequence {label} at offset {pos - 4 + _HEADER_SIZE} claims {count} elements '
                    f'(at least {count * op[2]} bytes) but only {end - pos} bytes are left')
            if out is not None:
                out.pad(4)
                out.cur += buf[pos - 4:pos]
            sub = op[1]
            base = prefix + op[5]
            for index in range(count):
                pos = _walk(sub, buf, pos, end, unpack, out, base + (index,), blob)
        elif kind == _ARRAY:
            sub = op[1]
            base = prefix + op[4]
            for index in range(op[2]):
                pos = _walk(sub, buf, pos, end, unpack, out, base + (index,), blob)
        else:  # _BLOB with a handler
            pos = blob(prefix + op[1], op[2], pos)
    return pos


# --- per-type plans ------------------------------------------------------------------------------

# A type's tree of uint8[] fields, to reach them in an instance: one entry per field that is or
# holds one, in field order: (slot, name, kind, sub-tree).
_T_BLOB, _T_MESSAGE, _T_ELEMENTS = range(3)
_Tree = Tuple[Tuple[str, str, int, Any], ...]


@dataclass(frozen=True)
class _Plan:
    """The short path: one top-level payload followed by fixed-size alignment-1 fields only."""

    msg_type: Type
    field: str                      # the payload field
    slot: str                       # its __slots__ entry ('_data')
    slots: Tuple[str, ...]          # every slot, copied into the clone that encode serializes
    prefix_ops: Tuple[tuple, ...]   # the fields before the payload
    suffix_size: int                # the fields after it: alignment 1, fixed size
    path: FieldPath                 # (field,)


@dataclass(frozen=True)
class _TypeCodec:
    """Everything the codec compiled for one message type."""

    msg_type: Type
    ops: Tuple[tuple, ...]          # the whole message, uint8[] fields as _BLOB ops
    tree: _Tree
    templates: Tuple[FieldPath, ...]
    payload: Optional[str]          # the last top-level uint8[] field (payload_field)
    plan: Optional[_Plan]           # the short path, when the type has its shape
    plain: bool                     # fixed size: rmw_fastrtps pads it to a multiple of 4
    slack: bool                     # rmw_fastrtps may size it larger than its data (_estimate)


def _tree(msg_type: Type, stack: Tuple[Type, ...]) -> _Tree:
    slots = set(getattr(msg_type, '__slots__', ()))
    entries = []
    for name, slot_type in _fields(msg_type):
        if _is_blob(slot_type):
            kind, sub = _T_BLOB, None
        elif isinstance(slot_type, definition.NamespacedType):
            kind, sub = _T_MESSAGE, _nested_tree(slot_type, stack)
        elif (isinstance(slot_type, (definition.Array, definition.AbstractSequence))
              and isinstance(slot_type.value_type, definition.NamespacedType)):
            kind, sub = _T_ELEMENTS, _nested_tree(slot_type.value_type, stack)
        else:
            continue
        if kind != _T_BLOB and not sub:
            continue
        if '_' + name not in slots:
            raise UnsupportedMessageTypeError(
                f'{msg_type.__name__} has no slot {"_" + name!r} for its field {name!r}')
        entries.append(('_' + name, name, kind, sub))
    return tuple(entries)


def _nested_tree(slot_type: definition.NamespacedType, stack: Tuple[Type, ...]) -> _Tree:
    nested = _nested_class(slot_type)
    if nested in stack:
        raise UnsupportedMessageTypeError(f'{nested.__name__} contains itself')
    return _tree(nested, stack + (nested,))


def _templates(tree: _Tree, prefix: Tuple = ()) -> List[FieldPath]:
    out = []
    for _, name, kind, sub in tree:
        if kind == _T_BLOB:
            out.append(FieldPath(prefix + (name,)))
        else:
            out.extend(_templates(sub, prefix + ((name,) if kind == _T_MESSAGE else
                                                 (name, EACH))))
    return out


def _compile(msg_type: Type) -> _TypeCodec:
    fields = _fields(msg_type)
    builder = _Builder()
    if not fields:  # the wire carries structure_needs_at_least_one_member (see _add_type)
        builder.fixed(1, 1, 'structure_needs_at_least_one_member')
    for name, slot_type in fields:
        _add_type(builder, slot_type, name, (msg_type,), (name,), blobs=True)
    ops = builder.freeze()
    tree = _tree(msg_type, (msg_type,))
    templates = tuple(_templates(tree))
    top = [index for index, (_, slot_type) in enumerate(fields) if _is_blob(slot_type)]
    payload = fields[top[-1]][0] if top else None
    plan = None
    if len(templates) == 1 and payload is not None:
        plan = _short_plan(msg_type, fields, top[-1])
    slack = _has_slack(ops)
    return _TypeCodec(msg_type, ops, tree, templates, payload, None if slack else plan,
                      _fixed_size(ops), slack)


def _has_slack(ops: Tuple[tuple, ...]) -> bool:
    return any(op[0] == _WSTRING or (op[0] == _PSEQ and op[1] > 1) or
               (op[0] in (_SEQ, _ARRAY) and _has_slack(op[1])) for op in ops)


def _fixed_size(ops: Tuple[tuple, ...]) -> bool:
    return all(op[0] == _FIXED or (op[0] == _ARRAY and _fixed_size(op[1])) for op in ops)


def _short_plan(msg_type: Type, fields, index: int) -> Optional[_Plan]:
    """The short path's plan, or None when a field after the payload needs alignment or has a
    variable size (its padding would then depend on the payload length)."""
    suffix = _Builder()
    for name, slot_type in fields[index + 1:]:
        _add_type(suffix, slot_type, name, (msg_type,))
    suffix_ops = suffix.freeze()
    if any(op[0] != _FIXED or op[1] != 1 for op in suffix_ops):
        return None
    prefix = _Builder()
    for name, slot_type in fields[:index]:
        _add_type(prefix, slot_type, name, (msg_type,))
    field = fields[index][0]
    return _Plan(msg_type, field, '_' + field, tuple(msg_type.__slots__), prefix.freeze(),
                 sum(op[2] for op in suffix_ops), FieldPath((field,)))


_codecs: Dict[Type, _TypeCodec] = {}
_codecs_lock = threading.Lock()


def _codec(msg_type: Type) -> _TypeCodec:
    try:
        compiled = _codecs.get(msg_type)
    except TypeError:  # unhashable: not a class
        compiled = None
    if compiled is None:
        if not isinstance(msg_type, type):
            raise UnsupportedMessageTypeError(
                f'expected a message class, got {type(msg_type).__name__} {msg_type!r:.200}')
        with _codecs_lock:
            compiled = _codecs.get(msg_type)
            if compiled is None:
                compiled = _compile(msg_type)
                enable_buffer_fields(msg_type)
                _codecs[msg_type] = compiled
    return compiled


def _plan(msg_type: Type) -> _Plan:
    """The short path's plan of ``msg_type`` (for types that have it)."""
    plan = _codec(msg_type).plan
    if plan is None:
        raise UnsupportedMessageTypeError(f'{msg_type.__name__} does not have the short path')
    return plan


def payload_field(msg_type: Type) -> str:
    """Return the name of the payload field of ``msg_type``: its last top-level ``uint8[]``.

    What the single-payload API (``encode(msg, (backend, descriptor))``,
    ``Decoded.backend_type``) refers to. For every ``uint8[]`` field see :func:`buffer_paths`.

    :raises UnsupportedMessageTypeError: (a :class:`CodecError` and a ``TypeError``) when the
        codec cannot handle ``msg_type`` or it has no top-level ``uint8[]``; the message says why.
    """
    compiled = _codec(msg_type)
    if compiled.payload is None:
        kinds = msg_type.get_fields_and_field_types()
        deeper = (f'; its uint8[] fields are deeper: {", ".join(map(str, compiled.templates))} '
                  '(see codec.buffer_paths)' if compiled.templates else '')
        raise UnsupportedMessageTypeError(
            f'{msg_type.__name__} has no top-level uint8[] field (fields: '
            f'{", ".join(f"{n}: {k}" for n, k in kinds.items()) or "none"}){deeper}')
    return compiled.payload


def buffer_paths(msg_type: Type) -> Tuple[FieldPath, ...]:
    """The ``uint8[]`` fields of ``msg_type`` at any depth, in wire order, as template paths:
    :data:`EACH` stands for the elements of a sequence or array of messages
    (``('images', EACH, 'data')``). Empty for a type without any, or for anything the codec
    cannot handle; never raises."""
    try:
        return _codec(msg_type).templates
    except Exception:  # noqa: BLE001 - documented: never raises
        return ()


def _instance_blobs(msg: Any, tree: _Tree, prefix: Tuple) -> Iterator[Tuple[Tuple, Any]]:
    for slot, name, kind, sub in tree:
        value = getattr(msg, slot)
        if kind == _T_BLOB:
            yield prefix + (name,), value
        elif kind == _T_MESSAGE:
            yield from _instance_blobs(value, sub, prefix + (name,))
        else:
            for index, element in enumerate(value):
                yield from _instance_blobs(element, sub, prefix + (name, index))


def _blobs_of(msg: Any) -> Iterator[Tuple[Tuple, Any]]:
    try:
        yield from _instance_blobs(msg, _codec(type(msg)).tree, ())
    except (AttributeError, TypeError) as exc:
        if isinstance(exc, UnsupportedMessageTypeError):
            raise
        raise CodecError(f'{type(msg).__name__} instance is malformed: {exc}') from None


def field_paths(msg: Any) -> Tuple[FieldPath, ...]:
    """The paths of every ``uint8[]`` field of the message ``msg`` (element indices resolved),
    in wire order.

    :raises UnsupportedMessageTypeError: when the codec cannot handle ``type(msg)``.
    """
    return tuple(FieldPath(path) for path, _ in _blobs_of(msg))


def buffers_of(msg: Any) -> List[BufferAt]:
    """The ``uint8[]`` fields of ``msg`` that hold a :class:`~rosidl_buffer_py.Buffer`, in wire
    order.

    :raises UnsupportedMessageTypeError: when the codec cannot handle ``type(msg)``.
    """
    return [BufferAt(FieldPath(path), value) for path, value in _blobs_of(msg)
            if isinstance(value, Buffer)]


# --- encode --------------------------------------------------------------------------------------

def _payload_view(value: Any, field: Any) -> memoryview:
    """The payload as a flat, C-contiguous memoryview of bytes (no copy when possible)."""
    if isinstance(value, Buffer):
        if value.host_addressable:
            view = memoryview(value)
        else:
            try:
                data = value.host_bytes()
            except Exception as exc:
                raise CodecError(f'{field}: {value!r} cannot be read as CPU bytes: '
                                 f'{type(exc).__name__}: {exc}') from exc
            view = memoryview(data)
        if view.nbytes != len(value):
            raise CodecError(f'{field}: {value!r} gave {view.nbytes} bytes, not {len(value)}')
    elif isinstance(value, (list, tuple)):
        try:
            view = memoryview(bytes(value))
        except (TypeError, ValueError) as exc:
            raise CodecError(f'{field}: a {type(value).__name__} payload must hold ints in '
                             f'[0, 255]: {exc}') from None
    else:
        try:
            view = memoryview(value)
        except TypeError:
            raise CodecError(
                f'{field}: cannot send a {type(value).__name__} as uint8[]; accepted: '
                'array.array("B"), bytes, bytearray, memoryview, list, numpy uint8 array, '
                'Buffer') from None
        if view.format not in ('B', 'c') or view.itemsize != 1:
            raise CodecError(f'{field}: payload items must be uint8 (format "B"), got format '
                             f'{view.format!r} from {type(value).__name__}')
    if not view.c_contiguous:
        view = memoryview(view.tobytes())  # strided (e.g. a numpy slice): one gathering copy
    elif view.ndim != 1 or view.format != 'B':
        view = view.cast('B')
    return view


def _serialize(msg: Any) -> bytes:
    try:
        return serialize_message(msg)
    except Exception as exc:
        raise CodecError(f'cannot serialize {type(msg).__name__}: {type(exc).__name__}: '
                         f'{exc}') from exc


def _check_descriptor(descriptor: Any) -> Tuple[bytes, bytes]:
    try:
        backend_type, data = descriptor
    except (TypeError, ValueError):
        raise CodecError('descriptor must be a (backend_type, descriptor_bytes) pair, got '
                         f'{descriptor!r:.200}') from None
    if not isinstance(backend_type, str) or not backend_type or '\x00' in backend_type:
        raise CodecError('backend_type must be a non-empty str without NUL, got '
                         f'{backend_type!r:.200}')
    try:
        data = bytes(memoryview(data).cast('B')) if not isinstance(data, bytes) else data
    except TypeError:
        raise CodecError(f'descriptor bytes must be bytes-like, got {type(data).__name__}') \
            from None
    if len(data) > MAX_DESCRIPTOR_SIZE:
        raise CodecError(f'descriptor of backend {backend_type!r} is {len(data)} bytes, more '
                         f'than MAX_DESCRIPTOR_SIZE ({MAX_DESCRIPTOR_SIZE})')
    try:
        name = backend_type.encode('utf-8')
    except UnicodeEncodeError as exc:
        raise CodecError(f'backend_type {backend_type!r:.200} is not encodable as UTF-8: '
                         f'{exc}') from None
    return name, data


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


def _strip(msg: Any, tree: _Tree, prefix: Tuple, values: Dict[Tuple, Any]) -> Any:
    """A shallow copy of ``msg`` whose ``uint8[]`` fields are empty (copied down to them); their
    values go to ``values`` by path."""
    cls = type(msg)
    clone = cls.__new__(cls)
    for slot in cls.__slots__:
        setattr(clone, slot, getattr(msg, slot))
    for slot, name, kind, sub in tree:
        value = getattr(msg, slot)
        if kind == _T_BLOB:
            values[prefix + (name,)] = value
            setattr(clone, slot, _EMPTY_PAYLOAD)
        elif kind == _T_MESSAGE:
            setattr(clone, slot, _strip(value, sub, prefix + (name,), values))
        else:
            setattr(clone, slot, [_strip(element, sub, prefix + (name, index), values)
                                  for index, element in enumerate(value)])
    return clone


def _as_path(key: Any) -> FieldPath:
    try:
        path = FieldPath(key)
    except (TypeError, ValueError) as exc:
        raise CodecError(f'descriptors: {key!r:.100} is not a field path: {exc}') from None
    if not path or path.is_template:
        raise CodecError(f'descriptors: {key!r:.100} does not name one field of a message')
    return path


def _check_descriptors(descriptors: Mapping) -> Dict[FieldPath, Tuple[bytes, bytes]]:
    try:
        items = list(descriptors.items())
    except (AttributeError, TypeError):
        raise CodecError('descriptors must be a mapping {field path: (backend_type, '
                         f'descriptor_bytes)}}, got {descriptors!r:.200}') from None
    checked = {}
    for key, value in items:
        path = _as_path(key)
        try:
            checked[path] = _check_descriptor(value)
        except CodecError as exc:
            raise CodecError(f'{path}: {exc}') from None
    return checked


def _write_descriptor(out: _Out, u32: struct.Struct, name: bytes, data: bytes) -> None:
    """The descriptor form at ``out``'s position (4-aligned): marker, backend, descriptor."""
    cur = out.cur
    cur += _MARKER_BYTES
    cur += u32.pack(len(name) + 1)
    cur += name
    cur += b'\x00'
    out.pad(4)
    cur += u32.pack(len(data))
    cur += data


def _encode_walk(msg: Any, compiled: _TypeCodec, descriptors: Dict[FieldPath, Tuple],
                 apart: Optional[Tuple] = None) -> _Out:
    """Encode ``msg`` with the general walker: the fields in ``descriptors`` as descriptors, the
    others as CPU bytes; the payload at path ``apart`` is kept as its own part of the output."""
    values: Dict[Tuple, Any] = {}
    try:
        clone = _strip(msg, compiled.tree, (), values)
    except (AttributeError, TypeError) as exc:
        raise CodecError(f'{type(msg).__name__} instance is malformed: {type(exc).__name__}: '
                         f'{exc}') from None
    for path in descriptors:
        if path not in values:
            raise CodecError(
                f'descriptors: {type(msg).__name__} has no uint8[] field {path} (this '
                f'message\'s: {", ".join(str(FieldPath(p)) for p in values) or "none"})')
    small = _serialize(clone)
    u32 = _U32[small[1] == ENCAPSULATION_CDR_LE]
    unpack = u32.unpack_from
    body = memoryview(small)[_HEADER_SIZE:]
    end = len(body)
    out = _Out(small[:_HEADER_SIZE])
    lengths: List[int] = []  # of the CPU payloads, in wire order (for _estimate)

    def blob(path: Tuple, label: str, pos: int) -> int:
        _, pos = _read_u32(body, pos, end, unpack, label)  # the clone's empty field
        out.pad(4)
        described = descriptors.get(path)
        if described is None:
            view = _payload_view(values[path], FieldPath(path))  # printed on errors only
            out.cur += u32.pack(view.nbytes)
            out.payload(view, path == apart)
            lengths.append(view.nbytes)
        else:
            _write_descriptor(out, u32, *described)
            lengths.append(0)
        return pos

    _walk(compiled.ops, body, 0, end, unpack, out, (), blob)
    if compiled.plain:
        out.pad(4)  # as rmw_fastrtps sizes a fixed-size message: a multiple of 4
    elif compiled.slack:
        _, estimate = _estimate(compiled.ops, body, 0, end, unpack, 0, iter(lengths))
        written = out.base + len(out.cur)
        if estimate > written:
            out.cur += bytes(estimate - written)
    return out


def _estimate(ops: Tuple[tuple, ...], buf: memoryview, pos: int, end: int, unpack, est: int,
              lengths: Iterator[int]) -> Tuple[int, int]:
    """(position after ``ops``, rmw_fastrtps' size estimate at that point) over well-formed
    ``buf`` (a clone's serialization) whose ``_BLOB`` fields really are ``lengths`` long.

    ``serialize_message`` returns as many bytes as the type support's ``get_serialized_size``
    estimates, which counts the element alignment of empty sequences and a NUL per wstring that
    the data does not have: the bytes past the data are slack (uninitialized), matched here with
    zeros.
    """
    for op in ops:
        kind = op[0]
        if kind == _FIXED:
            align = op[1]
            pos = ((pos + align - 1) & -align) + op[2]
            est = ((est + align - 1) & -align) + op[2]
        elif kind == _ARRAY:
            for _ in range(op[2]):
                pos, est = _estimate(op[1], buf, pos, end, unpack, est, lengths)
        else:
            count, pos = _read_u32(buf, pos, end, unpack, 'a length')  # checked before
            est = ((est + 3) & -4) + 4
            if kind == _STRING:
                pos += count
                est += count
            elif kind == _WSTRING:
                pos += 4 * count
                est += 4 * (count + 1)
            elif kind == _PSEQ:
                align = op[1]
                if count:
                    pos = ((pos + align - 1) & -align) + count * op[2]
                est = ((est + align - 1) & -align) + count * op[2]
            elif kind == _SEQ:
                for _ in range(count):
                    pos, est = _estimate(op[1], buf, pos, end, unpack, est, lengths)
            else:  # _BLOB: empty in buf
                est += next(lengths)
    return pos, est


def _encode_head(msg: Any, plan: _Plan) -> Tuple[bytearray, bytes, Any]:
    """Serialize ``msg`` without its payload: (header + prefix with zero padding, suffix, u32)."""
    msg_type = plan.msg_type
    clone = msg_type.__new__(msg_type)
    try:
        for slot in plan.slots:
            setattr(clone, slot, getattr(msg, slot))
    except AttributeError as exc:
        raise CodecError(f'{msg_type.__name__} instance is incomplete: {exc}') from None
    setattr(clone, plan.slot, _EMPTY_PAYLOAD)
    small = _serialize(clone)
    u32 = _U32[small[1] == ENCAPSULATION_CDR_LE]
    body = memoryview(small)[_HEADER_SIZE:]
    out = _Out(small[:_HEADER_SIZE])
    pos = _walk(plan.prefix_ops, body, 0, len(body), u32.unpack_from, out)
    out.pad(4)
    start = (pos + 3) & -4
    return out.cur, bytes(body[start + 4:start + 4 + plan.suffix_size]), u32


def encode_parts(msg: Any) -> EncodedParts:
    """The legacy CDR bytes of ``msg`` as :class:`EncodedParts`, without joining them.

    ``b''.join(encode_parts(msg))`` equals ``encode(msg)``. A writer that takes a list of
    buffers (``os.writev``, a file) writes the payload (the :func:`payload_field`) straight from
    the message's memory: for a shared-memory Buffer, no copy of the payload is made in this
    process. Other ``uint8[]`` fields are copied into ``head`` or ``suffix``.

    :raises CodecError: on a payload or field value that cannot be encoded, or a type without a
        top-level ``uint8[]`` field (:class:`UnsupportedMessageTypeError`).
    """
    compiled = _codec(type(msg))
    plan = compiled.plan
    if plan is not None:
        view = _payload_view(getattr(msg, plan.slot, None), plan.field)
        head, suffix, u32 = _encode_head(msg, plan)
        head += u32.pack(view.nbytes)
        return EncodedParts(head, view, suffix)
    path = (payload_field(compiled.msg_type),)
    out = _encode_walk(msg, compiled, {}, apart=path)
    parts = out.finish()
    index = out.apart
    return EncodedParts(bytearray().join(parts[:index]), parts[index],
                        b''.join(parts[index + 1:]))


def encode(msg: Any,
           descriptor: Union[None, Tuple[str, bytes], Mapping[Any, Tuple[str, bytes]]] = None,
           *, descriptors: Optional[Mapping[Any, Tuple[str, bytes]]] = None) -> bytearray:
    """Serialize ``msg`` (CDR with its 4-byte encapsulation header) for the wire.

    :param msg: A message of any type. A ``uint8[]`` field (at any depth) may hold
        ``array.array('B')``, bytes, bytearray, memoryview, a list of ints, a numpy uint8 array
        or a :class:`~rosidl_buffer_py.Buffer` (sent as its CPU bytes unless described).
    :param descriptor: ``None`` for CPU bytes: exactly the legacy wire format (as
        ``serialize_message``, with zero padding). Or a mapping ``{path: (backend_type,
        descriptor_bytes)}`` (path: a :class:`FieldPath`, a tuple such as ``('image', 'data')``
        or its text ``'images[3].data'``): those fields are sent as the marker, the backend name
        and the descriptor, every other ``uint8[]`` as CPU bytes. A bare ``(backend_type,
        descriptor_bytes)`` pair is the descriptor of the :func:`payload_field`.
    :param descriptors: The mapping, by keyword (instead of ``descriptor``).
    :raises CodecError: on a payload, descriptor, path or field value that cannot be encoded.
    """
    if descriptors is not None:
        if descriptor is not None:
            raise TypeError('encode() takes descriptor or descriptors, not both')
        if not isinstance(descriptors, Mapping):
            raise CodecError('descriptors must be a mapping {field path: (backend_type, '
                             f'descriptor_bytes)}}, got {descriptors!r:.200}')
        descriptor = descriptors
    descriptors = descriptor
    compiled = _codec(type(msg))
    plan = compiled.plan
    if descriptors is None:
        if plan is not None:
            head, view, suffix = encode_parts(msg)
            head += view
            head += suffix
            return head
        return _encode_walk(msg, compiled, {}).joined()
    if type(descriptors) is tuple or not isinstance(descriptors, Mapping):  # one pair
        backend, data = _check_descriptor(descriptors)
        if plan is None:
            return _encode_walk(msg, compiled,
                                {FieldPath((payload_field(type(msg)),)): (backend, data)}).joined()
    else:
        checked = _check_descriptors(descriptors)
        if plan is None or (checked and set(checked) != {plan.path}):
            return _encode_walk(msg, compiled, checked).joined()
        if not checked:
            return encode(msg)
        backend, data = checked[plan.path]
    # the same bytes from C (None when it cannot: the code below then says why)
    out = _native.encode_descriptor(msg, plan.slots, plan.slot, _EMPTY_PAYLOAD, backend,
                                    data, plan.suffix_size)
    if out is not None:
        return out
    head, suffix, u32 = _encode_head(msg, plan)
    out = _Out(head)
    _write_descriptor(out, u32, backend, data)
    out.cur += suffix
    return out.cur


# --- decode --------------------------------------------------------------------------------------

def _deserialize(raw: bytes, msg_type: Type) -> Any:
    try:
        return deserialize_message(raw, msg_type)
    except Exception as exc:
        raise CodecError(f'cannot deserialize {msg_type.__name__}: {type(exc).__name__}: '
                         f'{exc}') from exc


def _input_view(raw: Any) -> memoryview:
    try:
        view = memoryview(raw)
    except TypeError:
        raise CodecError(f'raw must be bytes, bytearray or memoryview, got '
                         f'{type(raw).__name__}') from None
    if view.ndim != 1 or view.format != 'B':
        if not view.c_contiguous:
            raise CodecError('raw must be contiguous bytes')
        view = view.cast('B')
    return view


def _open(raw: Any) -> Tuple[memoryview, memoryview, int, Any]:
    """(whole input, body from the CDR origin, body length, uint32 unpacker) of CDR bytes."""
    view = _input_view(raw)
    size = len(view)
    if size < _HEADER_SIZE:
        raise CodecError(f'truncated message: {size} bytes, shorter than the 4-byte CDR '
                         'encapsulation header')
    kind = (view[0] << 8) | view[1]
    if kind == ENCAPSULATION_CDR_LE:
        little = True
    elif kind == ENCAPSULATION_CDR_BE:
        little = False
    else:
        raise CodecError(f'unsupported CDR encapsulation 0x{kind:04x}; accepted: 0x0000 (CDR big '
                         'endian) and 0x0001 (CDR little endian)')
    return view, view[_HEADER_SIZE:], size - _HEADER_SIZE, _U32[little].unpack_from


def _read_descriptor(body: memoryview, pos: int, end: int, unpack, label: str,
                     known_backends: Optional[Container[str]]) -> Tuple[FieldDescriptor, int]:
    """The backend name and descriptor after a marker at ``pos``; (descriptor, position after)."""
    at = pos + _HEADER_SIZE
    length, pos = _read_u32(body, pos, end, unpack, 'the backend name length')
    if length == 0 or length > end - pos:
        raise CodecError(f'backend name at offset {at} claims {length} bytes (with NUL); '
                         f'{end - pos} are left')
    if body[pos + length - 1] != 0:
        raise CodecError(f'backend name at offset {at} is not NUL-terminated')
    try:
        backend_type = str(body[pos:pos + length - 1], 'utf-8')
    except UnicodeDecodeError:
        raise CodecError(f'backend name at offset {at} is not UTF-8: '
                         f'{bytes(body[pos:pos + length - 1])!r:.100}') from None
    if not backend_type or '\x00' in backend_type:
        raise CodecError(f'backend name at offset {at} is invalid: {backend_type!r:.100}')
    if known_backends is not None and backend_type not in known_backends:
        try:
            known = ', '.join(sorted(known_backends))  # type: ignore[call-overload]
        except TypeError:
            known = repr(known_backends)
        raise CodecError(f'unknown backend {backend_type!r:.100} in the descriptor of '
                         f'{label}; known: {known}')
    pos += length
    nbytes, pos = _read_u32(body, pos, end, unpack, 'the descriptor length')
    if nbytes > MAX_DESCRIPTOR_SIZE:
        raise CodecError(f'descriptor of backend {backend_type!r} is {nbytes} bytes, more '
                         f'than MAX_DESCRIPTOR_SIZE ({MAX_DESCRIPTOR_SIZE})')
    if nbytes > end - pos:
        raise CodecError(f'descriptor of backend {backend_type!r} claims {nbytes} bytes but '
                         f'only {end - pos} are left')
    return FieldDescriptor(backend_type, bytes(body[pos:pos + nbytes])), pos + nbytes


def decode(raw: Any, msg_type: Type,
           known_backends: Optional[Container[str]] = None) -> Decoded:
    """Deserialize wire bytes (CDR with the encapsulation header) of ``msg_type``.

    :param raw: bytes, bytearray or memoryview.
    :param msg_type: The message class (any type: see :func:`buffer_paths` for its ``uint8[]``
        fields).
    :param known_backends: When given, a descriptor whose backend is not in it is rejected.
    :return: A :class:`Decoded`: the message (each field that came as CPU bytes holds them, as
        ``deserialize_message`` gives) and the descriptors by path. Legacy bytes decode to the
        message ``deserialize_message`` gives.
    :raises CodecError: on malformed input, an unknown backend or an oversized descriptor.
    """
    compiled = _codec(msg_type)
    plan = compiled.plan
    if plan is None:
        return _decode_walk(raw, compiled, known_backends)[0]
    # Descriptor messages are decoded in C; CPU bytes and anything malformed come back as None
    # and take the path below (which names what is wrong).
    fast = _native.decode_descriptor(raw, msg_type, plan.prefix_ops, plan.suffix_size,
                                     MAX_DESCRIPTOR_SIZE)
    if fast is not None and (known_backends is None or fast[1] in known_backends):
        msg, backend_type, descriptor = fast
        return Decoded(msg, backend_type, descriptor,
                       {plan.path: FieldDescriptor(backend_type, descriptor)})
    decoded, payload = _decode_short(raw, plan, known_backends)
    if payload.nbytes:
        getattr(decoded.msg, plan.slot).frombytes(payload)
    return decoded


def split_payload(raw: Any, msg_type: Type) -> Tuple[Any, memoryview]:
    """Split legacy CDR bytes of ``msg_type`` into the message and a view of its payload bytes
    (those of its :func:`payload_field`).

    The message's payload field is left empty; the view points into ``raw`` (no copy), so that
    a caller can put the payload where it wants it (a backend's memory) with one copy.

    :raises CodecError: on malformed input, on descriptor-encoded bytes (no payload here), or
        a type without a top-level ``uint8[]`` (:class:`UnsupportedMessageTypeError`).
    """
    compiled = _codec(msg_type)
    if compiled.plan is not None:
        decoded, payload = _decode_short(raw, compiled.plan, None)
    else:
        path = FieldPath((payload_field(msg_type),))
        decoded, payloads = _decode_walk(raw, compiled, None, keep=path)
        payload = payloads.get(path, memoryview(b''))
    if decoded.is_descriptor:
        path, described = next(iter(decoded.descriptors.items()))
        raise CodecError(f'{path} holds a descriptor of backend {described.backend_type!r}, '
                         'not payload bytes')
    return decoded.msg, payload


def _decode_walk(raw: Any, compiled: _TypeCodec, known_backends: Optional[Container[str]],
                 keep: Optional[Tuple] = None) -> Tuple[Decoded, Dict[Tuple, memoryview]]:
    """:func:`decode` with the general walker. The CPU bytes of the field at path ``keep`` are
    not put in the message but returned, by path, as a view into ``raw``."""
    view, body, end, unpack = _open(raw)
    out = _Out(view[:_HEADER_SIZE])
    payloads: Dict[Tuple, memoryview] = {}
    descriptors: Dict[FieldPath, FieldDescriptor] = {}

    def blob(path: Tuple, label: str, pos: int) -> int:
        first, pos = _read_u32(body, pos, end, unpack, f'the length of {FieldPath(path)}')
        out.pad(4)
        out.cur += _ZERO_LENGTH
        if first == DESCRIPTOR_MARKER:
            path = FieldPath(path)
            descriptors[path], pos = _read_descriptor(body, pos, end, unpack, str(path),
                                                      known_backends)
        else:
            if first > end - pos:
                raise CodecError(f'{FieldPath(path)} claims {first} bytes at offset '
                                 f'{pos - 4 + _HEADER_SIZE} but only {end - pos} are left')
            payloads[path] = body[pos:pos + first]
            pos += first
        return pos

    _walk(compiled.ops, body, 0, end, unpack, out, (), blob)
    msg = _deserialize(bytes(out.cur), compiled.msg_type)
    try:
        for path, data in payloads.items():
            if data.nbytes and path != keep:
                get_at(msg, path).frombytes(data)
    except (LookupError, AttributeError) as exc:  # the message does not match its walk
        raise CodecError(f'{compiled.msg_type.__name__}: {exc}') from None
    legacy = None
    if compiled.payload is not None:
        legacy = descriptors.get((compiled.payload,))
    decoded = Decoded(msg, legacy and legacy.backend_type, legacy and legacy.descriptor,
                      descriptors)
    return decoded, payloads


def _decode_short(raw: Any, plan: _Plan,
                  known_backends: Optional[Container[str]]) -> Tuple[Decoded, memoryview]:
    """:func:`decode` of the short path with an empty payload field, and a view of the payload
    bytes in ``raw``."""
    view, body, end, unpack = _open(raw)
    pos = _walk(plan.prefix_ops, body, 0, end, unpack)
    first, pos = _read_u32(body, pos, end, unpack, f'the length of {plan.field}')
    head_end = _HEADER_SIZE + pos - 4

    descriptors = {}
    if first == DESCRIPTOR_MARKER:
        described, pos = _read_descriptor(body, pos, end, unpack, plan.field, known_backends)
        descriptors[plan.path] = described
        data_start = data_end = pos
    else:
        if first > end - pos:
            raise CodecError(f'{plan.field} claims {first} bytes at offset '
                             f'{pos - 4 + _HEADER_SIZE} but only {end - pos} are left')
        data_start, data_end = pos, pos + first
    if plan.suffix_size > end - data_end:
        raise _truncated(f'the fields after {plan.field}', data_end, plan.suffix_size, end)

    small = b''.join((view[:head_end], _ZERO_LENGTH,
                      body[data_end:data_end + plan.suffix_size]))
    msg = _deserialize(small, plan.msg_type)
    setattr(msg, plan.slot, array.array('B'))
    described = descriptors.get(plan.path)
    return (Decoded(msg, described and described.backend_type,
                    described and described.descriptor, descriptors),
            body[data_start:data_end])
