"""The compiled walker: a message type's layout as ops, and the walk that checks and copies CDR.

The ops of a type are compiled once from its ``SLOT_TYPES`` (:class:`Builder`,
:func:`add_type`); :func:`walk` runs them over CDR bytes, checking every length against the end
of the input before it is used, and optionally copies the bytes realigned to an :class:`Out`.
"""
import importlib
from typing import Any, Callable, List, NamedTuple, Optional, Tuple, Type, Union

from rosidl_parser import definition

from rosidl_buffer_py.codec.wire import (
    BIG_PAYLOAD, CodecError, HEADER_SIZE, UnsupportedMessageTypeError, ZEROS)

# Wire size (= XCDR1 alignment) of each supported basic type.
BASIC_SIZES = {
    'boolean': 1, 'octet': 1, 'char': 1, 'int8': 1, 'uint8': 1,
    'short': 2, 'unsigned short': 2, 'int16': 2, 'uint16': 2,
    'long': 4, 'unsigned long': 4, 'int32': 4, 'uint32': 4, 'float': 4,
    'long long': 8, 'unsigned long long': 8, 'int64': 8, 'uint64': 8, 'double': 8,
}


# --- the compiled walker -----------------------------------------------------------------------
#
# Positions are relative to the CDR origin (just after the encapsulation header): XCDR1 aligns
# every primitive to its size relative to that origin. Ops, one NamedTuple class per kind, its
# first field the kind:
#   FixedOp(FIXED, align, size, inner_pads, label)      fixed-size run; its first item aligns to
#                                                       `align` and every later item's alignment
#                                                       divides it
#   StringOp(STRING, bound, label)                      uint32 length (incl. NUL) + chars + NUL
#   PrimitiveSeqOp(PSEQ, align, itemsize, bound, label) uint32 count + primitives (aligned if
#                                                       count > 0)
#   SeqOp(SEQ, sub_ops, min_size, bound, label, path)   uint32 count + elements walked with
#                                                       sub_ops
#   ArrayOp(ARRAY, sub_ops, count, label, path)         count elements walked with sub_ops
#   BlobOp(BLOB, path, label)                           an unbounded uint8[] field: CPU bytes
#                                                       (uint32 length + bytes) or a descriptor
#   WStringOp(WSTRING, bound, label)                    uint32 length (characters) + 4 bytes each
# `path` is the field's path relative to the element (or message) the ops belong to; nested
# messages are flattened into their parent's ops. src/native/codec_fast.cpp walks the first five
# kinds, reading each op by position (they are tuples): their field order is what it reads
# (test_codec.py's test_op_fields_are_in_the_order_the_fast_path_reads pins it).
FIXED, STRING, PSEQ, SEQ, ARRAY, BLOB, WSTRING = range(7)


class FixedOp(NamedTuple):
    """A fixed-size run of fields; ``inner_pads``: (start, end) of its padding, from its start."""

    kind: int
    align: int
    size: int
    inner_pads: Tuple[Tuple[int, int], ...]
    label: str


class StringOp(NamedTuple):
    """A string: uint32 length (with the NUL), the UTF-8 bytes, NUL."""

    kind: int
    bound: Optional[int]
    label: str


class PrimitiveSeqOp(NamedTuple):
    """A sequence of basic values: uint32 count, then the values (aligned when there are some)."""

    kind: int
    align: int
    itemsize: int
    bound: Optional[int]
    label: str


class SeqOp(NamedTuple):
    """A sequence of non-basic values: uint32 count, then each element walked with ``sub_ops``."""

    kind: int
    sub_ops: 'Ops'
    min_size: int
    bound: Optional[int]
    label: str
    path: Tuple


class ArrayOp(NamedTuple):
    """A non-empty array of non-basic values: ``count`` elements walked with ``sub_ops``."""

    kind: int
    sub_ops: 'Ops'
    count: int
    label: str
    path: Tuple


class BlobOp(NamedTuple):
    """An unbounded ``uint8[]`` field: CPU bytes (uint32 length + bytes) or a descriptor."""

    kind: int
    path: Tuple
    label: str


class WStringOp(NamedTuple):
    """A wstring: uint32 length (characters), then 4 bytes per character."""

    kind: int
    bound: Optional[int]
    label: str


Op = Union[FixedOp, StringOp, PrimitiveSeqOp, SeqOp, ArrayOp, BlobOp, WStringOp]
Ops = Tuple[Op, ...]

# The op class of each kind, by kind.
_OP_TYPES = (FixedOp, StringOp, PrimitiveSeqOp, SeqOp, ArrayOp, BlobOp, WStringOp)


