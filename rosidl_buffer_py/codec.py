"""The wire format of messages with a ``uint8[]`` payload field (``sensor_msgs/Image.data``).

Two encodings share one layout, as in upstream's native buffer feature (XCDR1, the bytes
``rclpy.serialization.serialize_message`` produces, 4-byte encapsulation header included):

* **CPU** (legacy): exactly the bytes of a stock ``uint8[]``: ``uint32 length`` + the bytes. Every
  ROS 2 node, ``ros2 bag`` and this package read it; a vendor Buffer that cannot be described to a
  peer falls back to it.
* **Descriptor**: where the payload's ``uint32 length`` would be, the marker ``0xFFFFFFFF``, the
  backend name as a CDR string, then (aligned to 4) ``uint32 length`` + the descriptor bytes
  (at most :data:`~rosidl_buffer_py.MAX_DESCRIPTOR_SIZE`). The payload bytes stay in the backend's
  memory; the receiver resolves the descriptor with that backend.

A decoder peeks the payload's first ``uint32``: the marker selects the descriptor path, any other
value is a legacy length (a 4 GiB payload cannot be sent anyway).

rclpy's C serializer does the small non-payload part of every message; the payload is spliced in
with one copy, so encode and decode cost about one ``memcpy`` of the payload. A per-type walker,
compiled once from the message's ``SLOT_TYPES``, finds the payload and checks every length against
the end of the input before anything is read, so malformed input raises :class:`CodecError` and
never reads out of bounds.

Unlike ``serialize_message``, which leaves its alignment padding uninitialized (it carries stale
heap bytes), :func:`encode` writes zero padding; every other byte is the same.
"""
import array
import importlib
import struct
import threading
from dataclasses import dataclass
from typing import Any, Container, Dict, List, NamedTuple, Optional, Tuple, Type

from rclpy.serialization import deserialize_message, serialize_message
from rosidl_parser import definition

from rosidl_buffer_py import _native
from rosidl_buffer_py.backend import MAX_DESCRIPTOR_SIZE
from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.message_support import enable_buffer_fields

__all__ = [
    'CodecError',
    'DESCRIPTOR_MARKER',
    'Decoded',
    'EncodedParts',
    'UnsupportedMessageTypeError',
    'decode',
    'encode',
    'encode_parts',
    'payload_field',
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
_U32 = {True: struct.Struct('<I'), False: struct.Struct('>I')}
_MARKER_BYTES = b'\xff\xff\xff\xff'
#: The payload of the clone that encode_descriptor serializes (read, never modified).
_EMPTY_PAYLOAD = array.array('B')

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
    """A message type this codec cannot handle (no payload field, unsupported field types...)."""


@dataclass
class Decoded:
    """The result of :func:`decode`.

    :ivar msg: The message. On the CPU path its payload field holds the bytes as
        ``array.array('B')``; on the descriptor path it holds an empty ``array.array('B')``.
    :ivar backend_type: Backend named by the descriptor, or ``None`` for CPU bytes.
    :ivar descriptor: The descriptor bytes, or ``None`` for CPU bytes.
    """

    msg: Any
    backend_type: Optional[str] = None
    descriptor: Optional[bytes] = None

    @property
    def is_descriptor(self) -> bool:
        """True when the payload travelled as a descriptor."""
        return self.backend_type is not None


# --- the compiled walker -----------------------------------------------------------------------
#
# Positions are relative to the CDR origin (just after the encapsulation header): XCDR1 aligns
# every primitive to its size relative to that origin. Ops:
#   (_FIXED, align, size, inner_pads, label)      fixed-size run; its first item aligns to `align`
#                                                 and every later item's alignment divides it
#   (_STRING, bound, label)                       uint32 length (incl. NUL) + chars + NUL
#   (_PSEQ, align, itemsize, bound, label)        uint32 count + primitives (aligned if count > 0)
#   (_SEQ, sub_ops, min_size, bound, label)       uint32 count + elements walked with sub_ops
#   (_ARRAY, sub_ops, count, label)               count elements walked with sub_ops
_FIXED, _STRING, _PSEQ, _SEQ, _ARRAY = range(5)


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
        elif kind in (_PSEQ, _SEQ):
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
            f'{msg_type!r} is not a generated ROS message class') from None
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


