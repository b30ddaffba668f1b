"""What the codec compiles once per message type, and the field API built on it.

:func:`compiled` gives a type's :class:`TypeCodec` (its walker ops, its tree of ``uint8[]``
fields, its short-path :class:`Plan` when it has that shape), compiled on first use and cached;
:func:`payload_field`, :func:`buffer_paths`, :func:`field_paths` and :func:`buffers_of` answer
from it.
"""
import array
import functools
import importlib
import threading
from dataclasses import dataclass
from typing import Any, Dict, Iterator, List, Optional, Tuple, Type

from rosidl_parser import definition

from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.codec.walker import (
    add_type, ARRAY, Builder, FIXED, is_blob, message_fields, nested_class, Ops, PSEQ, SEQ,
    WSTRING)
from rosidl_buffer_py.codec.wire import BufferAt, CodecError, UnsupportedMessageTypeError
from rosidl_buffer_py.field_path import EACH, FieldPath
from rosidl_buffer_py.message_support import enable_buffer_fields

# --- per-type plans ------------------------------------------------------------------------------

# A type's tree of uint8[] fields, to reach them in an instance: one entry per field that is or
# holds one, in field order: (slot, name, kind, sub-tree).
T_BLOB, T_MESSAGE, T_ELEMENTS = range(3)
Tree = Tuple[Tuple[str, str, int, Any], ...]


@dataclass(frozen=True)
class Plan:
    """The short path: one top-level payload followed by fixed-size alignment-1 fields only."""

    msg_type: Type
    field: str                      # the payload field
    slot: str                       # its __slots__ entry ('_data')
    slots: Tuple[str, ...]          # every slot, copied into the clone that encode serializes
    prefix_ops: Ops                 # the fields before the payload
    suffix_size: int                # the fields after it: alignment 1, fixed size
    path: FieldPath                 # (field,)


@dataclass(frozen=True)
class TypeCodec:
    """Everything the codec compiled for one message type."""

    msg_type: Type
    ops: Ops                        # the whole message, uint8[] fields as BLOB ops
    tree: Tree
    templates: Tuple[FieldPath, ...]
    payload: Optional[str]          # the last top-level uint8[] field (payload_field)
    plan: Optional[Plan]            # the short path, when the type has its shape
    plain: bool                     # fixed size: rmw_fastrtps pads it to a multiple of 4
    slack: bool                     # rmw_fastrtps may size it larger than its data (_estimate)
    #: how C builds the message from its CDR and writes its CDR (:func:`slot_program`; its
    #: payload the single top-level uint8[] field), or None
    program: Optional[tuple] = None


def _tree(msg_type: Type, stack: Tuple[Type, ...]) -> Tree:
    slots = set(getattr(msg_type, '__slots__', ()))
    entries = []
    for name, slot_type in message_fields(msg_type):
        if is_blob(slot_type):
            kind, sub = T_BLOB, None
        elif isinstance(slot_type, definition.NamespacedType):
            kind, sub = T_MESSAGE, _nested_tree(slot_type, stack)
        elif (isinstance(slot_type, (definition.Array, definition.AbstractSequence))
              and isinstance(slot_type.value_type, definition.NamespacedType)):
            kind, sub = T_ELEMENTS, _nested_tree(slot_type.value_type, stack)
        else:
            continue
        if kind != T_BLOB and not sub:
            continue
        if '_' + name not in slots:
            raise UnsupportedMessageTypeError(
                f'{msg_type.__name__} has no slot {"_" + name!r} for its field {name!r}')
        entries.append(('_' + name, name, kind, sub))
    return tuple(entries)


def _nested_tree(slot_type: definition.NamespacedType, stack: Tuple[Type, ...]) -> Tree:
    nested = nested_class(slot_type)
    if nested in stack:
        raise UnsupportedMessageTypeError(f'{nested.__name__} contains itself')
    return _tree(nested, stack + (nested,))


def _templates(tree: Tree, prefix: Tuple = ()) -> List[FieldPath]:
    out = []
    for _, name, kind, sub in tree:
        if kind == T_BLOB:
            out.append(FieldPath(prefix + (name,)))
        else:
            out.extend(_templates(sub, prefix + ((name,) if kind == T_MESSAGE else
                                                 (name, EACH))))
    return out


def _compile(msg_type: Type) -> TypeCodec:
    fields = message_fields(msg_type)
    builder = Builder()
    if not fields:  # the wire carries structure_needs_at_least_one_member (see add_type)
        builder.fixed(1, 1, 'structure_needs_at_least_one_member')
    for name, slot_type in fields:
        add_type(builder, slot_type, name, (msg_type,), (name,), blobs=True)
    ops = builder.freeze()
    tree = _tree(msg_type, (msg_type,))
    templates = tuple(_templates(tree))
    top = [index for index, (_, slot_type) in enumerate(fields) if is_blob(slot_type)]
    payload = fields[top[-1]][0] if top else None
    plan = None
    if len(templates) == 1 and payload is not None:
        plan = _short_plan_of(msg_type, fields, top[-1])
    slack = _has_slack(ops)
    program = slot_program(msg_type, '_' + payload if len(templates) == 1 and top else None)
    return TypeCodec(msg_type, ops, tree, templates, payload, None if slack else plan,
                     _fixed_size(ops), slack, program)


