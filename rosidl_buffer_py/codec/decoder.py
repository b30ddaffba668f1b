"""Decode: wire bytes to a message, and the descriptors of the fields that came as descriptors.

:func:`decode`, :func:`split_payload` and :func:`deserialize`; the short path's descriptor
form runs in C (``_native.decode_descriptor``), and so does every message a slot program builds
(``_native.deserialize``); everything else walks the type's ops (:mod:`.walker`), which checks
every length before anything is read.
"""
import array
from typing import Any, Container, Dict, NamedTuple, Optional, Tuple, Type

from rclpy.serialization import deserialize_message

from rosidl_buffer_py import _native
from rosidl_buffer_py.backend import MAX_DESCRIPTOR_SIZE
from rosidl_buffer_py.codec.plans import (
    compiled, payload_field, Plan, program_of, short_path_codec, TypeCodec)
from rosidl_buffer_py.codec.walker import Out, read_u32, truncated, walk
from rosidl_buffer_py.codec.wire import (
    CodecError, Decoded, DESCRIPTOR_MARKER, ENCAPSULATION_CDR_BE, ENCAPSULATION_CDR_LE,
    FieldDescriptor, HEADER_SIZE, U32, ZERO_LENGTH)
from rosidl_buffer_py.field_path import FieldPath, get_at


# --- decode --------------------------------------------------------------------------------------

def _deserialize(raw: bytes, msg_type: Type) -> Any:
    try:
        return deserialize_message(raw, msg_type)
    except Exception as exc:
        raise CodecError(f'cannot deserialize {msg_type.__name__}: {type(exc).__name__}: '
                         f'{exc}') from exc


def deserialize(raw: Any, msg_type: Type) -> Any:
    """``deserialize_message(raw, msg_type)``: the same message, built in C from its slots where
    the type has a slot program (:func:`~rosidl_buffer_py.codec.plans.program_of`), without the
    generated code's ``__init__`` and one Python setter per field; rclpy's own deserialization
    for the other types and for anything the program does not build exactly."""
    program = program_of(msg_type)
    if program is not None:
        msg = _native.deserialize(raw, program)
        if msg is not None:
            return msg
    return deserialize_message(raw, msg_type)


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
    if size < HEADER_SIZE:
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
    return view, view[HEADER_SIZE:], size - HEADER_SIZE, U32[little].unpack_from


def _read_descriptor(body: memoryview, pos: int, end: int, unpack, label: str,
                     known_backends: Optional[Container[str]]) -> Tuple[FieldDescriptor, int]:
    """The backend name and descriptor after a marker at ``pos``; (descriptor, position after)."""
    at = pos + HEADER_SIZE
    length, pos = read_u32(body, pos, end, unpack, 'the backend name length')
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
    nbytes, pos = read_u32(body, pos, end, unpack, 'the descriptor length')
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
    type_codec = compiled(msg_type)
    plan = type_codec.plan
    if plan is None:
        return _decode_walk(raw, type_codec, known_backends)[0]
    # Descriptor messages are decoded in C; CPU bytes and anything malformed come back as None
    # and take the path below (which names what is wrong).
    program = type_codec.program
    fast = _native.decode_descriptor(raw, msg_type, plan.prefix_ops, plan.suffix_size,
                                     MAX_DESCRIPTOR_SIZE, program)
    if fast is not None and (known_backends is None or fast[1] in known_backends):
        msg, backend_type, descriptor = fast
        return Decoded(msg, backend_type, descriptor,
                       {plan.path: FieldDescriptor(backend_type, descriptor)})
    if fast is None and program is not None:
        # CPU bytes built in C, the payload copied once (None for a descriptor and for
        # malformed input: the path below names what is wrong)
        msg = _native.deserialize(raw, program)
        if msg is not None:
            return Decoded(msg)
    decoded, payload = _decode_short(raw, plan, known_backends)
    if payload.nbytes:
        getattr(decoded.msg, plan.slot).frombytes(payload)
    return decoded


class DescriptorReading(NamedTuple):
    """How a take reads the descriptor form of a type in C, the message with the payload
    decoded there (``ChannelSubscription.take_described(*args)``): what :func:`decode` does
    first, without its Python frames. Anything it does not read comes as bytes for
    :func:`decode`."""

    field: str   #: the payload (a top-level field), where the descriptor's Buffer goes
    args: tuple  #: (msg_type, prefix ops, suffix size, MAX_DESCRIPTOR_SIZE, program)


def descriptor_reading(msg_type: Type) -> Optional[DescriptorReading]:
    """The :class:`DescriptorReading` of ``msg_type``, or None: a type without the short path
    (its descriptor messages are decoded by :func:`decode`)."""
    type_codec = short_path_codec(msg_type)
    if type_codec is None:
        return None
    plan = type_codec.plan
    return DescriptorReading(type_codec.payload, (msg_type, plan.prefix_ops, plan.suffix_size,
                                                  MAX_DESCRIPTOR_SIZE, type_codec.program))