def _add_type(builder: _Builder, slot_type: Any, label: str, stack: Tuple[Type, ...]) -> None:
    """Append the ops of one value of ``slot_type`` (a rosidl_parser.definition type)."""
    if isinstance(slot_type, definition.BasicType):
        size = _BASIC_SIZES.get(slot_type.typename)
        if size is None:
            raise UnsupportedMessageTypeError(
                f'field {label!r} has type {slot_type.typename!r}, which this codec does not '
                f'support (supported basic types: {", ".join(sorted(_BASIC_SIZES))})')
        builder.fixed(size, size, label)
    elif isinstance(slot_type, definition.AbstractWString):
        raise UnsupportedMessageTypeError(
            f'field {label!r} is a wstring, which this codec does not support')
    elif isinstance(slot_type, definition.AbstractString):
        builder.add([_STRING, getattr(slot_type, 'maximum_size', None), label])
    elif isinstance(slot_type, definition.NamespacedType):
        nested = _nested_class(slot_type)
        if nested in stack:
            raise UnsupportedMessageTypeError(f'{nested.__name__} contains itself ({label!r})')
        for name, field_type in _fields(nested):
            _add_type(builder, field_type, f'{label}.{name}', stack + (nested,))
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
            sub = _element_ops(value_type, label + '[]', stack)
            if slot_type.size:
                builder.add([_ARRAY, sub, slot_type.size, label])
            return
        bound = getattr(slot_type, 'maximum_size', None)
        if basic:
            size = _BASIC_SIZES[value_type.typename]
            builder.add([_PSEQ, size, size, bound, label])
            return
        sub = _element_ops(value_type, label + '[]', stack)
        min_size = _min_size(sub)
        if min_size <= 0:
            raise UnsupportedMessageTypeError(
                f'field {label!r}: sequences of zero-size elements are not supported')
        builder.add([_SEQ, sub, min_size, bound, label])
    else:
        raise UnsupportedMessageTypeError(
            f'field {label!r} has a type this codec does not support: {slot_type!r}')


def _element_ops(value_type: Any, label: str, stack: Tuple[Type, ...]) -> Tuple[tuple, ...]:
    builder = _Builder()
    _add_type(builder, value_type, label, stack)
    return builder.freeze()


def _truncated(label: str, offset: int, needed: int, end: int) -> CodecError:
    return CodecError(
        f'truncated message: {label} needs {needed} bytes at offset {offset + _HEADER_SIZE} but '
        f'the message ends at offset {end + _HEADER_SIZE}')


def _read_u32(buf: memoryview, pos: int, end: int, unpack, label: str,
              pads: Optional[List[Tuple[int, int]]]) -> Tuple[int, int]:
    """Return (value, position after) of the 4-aligned uint32 at or after ``pos``."""
    start = (pos + 3) & -4
    if start + 4 > end:
        raise _truncated(label, start, 4, end)
    if pads is not None and start != pos:
        pads.append((pos, start))
    return unpack(buf, start)[0], start + 4


def _walk(ops: Tuple[tuple, ...], buf: memoryview, pos: int, end: int, unpack,
          pads: Optional[List[Tuple[int, int]]]) -> int:
    """Walk ``ops`` over ``buf`` from ``pos``; return the position after them.

    ``buf`` starts at the CDR origin. Every length is checked against ``end`` before it is used.
    When ``pads`` is a list, the alignment padding met is appended to it as (start, end) ranges.
    """
    for op in ops:
        kind = op[0]
        if kind == _FIXED:
            align = op[1]
            start = (pos + align - 1) & -align
            if start + op[2] > end:
                raise _truncated(op[4], start, op[2], end)
            if pads is not None:
                if start != pos:
                    pads.append((pos, start))
                pads.extend((start + s, start + e) for s, e in op[3])
            pos = start + op[2]
        elif kind == _STRING:
            label = op[2]
            length, pos = _read_u32(buf, pos, end, unpack, f'the length of string {label}', pads)
            at = pos - 4 + _HEADER_SIZE
            if length == 0:
                raise CodecError(f'string {label} at offset {at} has length 0; a CDR string '
                                 'length counts its terminating NUL')
            if length > end - pos:
                raise CodecError(f'string {label} at offset {at} claims {length} bytes but only '
                                 f'{end - pos} are left')
            if buf[pos + length - 1] != 0:
                raise CodecError(f'string {label} at offset {at} is not NUL-terminated')
            if op[1] is not None and length - 1 > op[1]:
                raise CodecError(f'string {label} at offset {at} has {length - 1} characters, '
                                 f'more than its bound {op[1]}')
            pos += length
        elif kind == _PSEQ:
            label = op[4]
            count, pos = _read_u32(buf, pos, end, unpack, f'the count of sequence {label}', pads)
            if op[3] is not None and count > op[3]:
                raise CodecError(f'sequence {label} has {count} elements, more than its bound '
                                 f'{op[3]}')
            if count:  # Fast CDR aligns the elements only when there are some
                align = op[1]
                start = (pos + align - 1) & -align
                nbytes = count * op[2]
                if nbytes > end - start:
                    raise CodecError(
                        f'sequence {label} at offset {pos - 4 + _HEADER_SIZE} claims {count} '
                        f'elements ({nbytes} bytes) but only {max(end - start, 0)} bytes are left')
                if pads is not None and start != pos:
                    pads.append((pos, start))
                pos = start + nbytes
        elif kind == _SEQ:
            label = op[4]
            count, pos = _read_u32(buf, pos, end, unpack, f'the count of sequence {label}', pads)
            if op[3] is not None and count > op[3]:
                raise CodecError(f'sequence {label} has {count} elements, more than its bound '
                                 f'{op[3]}')
            if count * op[2] > end - pos:
                raise CodecError(
                    f'sequence {label} at offset {pos - 4 + _HEADER_SIZE} claims {count} elements '
                    f'(at least {count * op[2]} bytes) but only {end - pos} bytes are left')
            sub = op[1]
            for _ in range(count):
                pos = _walk(sub, buf, pos, end, unpack, pads)
        else:  # _ARRAY
            sub = op[1]
            for _ in range(op[2]):
                pos = _walk(sub, buf, pos, end, unpack, pads)
    return pos