def _has_slack(ops: Ops) -> bool:
    return any(op[0] == WSTRING or (op[0] == PSEQ and op[1] > 1) or
               (op[0] in (SEQ, ARRAY) and _has_slack(op[1])) for op in ops)


def _fixed_size(ops: Ops) -> bool:
    return all(op[0] == FIXED or (op[0] == ARRAY and _fixed_size(op[1])) for op in ops)


def _short_plan_of(msg_type: Type, fields, index: int) -> Optional[Plan]:
    """The short path's plan, or None when a field after the payload needs alignment or has a
    variable size (its padding would then depend on the payload length)."""
    suffix = Builder()
    for name, slot_type in fields[index + 1:]:
        add_type(suffix, slot_type, name, (msg_type,))
    suffix_ops = suffix.freeze()
    if any(op[0] != FIXED or op[1] != 1 for op in suffix_ops):
        return None
    prefix = Builder()
    for name, slot_type in fields[:index]:
        add_type(prefix, slot_type, name, (msg_type,))
    field = fields[index][0]
    return Plan(msg_type, field, '_' + field, tuple(msg_type.__slots__), prefix.freeze(),
                sum(op[2] for op in suffix_ops), FieldPath((field,)))


# --- slot programs ---------------------------------------------------------------------------

# How src/native/codec_fast.cpp builds a decoded message without the generated code's
# convert_to_py: that runs the class's __init__ (which builds every nested default) and then one
# Python property setter per field, about 100 µs for an Image in a process woken for one frame;
# setting the slots from C gives the same object for a fraction. A program is
# ``(class, check_fields, ((slot, kind, arg), ...))``; the kinds, in the order codec_fast.cpp
# reads them (test_codec.py pins them):
(P_BOOL, P_INT8, P_UINT8, P_INT16, P_UINT16, P_INT32, P_UINT32, P_INT64, P_UINT64, P_FLOAT32,
 P_FLOAT64, P_STRING, P_MESSAGE, P_PAYLOAD) = range(14)
_BASIC_KINDS = {
    'boolean': P_BOOL, 'int8': P_INT8, 'uint8': P_UINT8, 'int16': P_INT16, 'uint16': P_UINT16,
    'int32': P_INT32, 'uint32': P_UINT32, 'int64': P_INT64, 'uint64': P_UINT64,
    'float': P_FLOAT32, 'double': P_FLOAT64}


def slot_program(msg_type: Type, payload_slot: Optional[str] = None,
                 stack: Tuple[Type, ...] = ()) -> Optional[tuple]:
    """The program by which C builds a ``msg_type`` from its CDR as ``deserialize_message``
    would (the same field values, of the same types; ``payload_slot``, a top-level ``uint8[]``,
    an ``array.array('B')``), and writes its CDR from the slots, or None when a field
    has a kind it does not build (sequences and arrays other than the payload, wide strings,
    ``byte``, ``char``) or the class is not laid out as rosidl generates it: the message then
    comes from the generated code."""
    if msg_type in stack:
        return None
    fields = message_fields(msg_type)
    slots = ['_' + name for name, _ in fields]
    module = importlib.import_module(msg_type.__module__)
    check = getattr(module, 'ros_python_check_fields', None)
    if list(getattr(msg_type, '__slots__', ())) != slots + ['_check_fields'] or \
            not isinstance(check, str) or not fields:
        return None
    entries = []
    for slot, (_, slot_type) in zip(slots, fields):
        if slot == payload_slot:
            entries.append((slot, P_PAYLOAD, functools.partial(array.array, 'B')))
        elif isinstance(slot_type, definition.BasicType) and slot_type.typename in _BASIC_KINDS:
            entries.append((slot, _BASIC_KINDS[slot_type.typename], None))
        elif isinstance(slot_type, definition.UnboundedString):
            entries.append((slot, P_STRING, -1))
        elif isinstance(slot_type, definition.BoundedString):
            entries.append((slot, P_STRING, int(slot_type.maximum_size)))
        elif isinstance(slot_type, definition.NamespacedType):
            nested = slot_program(nested_class(slot_type), None, stack + (msg_type,))
            if nested is None:
                return None
            entries.append((slot, P_MESSAGE, nested))
        else:
            return None
    # what the generated __init__ sets (its module's ROS_PYTHON_CHECK_FIELDS, read at import)
    return (msg_type, check == '1', tuple(entries))


_codecs: Dict[Type, TypeCodec] = {}
_codecs_lock = threading.Lock()


