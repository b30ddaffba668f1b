"""Encode: a message to wire bytes, each ``uint8[]`` field as CPU bytes or as a descriptor.

:func:`encode` and :func:`encode_parts`; the short path's descriptor form runs in C
(``_native.encode_descriptor``), everything else walks the type's ops (:mod:`.walker`).
"""
import struct
from typing import Any, Dict, Iterator, List, Mapping, Optional, Tuple, Union

from rclpy.serialization import serialize_message

from rosidl_buffer_py import _native
from rosidl_buffer_py.backend import MAX_DESCRIPTOR_SIZE
from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.codec.plans import (
    compiled, payload_field, Plan, T_BLOB, T_MESSAGE, Tree, TypeCodec)
from rosidl_buffer_py.codec.walker import (
    ARRAY, FIXED, Ops, Out, PSEQ, read_u32, SEQ, STRING, walk, WSTRING)
from rosidl_buffer_py.codec.wire import (
    CodecError, EMPTY_PAYLOAD, ENCAPSULATION_CDR_LE, EncodedParts, HEADER_SIZE, MARKER_BYTES,
    U32)
from rosidl_buffer_py.field_path import FieldPath


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


def _strip(msg: Any, tree: Tree, prefix: Tuple, values: Dict[Tuple, Any]) -> Any:
    """A shallow copy of ``msg`` whose ``uint8[]`` fields are empty (copied down to them); their
    values go to ``values`` by path."""
    cls = type(msg)
    clone = cls.__new__(cls)
    for slot in cls.__slots__:
        setattr(clone, slot, getattr(msg, slot))
    for slot, name, kind, sub in tree:
        value = getattr(msg, slot)
        if kind == T_BLOB:
            values[prefix + (name,)] = value
            setattr(clone, slot, EMPTY_PAYLOAD)
        elif kind == T_MESSAGE:
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


def _write_descriptor(out: Out, u32: struct.Struct, name: bytes, data: bytes) -> None:
    """The descriptor form at ``out``'s position (4-aligned): marker, backend, descriptor."""
    cur = out.cur
    cur += MARKER_BYTES
    cur += u32.pack(len(name) + 1)
    cur += name
    cur += b'\x00'
    out.pad(4)
    cur += u32.pack(len(data))
    cur += data


def _encode_walk(msg: Any, type_codec: TypeCodec, descriptors: Dict[FieldPath, Tuple],
                 apart: Optional[Tuple] = None) -> Out:
    """Encode ``msg`` with the general walker: the fields in ``descriptors`` as descriptors, the
    others as CPU bytes; the payload at path ``apart`` is kept as its own part of the output."""
    values: Dict[Tuple, Any] = {}
    try:
        clone = _strip(msg, type_codec.tree, (), values)
    except (AttributeError, TypeError) as exc:
        raise CodecError(f'{type(msg).__name__} instance is malformed: {type(exc).__name__}: '
                         f'{exc}') from None
    for path in descriptors:
        if path not in values:
            raise CodecError(
                f'descriptors: {type(msg).__name__} has no uint8[] field {path} (this '
                f'message\'s: {", ".join(str(FieldPath(p)) for p in values) or "none"})')
    small = _serialize(clone)
    u32 = U32[small[1] == ENCAPSULATION_CDR_LE]
    unpack = u32.unpack_from
    body = memoryview(small)[HEADER_SIZE:]
    end = len(body)
    out = Out(small[:HEADER_SIZE])
    lengths: List[int] = []  # of the CPU payloads, in wire order (for _estimate)

    def blob(path: Tuple, label: str, pos: int) -> int:
        _, pos = read_u32(body, pos, end, unpack, label)  # the clone's empty field
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

    walk(type_codec.ops, body, 0, end, unpack, out, (), blob)
    if type_codec.plain:
        out.pad(4)  # as rmw_fastrtps sizes a fixed-size message: a multiple of 4
    elif type_codec.slack:
        _, estimate = _estimate(type_codec.ops, body, 0, end, unpack, 0, iter(lengths))
        written = out.base + len(out.cur)
        if estimate > written:
            out.cur += bytes(estimate - written)
    return out