# --- per-type plans ------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Plan:
    msg_type: Type
    field: str                      # the payload field
    slot: str                       # its __slots__ entry ('_data')
    slots: Tuple[str, ...]          # every slot, copied into the clone that encode serializes
    plain_slots: Tuple[str, ...]    # other uint8[] fields (a Buffer there is sent as bytes)
    prefix_ops: Tuple[tuple, ...]   # the fields before the payload
    suffix_size: int                # the fields after it: alignment 1, fixed size


_plans: Dict[Type, _Plan] = {}
_plans_lock = threading.Lock()


def _compile(msg_type: Type) -> _Plan:
    fields = _fields(msg_type)
    kinds = msg_type.get_fields_and_field_types()
    payload_index = None
    for index, (name, _) in enumerate(fields):
        if kinds[name] == _UINT8_SEQUENCE:
            payload_index = index
    if payload_index is None:
        raise UnsupportedMessageTypeError(
            f'{msg_type.__name__} has no top-level uint8[] field (fields: '
            f'{", ".join(f"{n}: {kinds[n]}" for n, _ in fields) or "none"})')
    field = fields[payload_index][0]
    slots = tuple(msg_type.__slots__)
    slot = '_' + field
    if slot not in slots:
        raise UnsupportedMessageTypeError(
            f'{msg_type.__name__} has no slot {slot!r} for its field {field!r}')

    prefix = _Builder()
    for name, slot_type in fields[:payload_index]:
        _add_type(prefix, slot_type, name, (msg_type,))

    suffix = _Builder()
    for name, slot_type in fields[payload_index + 1:]:
        _add_type(suffix, slot_type, name, (msg_type,))
    suffix_ops = suffix.freeze()
    for op in suffix_ops:
        if op[0] != _FIXED or op[1] != 1:
            raise UnsupportedMessageTypeError(
                f'{msg_type.__name__}: field {op[-1]!r} after the payload {field!r} needs '
                'alignment or has a variable size, so its padding would depend on the payload '
                'length; only fixed-size alignment-1 fields (bool, uint8, ...) may follow it')
    plain_slots = tuple('_' + name for name, _ in fields[:payload_index]
                        if kinds[name] == _UINT8_SEQUENCE)
    return _Plan(msg_type, field, slot, slots, plain_slots, prefix.freeze(),
                 sum(op[2] for op in suffix_ops))


def _plan(msg_type: Type) -> _Plan:
    try:
        plan = _plans.get(msg_type)
    except TypeError:  # unhashable: not a class
        plan = None
    if plan is None:
        if not isinstance(msg_type, type):
            raise UnsupportedMessageTypeError(
                f'expected a message class, got {type(msg_type).__name__} {msg_type!r:.200}')
        with _plans_lock:
            plan = _plans.get(msg_type)
            if plan is None:
                plan = _compile(msg_type)
                enable_buffer_fields(msg_type)
                _plans[msg_type] = plan
    return plan