def compiled(msg_type: Type) -> TypeCodec:
    """The :class:`TypeCodec` of ``msg_type``, compiled on first use (which also enables its
    ``uint8[]`` fields to hold a Buffer) and cached.

    :raises UnsupportedMessageTypeError: when the codec cannot handle ``msg_type``.
    """
    try:
        found = _codecs.get(msg_type)
    except TypeError:  # unhashable: not a class
        found = None
    if found is None:
        if not isinstance(msg_type, type):
            raise UnsupportedMessageTypeError(
                f'expected a message class, got {type(msg_type).__name__} {msg_type!r:.200}')
        with _codecs_lock:
            found = _codecs.get(msg_type)
            if found is None:
                found = _compile(msg_type)
                enable_buffer_fields(msg_type)
                _codecs[msg_type] = found
    return found


def program_of(msg_type: Type) -> Optional[tuple]:
    """The slot program of ``msg_type`` (:func:`slot_program`: how C builds it from its CDR and
    writes its CDR from its slots), or None: for a type without one, or that the codec does not
    handle."""
    try:
        return compiled(msg_type).program
    except CodecError:
        return None


def short_path_codec(msg_type: Type) -> Optional[TypeCodec]:
    """The compiled codec of ``msg_type`` when it has the short path (its descriptor form is its
    one payload described, what C encodes and decodes), else None."""
    try:
        type_codec = compiled(msg_type)
    except CodecError:
        return None
    return type_codec if type_codec.plan is not None else None


def descriptor_program(msg_type: Type) -> Optional[tuple]:
    """The slot program that writes the descriptor form of ``msg_type`` (its one payload
    described) as :func:`~rosidl_buffer_py.codec.encode` writes it, or None: a type without the
    short path or without a program (encode then walks it)."""
    type_codec = short_path_codec(msg_type)
    return None if type_codec is None else type_codec.program


def short_plan(msg_type: Type) -> Plan:
    """The short path's plan of ``msg_type`` (for types that have it)."""
    plan = compiled(msg_type).plan
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
    type_codec = compiled(msg_type)
    if type_codec.payload is None:
        kinds = msg_type.get_fields_and_field_types()
        deeper = (f'; its uint8[] fields are deeper: {", ".join(map(str, type_codec.templates))} '
                  '(see codec.buffer_paths)' if type_codec.templates else '')
        raise UnsupportedMessageTypeError(
            f'{msg_type.__name__} has no top-level uint8[] field (fields: '
            f'{", ".join(f"{n}: {k}" for n, k in kinds.items()) or "none"}){deeper}')
    return type_codec.payload


def buffer_paths(msg_type: Type) -> Tuple[FieldPath, ...]:
    """The ``uint8[]`` fields of ``msg_type`` at any depth, in wire order, as template paths:
    :data:`EACH` stands for the elements of a sequence or array of messages
    (``('images', EACH, 'data')``). Empty for a type without any, or for anything the codec
    cannot handle; never raises."""
    try:
        return compiled(msg_type).templates
    except Exception:  # noqa: BLE001 - documented: never raises
        return ()


def _instance_blobs(msg: Any, tree: Tree, prefix: Tuple) -> Iterator[Tuple[Tuple, Any]]:
    for slot, name, kind, sub in tree:
        value = getattr(msg, slot)
        if kind == T_BLOB:
            yield prefix + (name,), value
        elif kind == T_MESSAGE:
            yield from _instance_blobs(value, sub, prefix + (name,))
        else:
            for index, element in enumerate(value):
                yield from _instance_blobs(element, sub, prefix + (name, index))


def blobs_of(msg: Any) -> Iterator[Tuple[Tuple, Any]]:
    """(path, value) of every ``uint8[]`` field of the message ``msg``, in wire order.

    :raises UnsupportedMessageTypeError: when the codec cannot handle ``type(msg)``.
    :raises CodecError: when ``msg`` is malformed.
    """
    try:
        yield from _instance_blobs(msg, compiled(type(msg)).tree, ())
    except (AttributeError, TypeError) as exc:
        if isinstance(exc, UnsupportedMessageTypeError):
            raise
        raise CodecError(f'{type(msg).__name__} instance is malformed: {exc}') from None


def field_paths(msg: Any) -> Tuple[FieldPath, ...]:
    """The paths of every ``uint8[]`` field of the message ``msg`` (element indices resolved),
    in wire order.

    :raises UnsupportedMessageTypeError: when the codec cannot handle ``type(msg)``.
    """
    return tuple(FieldPath(path) for path, _ in blobs_of(msg))


def buffers_of(msg: Any) -> List[BufferAt]:
    """The ``uint8[]`` fields of ``msg`` that hold a :class:`~rosidl_buffer_py.Buffer`, in wire
    order.

    :raises UnsupportedMessageTypeError: when the codec cannot handle ``type(msg)``.
    """
    return [BufferAt(FieldPath(path), value) for path, value in blobs_of(msg)
            if isinstance(value, Buffer)]