def _estimate(ops: Ops, buf: memoryview, pos: int, end: int, unpack, est: int,
              lengths: Iterator[int]) -> Tuple[int, int]:
    """(position after ``ops``, rmw_fastrtps' size estimate at that point) over well-formed
    ``buf`` (a clone's serialization) whose ``BLOB`` fields really are ``lengths`` long.

    ``serialize_message`` returns as many bytes as the type support's ``get_serialized_size``
    estimates, which counts the element alignment of empty sequences and a NUL per wstring that
    the data does not have: the bytes past the data are slack (uninitialized), matched here with
    zeros.
    """
    for op in ops:
        kind = op[0]
        if kind == FIXED:
            align = op[1]
            pos = ((pos + align - 1) & -align) + op[2]
            est = ((est + align - 1) & -align) + op[2]
        elif kind == ARRAY:
            for _ in range(op[2]):
                pos, est = _estimate(op[1], buf, pos, end, unpack, est, lengths)
        else:
            count, pos = read_u32(buf, pos, end, unpack, 'a length')  # checked before
            est = ((est + 3) & -4) + 4
            if kind == STRING:
                pos += count
                est += count
            elif kind == WSTRING:
                pos += 4 * count
                est += 4 * (count + 1)
            elif kind == PSEQ:
                align = op[1]
                if count:
                    pos = ((pos + align - 1) & -align) + count * op[2]
                est = ((est + align - 1) & -align) + count * op[2]
            elif kind == SEQ:
                for _ in range(count):
                    pos, est = _estimate(op[1], buf, pos, end, unpack, est, lengths)
            else:  # BLOB: empty in buf
                est += next(lengths)
    return pos, est


def _encode_head(msg: Any, plan: Plan) -> Tuple[bytearray, bytes, Any]:
    """Serialize ``msg`` without its payload: (header + prefix with zero padding, suffix, u32)."""
    msg_type = plan.msg_type
    clone = msg_type.__new__(msg_type)
    try:
        for slot in plan.slots:
            setattr(clone, slot, getattr(msg, slot))
    except AttributeError as exc:
        raise CodecError(f'{msg_type.__name__} instance is incomplete: {exc}') from None
    setattr(clone, plan.slot, EMPTY_PAYLOAD)
    small = _serialize(clone)
    u32 = U32[small[1] == ENCAPSULATION_CDR_LE]
    body = memoryview(small)[HEADER_SIZE:]
    out = Out(small[:HEADER_SIZE])
    pos = walk(plan.prefix_ops, body, 0, len(body), u32.unpack_from, out)
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
    type_codec = compiled(type(msg))
    plan = type_codec.plan
    if plan is not None:
        view = _payload_view(getattr(msg, plan.slot, None), plan.field)
        head, suffix, u32 = _encode_head(msg, plan)
        head += u32.pack(view.nbytes)
        return EncodedParts(head, view, suffix)
    path = (payload_field(type_codec.msg_type),)
    out = _encode_walk(msg, type_codec, {}, apart=path)
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
    type_codec = compiled(type(msg))
    plan = type_codec.plan
    if descriptors is None:
        if plan is not None:
            head, view, suffix = encode_parts(msg)
            head += view
            head += suffix
            return head
        return _encode_walk(msg, type_codec, {}).joined()
    if type(descriptors) is tuple or not isinstance(descriptors, Mapping):  # one pair
        backend, data = _check_descriptor(descriptors)
        if plan is None:
            return _encode_walk(msg, type_codec,
                                {FieldPath((payload_field(type(msg)),)): (backend, data)}).joined()
    else:
        checked = _check_descriptors(descriptors)
        if plan is None or (checked and set(checked) != {plan.path}):
            return _encode_walk(msg, type_codec, checked).joined()
        if not checked:
            return encode(msg)
        backend, data = checked[plan.path]
    # the same bytes from C (None when it cannot: the code below then says why)
    out = _native.encode_descriptor(msg, plan.slots, plan.slot, EMPTY_PAYLOAD, backend,
                                    data, plan.suffix_size, type_codec.program)
    if out is not None:
        return out
    head, suffix, u32 = _encode_head(msg, plan)
    out = Out(head)
    _write_descriptor(out, u32, backend, data)
    out.cur += suffix
    return out.cur