def payload_field(msg_type: Type) -> str:
    """Return the name of the payload field of ``msg_type``: its last top-level ``uint8[]``.

    :raises UnsupportedMessageTypeError: (a :class:`CodecError` and a ``TypeError``) when the
        codec cannot handle ``msg_type``; the message says why.
    """
    return _plan(msg_type).field


# --- encode --------------------------------------------------------------------------------------

def _payload_view(value: Any, field: str) -> memoryview:
    """The payload as a flat, C-contiguous memoryview of bytes (no copy when possible)."""
    if isinstance(value, Buffer):
        if value.host_addressable:
            view = memoryview(value)
        else:
            try:
                data = value.to_bytes()
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
    :ivar suffix: The fixed-size fields after the payload.
    """

    head: bytearray
    payload: memoryview
    suffix: bytes

    @property
    def nbytes(self) -> int:
        """Length of the whole CDR message."""
        return len(self.head) + self.payload.nbytes + len(self.suffix)


def _encode_head(msg: Any, plan: _Plan) -> Tuple[bytearray, bytes, Any]:
    """Serialize ``msg`` without its payload: (header + prefix with zero padding, suffix, u32)."""
    msg_type = plan.msg_type
    clone = msg_type.__new__(msg_type)
    try:
        for slot in plan.slots:
            setattr(clone, slot, getattr(msg, slot))
    except AttributeError as exc:
        raise CodecError(f'{msg_type.__name__} instance is incomplete: {exc}') from None
    setattr(clone, plan.slot, array.array('B'))
    for slot in plan.plain_slots:
        value = getattr(clone, slot)
        if isinstance(value, Buffer):
            setattr(clone, slot, array.array('B', _payload_view(value, slot[1:])))
    small = _serialize(clone)

    little = small[1] == ENCAPSULATION_CDR_LE
    u32 = _U32[little]
    pads: List[Tuple[int, int]] = []
    body = memoryview(small)[_HEADER_SIZE:]
    pos = _walk(plan.prefix_ops, body, 0, len(body), u32.unpack_from, pads)
    start = (pos + 3) & -4
    if start != pos:
        pads.append((pos, start))
    out = bytearray(small[:_HEADER_SIZE])
    out += body[:start]
    for s, e in pads:
        out[_HEADER_SIZE + s:_HEADER_SIZE + e] = bytes(e - s)
    suffix = bytes(body[start + 4:start + 4 + plan.suffix_size])
    return out, suffix, u32


def encode_parts(msg: Any) -> EncodedParts:
    """The legacy CDR bytes of ``msg`` as :class:`EncodedParts`, without joining them.

    ``b''.join(encode_parts(msg))`` equals ``encode(msg)``. A writer that takes a list of
    buffers (``os.writev``, a file) writes the payload straight from the message's memory: for
    a shared-memory Buffer, no copy of the payload is made in this process.

    :raises CodecError: on a payload or field value that cannot be encoded.
    """
    plan = _plan(type(msg))
    view = _payload_view(getattr(msg, plan.slot, None), plan.field)
    head, suffix, u32 = _encode_head(msg, plan)
    head += u32.pack(view.nbytes)
    return EncodedParts(head, view, suffix)


def encode(msg: Any, descriptor: Optional[Tuple[str, bytes]] = None) -> bytearray:
    """Serialize ``msg`` (CDR with its 4-byte encapsulation header) for the wire.

    :param msg: A message whose type has a payload field (see :func:`payload_field`). The payload
        may be ``array.array('B')``, bytes, bytearray, memoryview, a list of ints, a numpy uint8
        array or a :class:`~rosidl_buffer_py.Buffer` (sent as its CPU bytes).
    :param descriptor: ``None`` for CPU bytes, exactly the legacy ``uint8[]`` wire format (as
        ``serialize_message``, with zero padding); or ``(backend_type, descriptor_bytes)`` to send
        the marker, the backend name and the descriptor instead of the payload bytes.
    :raises CodecError: on a payload, descriptor or field value that cannot be encoded.
    """
    if descriptor is None:
        head, view, suffix = encode_parts(msg)
        head += view
        head += suffix
        return head
    plan = _plan(type(msg))
    backend, data = _check_descriptor(descriptor)
    if not plan.plain_slots:
        # the same bytes from C (None when it cannot: the code below then says why)
        out = _native.encode_descriptor(msg, plan.slots, plan.slot, _EMPTY_PAYLOAD, backend,
                                        data, plan.suffix_size)
        if out is not None:
            return out
    out, suffix, u32 = _encode_head(msg, plan)
    out += _MARKER_BYTES
    out += u32.pack(len(backend) + 1)
    out += backend
    out += b'\x00'
    out += bytes(-(len(out) - _HEADER_SIZE) % 4)
    out += u32.pack(len(data))
    out += data
    out += suffix
    return out


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


def decode(raw: Any, msg_type: Type,
           known_backends: Optional[Container[str]] = None) -> Decoded:
    """Deserialize wire bytes (CDR with the encapsulation header) of ``msg_type``.

    :param raw: bytes, bytearray or memoryview.
    :param msg_type: The message class (see :func:`payload_field`).
    :param known_backends: When given, a descriptor whose backend is not in it is rejected.
    :return: A :class:`Decoded`. Legacy bytes decode to the message ``deserialize_message`` gives.
    :raises CodecError: on malformed input, an unknown backend or an oversized descriptor.
    """
    plan = _plan(msg_type)
    # Descriptor messages are decoded in C; CPU bytes and anything malformed come back as None
    # and take the path below (which names what is wrong).
    fast = _native.decode_descriptor(raw, msg_type, plan.prefix_ops, plan.suffix_size,
                                     MAX_DESCRIPTOR_SIZE)
    if fast is not None and (known_backends is None or fast[1] in known_backends):
        return Decoded(*fast)
    decoded, payload = _decode(raw, msg_type, known_backends)
    if payload.nbytes:
        getattr(decoded.msg, _plan(msg_type).slot).frombytes(payload)
    return decoded


def split_payload(raw: Any, msg_type: Type) -> Tuple[Any, memoryview]:
    """Split legacy CDR bytes of ``msg_type`` into the message and a view of its payload bytes.

    The message's payload field is left empty; the view points into ``raw`` (no copy), so that
    a caller can put the payload where it wants it (a backend's memory) with one copy.

    :raises CodecError: on malformed input, or on descriptor-encoded bytes (no payload here).
    """
    decoded, payload = _decode(raw, msg_type, None)
    if decoded.is_descriptor:
        raise CodecError(f'{_plan(msg_type).field} holds a descriptor of backend '
                         f'{decoded.backend_type!r}, not payload bytes')
    return decoded.msg, payload


def _decode(raw: Any, msg_type: Type,
            known_backends: Optional[Container[str]]) -> Tuple[Decoded, memoryview]:
    """:func:`decode` with an empty payload field, and a view of the payload bytes in ``raw``."""
    plan = _plan(msg_type)
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
    unpack = _U32[little].unpack_from
    body = view[_HEADER_SIZE:]
    end = size - _HEADER_SIZE
    pos = _walk(plan.prefix_ops, body, 0, end, unpack, None)
    first, pos = _read_u32(body, pos, end, unpack, f'the length of {plan.field}', None)
    head_end = _HEADER_SIZE + pos - 4

    backend_type = descriptor = None
    if first == DESCRIPTOR_MARKER:
        at = pos + _HEADER_SIZE
        length, pos = _read_u32(body, pos, end, unpack, 'the backend name length', None)
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
                             f'{plan.field}; known: {known}')
        pos += length
        nbytes, pos = _read_u32(body, pos, end, unpack, 'the descriptor length', None)
        if nbytes > MAX_DESCRIPTOR_SIZE:
            raise CodecError(f'descriptor of backend {backend_type!r} is {nbytes} bytes, more '
                             f'than MAX_DESCRIPTOR_SIZE ({MAX_DESCRIPTOR_SIZE})')
        if nbytes > end - pos:
            raise CodecError(f'descriptor of backend {backend_type!r} claims {nbytes} bytes but '
                             f'only {end - pos} are left')
        descriptor = bytes(body[pos:pos + nbytes])
        data_start = data_end = pos + nbytes
    else:
        if first > end - pos:
            raise CodecError(f'{plan.field} claims {first} bytes at offset '
                             f'{pos - 4 + _HEADER_SIZE} but only {end - pos} are left')
        data_start, data_end = pos, pos + first
    if plan.suffix_size > end - data_end:
        raise _truncated(f'the fields after {plan.field}', data_end, plan.suffix_size, end)

    small = b''.join((view[:head_end], _ZERO_LENGTH,
                      body[data_end:data_end + plan.suffix_size]))
    msg = _deserialize(small, msg_type)
    setattr(msg, plan.slot, array.array('B'))
    return Decoded(msg, backend_type, descriptor), body[data_start:data_end]