def split_payload(raw: Any, msg_type: Type) -> Tuple[Any, memoryview]:
    """Split legacy CDR bytes of ``msg_type`` into the message and a view of its payload bytes
    (those of its :func:`payload_field`).

    The message's payload field is left empty; the view points into ``raw`` (no copy), so that
    a caller can put the payload where it wants it (a backend's memory) with one copy.

    :raises CodecError: on malformed input, on descriptor-encoded bytes (no payload here), or
        a type without a top-level ``uint8[]`` (:class:`UnsupportedMessageTypeError`).
    """
    type_codec = compiled(msg_type)
    if type_codec.plan is not None:
        decoded, payload = _decode_short(raw, type_codec.plan, None)
    else:
        path = FieldPath((payload_field(msg_type),))
        decoded, payloads = _decode_walk(raw, type_codec, None, keep=path)
        payload = payloads.get(path, memoryview(b''))
    if decoded.is_descriptor:
        path, described = next(iter(decoded.descriptors.items()))
        raise CodecError(f'{path} holds a descriptor of backend {described.backend_type!r}, '
                         'not payload bytes')
    return decoded.msg, payload


def _decode_walk(raw: Any, type_codec: TypeCodec, known_backends: Optional[Container[str]],
                 keep: Optional[Tuple] = None) -> Tuple[Decoded, Dict[Tuple, memoryview]]:
    """:func:`decode` with the general walker. The CPU bytes of the field at path ``keep`` are
    not put in the message but returned, by path, as a view into ``raw``."""
    view, body, end, unpack = _open(raw)
    out = Out(view[:HEADER_SIZE])
    payloads: Dict[Tuple, memoryview] = {}
    descriptors: Dict[FieldPath, FieldDescriptor] = {}

    def blob(path: Tuple, label: str, pos: int) -> int:
        first, pos = read_u32(body, pos, end, unpack, f'the length of {FieldPath(path)}')
        out.pad(4)
        out.cur += ZERO_LENGTH
        if first == DESCRIPTOR_MARKER:
            path = FieldPath(path)
            descriptors[path], pos = _read_descriptor(body, pos, end, unpack, str(path),
                                                      known_backends)
        else:
            if first > end - pos:
                raise CodecError(f'{FieldPath(path)} claims {first} bytes at offset '
                                 f'{pos - 4 + HEADER_SIZE} but only {end - pos} are left')
            payloads[path] = body[pos:pos + first]
            pos += first
        return pos

    walk(type_codec.ops, body, 0, end, unpack, out, (), blob)
    msg = _deserialize(bytes(out.cur), type_codec.msg_type)
    try:
        for path, data in payloads.items():
            if data.nbytes and path != keep:
                get_at(msg, path).frombytes(data)
    except (LookupError, AttributeError) as exc:  # the message does not match its walk
        raise CodecError(f'{type_codec.msg_type.__name__}: {exc}') from None
    legacy = None
    if type_codec.payload is not None:
        legacy = descriptors.get((type_codec.payload,))
    decoded = Decoded(msg, legacy and legacy.backend_type, legacy and legacy.descriptor,
                      descriptors)
    return decoded, payloads


def _decode_short(raw: Any, plan: Plan,
                  known_backends: Optional[Container[str]]) -> Tuple[Decoded, memoryview]:
    """:func:`decode` of the short path with an empty payload field, and a view of the payload
    bytes in ``raw``."""
    view, body, end, unpack = _open(raw)
    pos = walk(plan.prefix_ops, body, 0, end, unpack)
    first, pos = read_u32(body, pos, end, unpack, f'the length of {plan.field}')
    head_end = HEADER_SIZE + pos - 4

    descriptors = {}
    if first == DESCRIPTOR_MARKER:
        described, pos = _read_descriptor(body, pos, end, unpack, plan.field, known_backends)
        descriptors[plan.path] = described
        data_start = data_end = pos
    else:
        if first > end - pos:
            raise CodecError(f'{plan.field} claims {first} bytes at offset '
                             f'{pos - 4 + HEADER_SIZE} but only {end - pos} are left')
        data_start, data_end = pos, pos + first
    if plan.suffix_size > end - data_end:
        raise truncated(f'the fields after {plan.field}', data_end, plan.suffix_size, end)

    small = b''.join((view[:head_end], ZERO_LENGTH,
                      body[data_end:data_end + plan.suffix_size]))
    msg = _deserialize(small, plan.msg_type)
    setattr(msg, plan.slot, array.array('B'))
    described = descriptors.get(plan.path)
    return (Decoded(msg, described and described.backend_type,
                    described and described.descriptor, descriptors),
            body[data_start:data_end])