class Builder:
    """Accumulates ops, merging runs of fixed-size fields into one op."""

    def __init__(self) -> None:
        self.ops: List[list] = []

    def fixed(self, align: int, size: int, label: str, inner_pads: Tuple = ()) -> None:
        last = self.ops[-1] if self.ops else None
        if last is not None and last[0] == FIXED and last[1] >= align:
            # The run starts aligned to last[1], a multiple of `align`: the layout is static.
            offset = (last[2] + align - 1) & -align
            if offset != last[2]:
                last[3].append((last[2], offset))
            last[3].extend((offset + s, offset + e) for s, e in inner_pads)
            last[2] = offset + size
        else:
            self.ops.append([FIXED, align, size, list(inner_pads), label])

    def add(self, op: list) -> None:
        if op[0] == FIXED:
            self.fixed(op[1], op[2], op[4], op[3])
        else:
            self.ops.append(op)

    def freeze(self) -> Ops:
        return tuple(FixedOp(op[0], op[1], op[2], tuple(op[3]), op[4]) if op[0] == FIXED
                     else _OP_TYPES[op[0]](*op) for op in self.ops)


def min_size(ops: Ops) -> int:
    """A lower bound of the wire size of ``ops`` (padding not counted)."""
    total = 0
    for op in ops:
        kind = op[0]
        if kind == FIXED:
            total += op[2]
        elif kind == STRING:
            total += 5
        elif kind in (PSEQ, SEQ, BLOB, WSTRING):
            total += 4
        else:
            total += op[2] * min_size(op[1])
    return total


def message_fields(msg_type: Type) -> List[Tuple[str, Any]]:
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


def nested_class(ns_type: definition.NamespacedType) -> Type:
    module_name = '.'.join(ns_type.namespaces)
    try:
        return getattr(importlib.import_module(module_name), ns_type.name)
    except (ImportError, AttributeError) as exc:
        raise UnsupportedMessageTypeError(
            f'cannot import the nested message type {module_name}.{ns_type.name}: {exc}') from None


def is_blob(slot_type: Any) -> bool:
    """True for an unbounded ``uint8[]``: the fields that may hold a Buffer."""
    return (isinstance(slot_type, definition.UnboundedSequence)
            and isinstance(slot_type.value_type, definition.BasicType)
            and slot_type.value_type.typename == 'uint8')


def add_type(builder: Builder, slot_type: Any, label: str, stack: Tuple[Type, ...],
             path: Tuple = (), blobs: bool = False) -> None:
    """Append the ops of one value of ``slot_type`` (a rosidl_parser.definition type).

    With ``blobs``, an unbounded ``uint8[]`` is a ``BLOB`` op (it may be a descriptor);
    otherwise a plain sequence.
    """
    if blobs and is_blob(slot_type):
        builder.add([BLOB, path, label])
    elif isinstance(slot_type, definition.BasicType):
        size = BASIC_SIZES.get(slot_type.typename)
        if size is None:
            raise UnsupportedMessageTypeError(
                f'field {label!r} has type {slot_type.typename!r}, which this codec does not '
                f'support (supported basic types: {", ".join(sorted(BASIC_SIZES))})')
        builder.fixed(size, size, label)
    elif isinstance(slot_type, definition.AbstractWString):
        builder.add([WSTRING, getattr(slot_type, 'maximum_size', None), label])
    elif isinstance(slot_type, definition.AbstractString):
        builder.add([STRING, getattr(slot_type, 'maximum_size', None), label])
    elif isinstance(slot_type, definition.NamespacedType):
        nested = nested_class(slot_type)
        if nested in stack:
            raise UnsupportedMessageTypeError(f'{nested.__name__} contains itself ({label!r})')
        fields = message_fields(nested)
        if not fields:
            # rosidl gives an empty structure one member, structure_needs_at_least_one_member
            # (uint8): Python does not show it, the wire carries it.
            builder.fixed(1, 1, f'{label}.structure_needs_at_least_one_member')
        for name, field_type in fields:
            add_type(builder, field_type, f'{label}.{name}', stack + (nested,), path + (name,),
                     blobs)
    elif isinstance(slot_type, (definition.Array, definition.AbstractSequence)):
        value_type = slot_type.value_type
        basic = (isinstance(value_type, definition.BasicType)
                 and value_type.typename in BASIC_SIZES)
        if isinstance(slot_type, definition.Array):
            if basic:
                size = BASIC_SIZES[value_type.typename]
                if slot_type.size:  # Fast CDR aligns an array only when it is not empty
                    builder.fixed(size, size * slot_type.size, label)
                return
            sub = element_ops(value_type, label + '[]', stack, blobs)
            if slot_type.size:
                builder.add([ARRAY, sub, slot_type.size, label, path])
            return
        bound = getattr(slot_type, 'maximum_size', None)
        if basic:
            size = BASIC_SIZES[value_type.typename]
            builder.add([PSEQ, size, size, bound, label])
            return
        sub = element_ops(value_type, label + '[]', stack, blobs)
        least = min_size(sub)
        if least <= 0:
            raise UnsupportedMessageTypeError(
                f'field {label!r}: sequences of zero-size elements are not supported')
        builder.add([SEQ, sub, least, bound, label, path])
    else:
        raise UnsupportedMessageTypeError(
            f'field {label!r} has a type this codec does not support: {slot_type!r}')


def element_ops(value_type: Any, label: str, stack: Tuple[Type, ...],
                blobs: bool = False) -> Ops:
    builder = Builder()
    add_type(builder, value_type, label, stack, (), blobs)
    return builder.freeze()


def truncated(label: str, offset: int, needed: int, end: int) -> CodecError:
    return CodecError(
        f'truncated message: {label} needs {needed} bytes at offset {offset + HEADER_SIZE} but '
        f'the message ends at offset {end + HEADER_SIZE}')


def read_u32(buf: memoryview, pos: int, end: int, unpack, label: str) -> Tuple[int, int]:
    """Return (value, position after) of the 4-aligned uint32 at or after ``pos``."""
    start = (pos + 3) & -4
    if start + 4 > end:
        raise truncated(label, start, 4, end)
    return unpack(buf, start)[0], start + 4


class Out:
    """The bytes a walk writes: small pieces copied into ``cur``, large payloads kept apart.

    Its position (relative to the CDR origin) drives the alignment of what comes next.
    """

    __slots__ = ('parts', 'cur', 'base', 'apart')

    def __init__(self, header) -> None:
        self.parts: List[Any] = []
        self.apart: Optional[int] = None  # the index in parts of the payload kept `apart`
        self.cur = bytearray(header)
        self.base = -HEADER_SIZE  # the origin is after the encapsulation header

    def pad(self, align: int) -> None:
        gap = -(self.base + len(self.cur)) % align
        if gap:
            self.cur += ZEROS[:gap]

    def payload(self, view: memoryview, apart: bool = False) -> None:
        """Append ``view``; a large one (or ``apart``) is not copied but kept as its own part."""
        if apart or view.nbytes >= BIG_PAYLOAD:
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


#: A walk's handler of a ``BLOB`` op: (path, label, position) -> position after the field.
BlobHandler = Callable[[Tuple, str, int], int]


def walk(ops: Ops, buf: memoryview, pos: int, end: int, unpack,
         out: Optional[Out] = None, prefix: Tuple = (),
         blob: Optional[BlobHandler] = None) -> int:
    """Walk ``ops`` over ``buf`` from ``pos``; return the position after them.

    ``buf`` starts at the CDR origin. Every length is checked against ``end`` before it is used.
    When ``out`` is given, the walked bytes are copied to it, realigned to its position, with
    zero padding. A ``BLOB`` op is handed to ``blob`` (which also writes it to ``out``) with its
    path below ``prefix``; without ``blob`` it is walked (and copied) as a plain ``uint8[]``.
    """
    for op in ops:
        kind = op[0]
        if kind == FIXED:
            align = op[1]
            size = op[2]  # (a local: an op is a tuple subclass, slower to index than a tuple)
            start = (pos + align - 1) & -align
            if start + size > end:
                raise truncated(op[4], start, size, end)
            pos = start + size
            if out is not None:
                out.pad(align)
                cur = out.cur
                at = len(cur)
                cur += buf[start:pos]
                for s, e in op[3]:
                    cur[at + s:at + e] = ZEROS[:e - s]
        elif kind == STRING or kind == WSTRING:
            label = op[2]
            length, pos = read_u32(buf, pos, end, unpack, f'the length of string {label}')
            at = pos - 4 + HEADER_SIZE
            if kind == STRING:
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
        elif kind == PSEQ or (kind == BLOB and blob is None):
            if kind == BLOB:
                op = PrimitiveSeqOp(PSEQ, 1, 1, None, op[2])
            label = op[4]
            count, pos = read_u32(buf, pos, end, unpack, f'the count of sequence {label}')
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
                        f'sequence {label} at offset {pos - 4 + HEADER_SIZE} claims {count} '
                        f'elements ({nbytes} bytes) but only {max(end - start, 0)} bytes are left')
                pos = start + nbytes
                if out is not None:
                    out.pad(align)
                    out.payload(buf[start:pos])
        elif kind == SEQ:
            label = op[4]
            count, pos = read_u32(buf, pos, end, unpack, f'the count of sequence {label}')
            if op[3] is not None and count > op[3]:
                raise CodecError(f'sequence {label} has {count} elements, more than its bound '
                                 f'{op[3]}')
            if count * op[2] > end - pos:
                raise CodecError(
                    f'sequence {label} at offset {pos - 4 + HEADER_SIZE} claims {count} elements '
                    f'(at least {count * op[2]} bytes) but only {end - pos} bytes are left')
            if out is not None:
                out.pad(4)
                out.cur += buf[pos - 4:pos]
            sub = op[1]
            base = prefix + op[5]
            for index in range(count):
                pos = walk(sub, buf, pos, end, unpack, out, base + (index,), blob)
        elif kind == ARRAY:
            sub = op[1]
            base = prefix + op[4]
            for index in range(op[2]):
                pos = walk(sub, buf, pos, end, unpack, out, base + (index,), blob)
        else:  # BLOB with a handler
            pos = blob(prefix + op[1], op[2], pos)
    return pos
