"""Tests of the codec's general path: every uint8[] field of every message type, at any depth.

The oracles: rclpy's own serializer (``serialize_message`` / ``deserialize_message``) and a
textbook CDR writer in this file, recursive over ``SLOT_TYPES`` (no compiled ops, no merging),
that writes zero padding and records where the padding is. ``serialize_message`` leaves its
padding uninitialized and returns as many bytes as the type support's size *estimate*: the
comparisons mask its padding, and check that the bytes past the data are what the codec writes
there (zeros), so the lengths agree.

The sweep imports every rosidl message package installed next to rclpy: every message type, and
the message types of every service and action.
"""
import array
import glob
import importlib
import os
import struct
import sys

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from rosidl_parser import definition
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from stereo_msgs.msg import DisparityImage
from test_msgs.msg import MultiNested, UnboundedSequences, WStrings

from rosidl_buffer_py import Buffer, MAX_DESCRIPTOR_SIZE
from rosidl_buffer_py import codec
from rosidl_buffer_py.codec import plans, walker
from rosidl_buffer_py.codec import (
    CodecError, DESCRIPTOR_MARKER, EACH, FieldDescriptor, FieldPath,
    UnsupportedMessageTypeError, buffer_paths, buffers_of, decode, encode, field_paths,
    get_at, set_at)


# --- every installed message type --------------------------------------------------------------

def installed_message_types():
    found = {}
    for directory in sys.path:
        for init in sorted(glob.glob(os.path.join(directory, '*', 'msg', '__init__.py'))):
            package = init.split(os.sep)[-3]
            try:
                module = importlib.import_module(f'{package}.msg')
            except ImportError:
                continue
            for name in dir(module):
                value = getattr(module, name)
                if isinstance(value, type) and hasattr(value, 'SLOT_TYPES'):
                    found[f'{package}/msg/{name}'] = value
    return found


def installed_interface_types():
    """The message classes of installed services and actions (``Request``, ``Response``,
    ``Event``, ``Goal``, ``Feedback``, ``SendGoal_Request``...)."""
    found = {}
    for directory in sys.path:
        for kind in ('srv', 'action'):
            for init in sorted(glob.glob(os.path.join(directory, '*', kind, '__init__.py'))):
                package = init.split(os.sep)[-3]
                try:
                    module = importlib.import_module(f'{package}.{kind}')
                except ImportError:
                    continue
                for name in dir(module):
                    outer = getattr(module, name)
                    if not isinstance(outer, type) or hasattr(outer, 'SLOT_TYPES'):
                        continue
                    for attr in dir(outer):
                        inner = getattr(outer, attr)
                        if (attr[:1].isupper() and isinstance(inner, type)
                                and hasattr(inner, 'SLOT_TYPES')):
                            found[f'{package}/{kind}/{inner.__name__}'] = inner
    return found


ALL_TYPES = installed_message_types()
TYPE_NAMES = sorted(ALL_TYPES)
INTERFACE_TYPES = installed_interface_types()
ALL_TYPES.update(INTERFACE_TYPES)
SWEEP = TYPE_NAMES + sorted(INTERFACE_TYPES)


def test_the_sweep_sees_the_installed_packages():
    packages = {name.split('/')[0] for name in TYPE_NAMES}
    assert {'sensor_msgs', 'std_msgs', 'stereo_msgs', 'test_msgs', 'geometry_msgs'} <= packages
    assert len(TYPE_NAMES) >= 150
    assert len(INTERFACE_TYPES) >= 50  # rcl_interfaces, test_msgs, action_msgs...


# --- a textbook reference writer ---------------------------------------------------------------

_FORMATS = {
    'boolean': '?', 'octet': 'B', 'char': 'B', 'int8': 'b', 'uint8': 'B', 'int16': 'h',
    'uint16': 'H', 'int32': 'i', 'uint32': 'I', 'int64': 'q', 'uint64': 'Q', 'float': 'f',
    'double': 'd', 'short': 'h', 'unsigned short': 'H', 'long': 'i', 'unsigned long': 'I',
    'long long': 'q', 'unsigned long long': 'Q',
}


def nested_class(ns_type):
    return getattr(importlib.import_module('.'.join(ns_type.namespaces)), ns_type.name)


class Ref:
    """CDR of a message written field by field; ``descriptors`` maps paths to descriptors."""

    def __init__(self, little=True, descriptors=None):
        self.e = '<' if little else '>'
        self.out = bytearray(b'\x00\x01\x00\x00' if little else b'\x00\x00\x00\x00')
        self.pads = []
        self.descriptors = descriptors or {}

    def align(self, n):
        gap = -(len(self.out) - 4) % n
        if gap:
            self.pads.append((len(self.out), len(self.out) + gap))
            self.out += bytes(gap)

    def prim(self, fmt, value):
        self.align(struct.calcsize(fmt))
        self.out += struct.pack(self.e + fmt, value)

    def string(self, text):
        data = text.encode('utf-8') + b'\x00'
        self.prim('I', len(data))
        self.out += data

    def message(self, msg, path=()):
        fields = list(zip(msg.get_fields_and_field_types(), msg.SLOT_TYPES))
        if not fields:
            self.prim('B', 0)  # structure_needs_at_least_one_member
        for name, slot_type in fields:
            self.value(slot_type, getattr(msg, name), path + (name,))

    def basic(self, typename, value):
        if typename in ('octet',) and isinstance(value, bytes):
            value = value[0]
        self.prim(_FORMATS[typename], value)

    def value(self, slot_type, value, path):
        if isinstance(slot_type, definition.BasicType):
            self.basic(slot_type.typename, value)
        elif isinstance(slot_type, definition.AbstractWString):
            units = value.encode('utf-16-le')
            self.prim('I', len(units) // 2)
            for i in range(0, len(units), 2):
                self.prim('I', int.from_bytes(units[i:i + 2], 'little'))
        elif isinstance(slot_type, definition.AbstractString):
            self.string(value)
        elif isinstance(slot_type, definition.NamespacedType):
            self.message(value, path)
        elif isinstance(slot_type, definition.Array):
            for index, item in enumerate(value):
                self.value(slot_type.value_type, item, path + (index,))
        else:  # a sequence
            if path in self.descriptors:
                backend, desc = self.descriptors[path]
                self.prim('I', DESCRIPTOR_MARKER)
                self.string(backend)
                self.prim('I', len(desc))
                self.out += desc
                return
            self.prim('I', len(value))
            for index, item in enumerate(value):
                self.value(slot_type.value_type, item, path + (index,))


def reference(msg, descriptors=None, little=True):
    ref = Ref(little, descriptors)
    ref.message(msg)
    return ref


def masked(raw, pads):
    out = bytearray(raw)
    for start, end in pads:
        out[start:end] = bytes(end - start)
    return bytes(out)


def check_cpu(msg):
    """encode(msg): the reference bytes, then zeros up to serialize_message's length; the stock
    bytes equal the reference with their padding masked."""
    ref = reference(msg)
    enc = encode(msg)
    stock = serialize_message(msg)
    n = len(ref.out)
    assert isinstance(enc, bytearray)
    assert bytes(enc[:n]) == bytes(ref.out)
    assert len(enc) == len(stock)
    assert bytes(enc[n:]) == bytes(len(enc) - n)
    assert masked(stock[:n], ref.pads) == bytes(ref.out)
    return enc


# --- random contents ---------------------------------------------------------------------------

_INTS = {'int8': 8, 'int16': 16, 'int32': 32, 'int64': 64, 'short': 16, 'long': 32,
         'long long': 64}
_UINTS = {'uint8': 8, 'uint16': 16, 'uint32': 32, 'uint64': 64, 'char': 8,
          'unsigned short': 16, 'unsigned long': 32, 'unsigned long long': 64}
_TEXT = st.characters(blacklist_categories=('Cs',), blacklist_characters='\x00')


def basic_values(typename):
    if typename == 'boolean':
        return st.booleans()
    if typename == 'octet':
        return st.binary(min_size=1, max_size=1)
    if typename in _INTS:
        bits = _INTS[typename]
        return st.integers(-2 ** (bits - 1), 2 ** (bits - 1) - 1)
    if typename in _UINTS:
        return st.integers(0, 2 ** _UINTS[typename] - 1)
    width = 32 if typename == 'float' else 64
    return st.floats(width=width, allow_nan=False)


def values_of(slot_type, depth=0):
    if isinstance(slot_type, definition.BasicType):
        return basic_values(slot_type.typename)
    if isinstance(slot_type, (definition.AbstractString, definition.AbstractWString)):
        return st.text(_TEXT.filter(lambda c: ord(c) < 0x10000)
                       if isinstance(slot_type, definition.AbstractWString) else _TEXT,
                       max_size=getattr(slot_type, 'maximum_size', None) or 12)
    if isinstance(slot_type, definition.NamespacedType):
        return messages_of(nested_class(slot_type), depth + 1)
    if walker.is_blob(slot_type):
        return st.binary(max_size=40)
    item = values_of(slot_type.value_type, depth)
    if isinstance(slot_type, definition.Array):
        return st.lists(item, min_size=slot_type.size, max_size=slot_type.size)
    bound = getattr(slot_type, 'maximum_size', None)
    return st.lists(item, max_size=min(bound or 3, 3 if depth < 2 else 1))


def messages_of(msg_type, depth=0):
    fields = list(zip(msg_type.get_fields_and_field_types(), msg_type.SLOT_TYPES))

    def build(values):
        msg = msg_type()
        for (name, _), value in zip(fields, values):
            setattr(msg, name, value)
        return msg
    return st.tuples(*(values_of(t, depth) for _, t in fields)).map(build)


_SETTINGS = settings(max_examples=6, deadline=None, database=None,
                     suppress_health_check=list(HealthCheck))


# --- the sweep ---------------------------------------------------------------------------------

@pytest.mark.parametrize('name', SWEEP)
def test_every_installed_type_default_message(name):
    msg_type = ALL_TYPES[name]
    msg = msg_type()
    enc = check_cpu(msg)
    decoded = decode(enc, msg_type)
    assert decoded.msg == msg == deserialize_message(bytes(enc), msg_type)
    assert decoded.descriptors == {} and not decoded.is_descriptor
    templates = buffer_paths(msg_type)
    assert all(isinstance(p, FieldPath) for p in templates)
    for path in field_paths(msg):
        assert any(matches(path, template) for template in templates), (path, templates)


def matches(path, template):
    return len(path) == len(template) and all(
        t is EACH and isinstance(p, int) or p == t for p, t in zip(path, template))


@pytest.mark.parametrize('name', SWEEP)
def test_every_installed_type_random_contents(name):
    msg_type = ALL_TYPES[name]

    @_SETTINGS
    @given(messages_of(msg_type), st.randoms(use_true_random=False))
    def run(msg, rnd):
        enc = check_cpu(msg)
        assert decode(enc, msg_type).msg == msg
        paths = field_paths(msg)
        templates = buffer_paths(msg_type)
        assert all(any(matches(p, t) for t in templates) for p in paths)
        assert len(set(paths)) == len(paths)
        # every uint8[] field present: describe a random subset of them
        chosen = [p for p in paths if rnd.random() < 0.5]
        descriptors = {p: (f'b{i}', bytes([i]) * rnd.randrange(0, 9))
                       for i, p in enumerate(chosen)}
        described = encode(msg, descriptors)
        ref = reference(msg, {tuple(p): d for p, d in descriptors.items()})
        assert bytes(described[:len(ref.out)]) == bytes(ref.out)
        assert not any(described[len(ref.out):])
        decoded = decode(described, msg_type)
        assert decoded.descriptors == {p: FieldDescriptor(*d) for p, d in descriptors.items()}
        expected = deserialize_message(serialize_message(msg), msg_type)
        for path in chosen:
            set_at(expected, path, array.array('B'))
        assert decoded.msg == expected
        for path in paths:
            if path not in descriptors:
                assert get_at(decoded.msg, path) == get_at(msg, path)
    run()


def test_the_sweep_covers_the_shapes_of_issue_20():
    paths = {name: buffer_paths(ALL_TYPES[name]) for name in TYPE_NAMES}
    with_payloads = [n for n, p in paths.items() if p]
    assert paths['stereo_msgs/msg/DisparityImage'] == (('image', 'data'),)
    assert ('array_of_unbounded_sequences', EACH, 'uint8_values') in \
        paths['test_msgs/msg/MultiNested']
    assert len(with_payloads) >= 10, with_payloads


# --- shapes: nested, several, inside sequences, fields after -----------------------------------

def disparity(data=b'', frame='stereo'):
    msg = DisparityImage(f=525.0, t=0.0625, min_disparity=1.5, max_disparity=64.0,
                         delta_d=0.125)
    msg.header.frame_id = frame
    msg.image.height, msg.image.width, msg.image.step = 2, len(data) // 8, len(data) // 2
    msg.image.encoding = '32FC1'
    msg.image.data = data
    msg.valid_window.x_offset, msg.valid_window.height = 3, 7
    return msg


def multi_nested(n=2):
    msg = MultiNested()
    for i, element in enumerate(msg.array_of_unbounded_sequences):
        element.uint8_values = bytes(range(i, i + 5 + i))
        element.string_values = ['after', 'the', 'payload']
        element.alignment_check = 7 + i
    msg.unbounded_sequence_of_unbounded_sequences = [
        UnboundedSequences(uint8_values=bytes([k]) * (k + 1), float64_values=[1.5] * k,
                           char_values=b'xy'[:k]) for k in range(n)]
    return msg


def test_disparity_image_payload_is_nested_and_followed_by_aligned_fields():
    msg = disparity(bytes(range(48)))
    assert buffer_paths(DisparityImage) == (('image', 'data'),)
    enc = check_cpu(msg)
    described = encode(msg, {('image', 'data'): ('demo', b'handle')})
    assert bytes(described) == bytes(reference(msg, {('image', 'data'): ('demo', b'handle')}).out)
    decoded = decode(described, DisparityImage, known_backends={'demo'})
    assert decoded.descriptors == {('image', 'data'): ('demo', b'handle')}
    assert decoded.backend_type is None  # no top-level payload field: see descriptors
    expected = disparity(bytes(range(48)))
    expected.image.data = b''
    assert decoded.msg == expected and decoded.msg.max_disparity == 64.0
    assert decode(enc, DisparityImage).msg == msg
    for text_key in ('image.data', FieldPath('image.data')):
        assert encode(msg, {text_key: ('demo', b'handle')}) == described


def test_a_buffer_in_a_nested_field():
    msg = disparity(bytes(16))
    buffer = Buffer('demo', bytearray(b'\x01\x02\x03\x04' * 4))
    msg.image.data = buffer  # enable_buffer_fields covers nested types
    assert msg.image.data is buffer
    assert buffers_of(msg) == [(('image', 'data'), buffer)]
    assert buffers_of(msg)[0].path == FieldPath('image.data')
    assert encode(msg) == encode(disparity(b'\x01\x02\x03\x04' * 4))


def test_several_payloads_in_sequences_and_arrays_of_messages():
    msg = multi_nested(3)
    paths = field_paths(msg)
    assert ('array_of_unbounded_sequences', 2, 'char_values_default') in paths
    assert ('unbounded_sequence_of_unbounded_sequences', 2, 'uint8_values') in paths
    assert len(paths) == (3 + 3) * 4  # four uint8[] fields per UnboundedSequences
    check_cpu(msg)
    descriptors = {('array_of_unbounded_sequences', 1, 'uint8_values'): ('gpu', b'a' * 3),
                   ('unbounded_sequence_of_unbounded_sequences', 2, 'uint8_values'):
                       ('demo', b''),
                   ('unbounded_sequence_of_unbounded_sequences', 0, 'char_values'):
                       ('demo', b'z' * 17)}
    enc = encode(msg, descriptors)
    assert bytes(enc)[:len(reference(msg, descriptors).out)] == bytes(
        reference(msg, descriptors).out)
    decoded = decode(enc, MultiNested, known_backends={'gpu', 'demo'})
    assert decoded.descriptors == descriptors
    for path, (backend, desc) in descriptors.items():
        assert len(get_at(decoded.msg, path)) == 0
        set_at(decoded.msg, path, Buffer(backend, bytearray(get_at(msg, path))))
    assert encode(decoded.msg) == encode(msg)  # Buffers back in place: the CPU form again


def test_buffers_of_and_set_at_inside_sequences():
    msg = multi_nested(2)
    buffer = Buffer('demo', bytearray(b'pixels'))
    set_at(msg, ('unbounded_sequence_of_unbounded_sequences', 1, 'uint8_values'), buffer)
    assert buffers_of(msg) == [
        (('unbounded_sequence_of_unbounded_sequences', 1, 'uint8_values'), buffer)]
    expected = multi_nested(2)
    expected.unbounded_sequence_of_unbounded_sequences[1].uint8_values = b'pixels'
    assert encode(msg) == encode(expected)


def test_field_path_text_and_templates():
    path = FieldPath(('images', 3, 'data'))
    assert str(path) == 'images[3].data' and FieldPath.parse('images[3].data') == path
    assert path == ('images', 3, 'data') and hash(path) == hash(('images', 3, 'data'))
    assert FieldPath.parse('images[*].data') == ('images', EACH, 'data')
    assert FieldPath.parse('images[*].data').is_template and not path.is_template
    for bad in ('', 'a..b', 'a[-1]', 'a[x]', '3'):
        with pytest.raises(ValueError):
            FieldPath.parse(bad)
    with pytest.raises(ValueError):
        FieldPath(('a', -1))


def test_get_at_and_set_at_name_missing_fields():
    msg = multi_nested(1)
    with pytest.raises(LookupError, match=r'no unbounded_sequence_of_unbounded_sequences\[5\]'):
        get_at(msg, ('unbounded_sequence_of_unbounded_sequences', 5, 'uint8_values'))
    with pytest.raises(LookupError, match='no nope'):
        set_at(msg, ('nope',), b'')


def test_buffer_paths_never_raises():
    for bad in (None, 3, 'sensor_msgs/msg/Image', Image(), object):
        assert buffer_paths(bad) == ()
    assert buffer_paths(Image) == (('data',),)


def test_bad_descriptor_maps_raise_codec_error():
    msg = disparity(b'12345678')
    for descriptors, match in (
            ({('image', 'nope'): ('demo', b'')}, r'no uint8\[\] field image.nope'),
            ({('image', EACH): ('demo', b'')}, 'does not name one field'),
            ({3: ('demo', b'')}, 'not a field path'),
            ({'image.data': ('', b'')}, r'image.data: backend_type must be'),
            ({'image.data': ('demo', bytes(MAX_DESCRIPTOR_SIZE + 1))}, 'MAX_DESCRIPTOR_SIZE'),
            ([('image', 'data')], 'descriptor must be a')):
        with pytest.raises(CodecError, match=match):
            encode(msg, descriptors)
    with pytest.raises(UnsupportedMessageTypeError, match='no top-level uint8'):
        encode(msg, ('demo', b'x'))  # the single-payload form needs a payload_field


def test_payload_field_of_a_nested_type_points_to_buffer_paths():
    with pytest.raises(UnsupportedMessageTypeError, match=r'deeper: image.data'):
        codec.payload_field(DisparityImage)


def test_single_payload_api_on_a_general_type():
    msg = UnboundedSequences(uint8_values=b'abc', float64_values=[2.5],
                             uint8_values_default=b'payload', string_values=['z'])
    field = codec.payload_field(UnboundedSequences)
    assert field == 'uint8_values_default' and plans.compiled(UnboundedSequences).plan is None
    head, payload, suffix = codec.encode_parts(msg)
    assert bytes(payload) == b'payload'
    assert bytes(head) + bytes(payload) + bytes(suffix) == bytes(encode(msg))
    back, view = codec.split_payload(encode(msg), UnboundedSequences)
    assert bytes(view) == b'payload' and len(back.uint8_values_default) == 0
    assert back.uint8_values == array.array('B', b'abc')
    enc = encode(msg, ('demo', b'd'))
    assert enc == encode(msg, {(field,): ('demo', b'd')})
    decoded = decode(enc, UnboundedSequences)
    assert (decoded.backend_type, decoded.descriptor) == ('demo', b'd')
    with pytest.raises(CodecError, match='holds a descriptor'):
        codec.split_payload(enc, UnboundedSequences)


def test_wstrings_walk():
    msg = WStrings(wstring_value='ab\u00e9\u6f22', array_of_wstrings=['x', '', 'yz'],
                   unbounded_sequence_of_wstrings=['long one'] * 2)
    enc = check_cpu(msg)
    assert decode(enc, WStrings).msg == msg


# --- malformed input ---------------------------------------------------------------------------

def described_samples():
    """(type, encoded bytes, length of the data in them: the rest is the estimate's slack)"""
    samples = [
        (disparity(bytes(16)), {('image', 'data'): ('demo', b'desc')}),
        (disparity(bytes(range(16))), {}),
        (multi_nested(1), {
            ('unbounded_sequence_of_unbounded_sequences', 0, 'uint8_values'): ('d', b'12')}),
    ]
    return [(type(msg), bytes(encode(msg, descriptors)), len(reference(msg, descriptors).out))
            for msg, descriptors in samples]


@pytest.mark.parametrize('index', range(3))
def test_every_truncation_raises_codec_error(index):
    msg_type, raw, data_end = described_samples()[index]
    decode(raw, msg_type)
    decode(raw[:data_end], msg_type)  # the slack is not needed
    for cut in range(data_end - 1, -1, -1 if index != 2 else -7):
        with pytest.raises(CodecError):
            decode(raw[:cut], msg_type)


@pytest.mark.parametrize('index', range(3))
def test_corrupted_bytes_raise_codec_error_or_decode(index):
    msg_type, raw, _ = described_samples()[index]

    @settings(max_examples=150, deadline=None, database=None)
    @given(st.integers(0, len(raw) - 1), st.integers(1, 255))
    def run(at, flip):
        bad = bytearray(raw)
        bad[at] ^= flip
        try:
            decode(bytes(bad), msg_type, known_backends={'demo', 'd'})
        except CodecError:
            pass
    run()


def test_nested_payload_length_past_the_end():
    raw = bytearray(encode(disparity(bytes(16))))
    at = bytes(raw).index(struct.pack('<I', 16) + bytes(16))
    for length in (2 ** 20, 0xFFFFFFFE):
        struct.pack_into('<I', raw, at, length)
        with pytest.raises(CodecError, match=rf'image.data claims {length} bytes'):
            decode(raw, DisparityImage)
    struct.pack_into('<I', raw, at, 17)  # within the message: the fields after run out
    with pytest.raises(CodecError, match=r'truncated message: f needs'):
        decode(raw, DisparityImage)


def test_bad_marker_strings_and_unknown_backends_in_a_sequence_element():
    path = ('unbounded_sequence_of_unbounded_sequences', 0, 'uint8_values')
    raw = bytes(encode(multi_nested(1), {path: ('demo', b'abcd')}))
    marker = raw.index(b'\xff\xff\xff\xff\x05\x00\x00\x00demo\x00')
    with pytest.raises(CodecError, match=r"unknown backend 'demo' in the descriptor of "
                                         r'unbounded_sequence_of_unbounded_sequences\[0\]'):
        decode(raw, MultiNested, known_backends={'cpu'})
    for name_len, match in ((0, 'claims 0 bytes'), (10 ** 6, 'claims 1000000 bytes'),
                            (3, 'not NUL-terminated')):
        bad = bytearray(raw)
        struct.pack_into('<I', bad, marker + 4, name_len)
        with pytest.raises(CodecError, match=match):
            decode(bad, MultiNested)


def test_big_endian_input_decodes():
    msg = disparity(bytes(range(24)))
    raw = bytes(reference(msg, {('image', 'data'): ('demo', b'xyz')}, little=False).out)
    decoded = decode(raw, DisparityImage)
    assert decoded.descriptors == {('image', 'data'): ('demo', b'xyz')}
    expected = disparity(bytes(range(24)))
    expected.image.data = b''
    assert decoded.msg == expected
    raw = bytes(reference(msg, little=False).out)
    assert decode(raw, DisparityImage).msg == msg


# --- the short path is unchanged for its types --------------------------------------------------

@pytest.mark.parametrize('msg_type', [Image, CompressedImage, PointCloud2])
def test_short_path_types_keep_it(msg_type):
    assert plans.compiled(msg_type).plan is not None
    decoded = decode(encode(msg_type(), {'data': ('demo', b'd')}), msg_type)
    assert decoded.descriptors == {('data',): ('demo', b'd')}
    assert (decoded.backend_type, decoded.descriptor) == ('demo', b'd')


def test_payload_forms_in_a_general_type():
    import numpy
    expected = encode(UnboundedSequences(uint8_values=bytes(range(12)), float64_values=[]))
    for form in (bytes(range(12)), bytearray(range(12)), list(range(12)),
                 numpy.arange(12, dtype=numpy.uint8).reshape(3, 4),
                 numpy.repeat(numpy.arange(12, dtype=numpy.uint8), 2)[::2],
                 Buffer('demo', bytearray(range(12)))):
        msg = UnboundedSequences(float64_values=[])
        msg._uint8_values = form  # any payload form, as the setter would not keep it
        assert encode(msg) == expected, type(form)
    msg = UnboundedSequences()
    msg._uint8_values = numpy.zeros(3, numpy.float32)
    with pytest.raises(CodecError, match=r"uint8_values: payload items must be uint8"):
        encode(msg)


def test_encode_takes_the_mapping_by_keyword_too():
    msg = disparity(bytes(8))
    by_position = encode(msg, {'image.data': ('demo', b'd')})
    assert encode(msg, descriptors={'image.data': ('demo', b'd')}) == by_position
    assert encode(Image(), descriptor=('demo', b'd')) == encode(Image(), {'data': ('demo', b'd')})
    with pytest.raises(TypeError, match='not both'):
        encode(msg, ('demo', b'd'), descriptors={'image.data': ('demo', b'd')})
    with pytest.raises(CodecError, match='must be a mapping'):
        encode(msg, descriptors=('demo', b'd'))


def test_the_docstring_endpoint_recipe_with_the_demo_backend():
    """The publisher/subscription recipe of the codec's docstring, through real shared memory:
    two payloads of a message, one described, one (a peer without the backend) as bytes."""
    import gc
    import numpy
    import demo_buffer_backend
    from demo_buffer_backend import DemoBuffer
    from rosidl_buffer_py import EndpointInfo, EndpointKind, registry
    demo_buffer_backend.shutdown()
    demo = registry.get_backend('demo')
    backends = {'demo': demo}
    peer = EndpointInfo(b'\x22' * 16, '/pair', EndpointKind.SUBSCRIPTION)
    assert demo.on_discovering_endpoint(peer, [], {'demo': demo.get_backend_metadata()})[0]
    msg = multi_nested(2)
    left = DemoBuffer.from_cpu(numpy.arange(16, dtype=numpy.uint8))
    msg.unbounded_sequence_of_unbounded_sequences[0].uint8_values = left
    msg.unbounded_sequence_of_unbounded_sequences[1].uint8_values = Buffer(
        'elsewhere', bytearray(b'right'))
    described = {}
    for path, buffer in buffers_of(msg):
        backend = backends.get(buffer.backend_type)
        descriptor = backend and backend.create_descriptor_with_endpoint(buffer, peer)
        if descriptor is not None:
            described[path] = (buffer.backend_type, descriptor)
    assert list(described) == [('unbounded_sequence_of_unbounded_sequences', 0, 'uint8_values')]
    raw = encode(msg, described)
    decoded = decode(raw, MultiNested, known_backends=backends)
    for path, (backend_type, descriptor) in decoded.descriptors.items():
        set_at(decoded.msg, path,
               backends[backend_type].from_descriptor_with_endpoint(descriptor, peer))
    received = decoded.msg.unbounded_sequence_of_unbounded_sequences
    assert isinstance(received[0].uint8_values, DemoBuffer)
    assert bytes(received[0].uint8_values.to_bytes()) == bytes(range(16))
    assert received[1].uint8_values == array.array('B', b'right')
    assert encode(decoded.msg) == encode(msg)  # the same message, as CPU bytes
    del msg, decoded, received, left, buffer
    gc.collect()
    demo_buffer_backend.shutdown()


def test_two_nested_payloads_of_a_marker():
    """visualization_msgs/Marker holds two payloads (texture.data, a CompressedImage's, and
    mesh_file.data), with strings and sequences between and a bool after them."""
    from visualization_msgs.msg import Marker
    assert buffer_paths(Marker) == (('texture', 'data'), ('mesh_file', 'data'))
    msg = Marker(ns='n', text='label', texture_resource='t', mesh_use_embedded_materials=True)
    msg.texture.format = 'png'
    msg.texture.data = b'\x89PNG' * 3
    msg.mesh_file.filename = 'mesh.dae'
    msg.mesh_file.data = b'<collada/>'
    check_cpu(msg)
    for described in ({'texture.data': ('demo', b'tex')}, {'mesh_file.data': ('gpu', b'')},
                      {'texture.data': ('demo', b'tex'), 'mesh_file.data': ('gpu', b'm' * 7)}):
        enc = encode(msg, described)
        paths = {FieldPath(k): v for k, v in described.items()}
        ref = reference(msg, paths)
        assert bytes(enc[:len(ref.out)]) == bytes(ref.out)
        decoded = decode(enc, Marker)
        assert decoded.descriptors == paths
        assert decoded.msg.mesh_use_embedded_materials is True
        for path in field_paths(msg):
            assert get_at(decoded.msg, path) == (
                array.array('B') if path in paths else get_at(msg, path))


def test_enable_buffer_fields_reaches_nested_types(monkeypatch):
    """enable_buffer_fields(Outer) also patches the setter of Inner.data, Inner being the type
    of a field of Outer and of the elements of another (classes made here, never enabled)."""
    import types
    from rosidl_buffer_py import enable_buffer_fields

    def message_class(name, fields):
        namespace = {'__slots__': ['_' + f for f in fields],
                     'SLOT_TYPES': tuple(t for _, t in fields.values()),
                     'get_fields_and_field_types': classmethod(
                         lambda cls: {f: s for f, (s, _) in fields.items()})}
        for field in fields:
            def getter(self, slot='_' + field):
                return getattr(self, slot)

            def setter(self, value, slot='_' + field):
                setattr(self, slot, array.array('B', bytes(memoryview(value))))  # converts
            getter.__name__ = setter.__name__ = field  # as generated properties are named
            namespace[field] = property(getter, setter)
        return type(name, (), namespace)

    inner = message_class('Inner', {'data': ('sequence<uint8>', definition.UnboundedSequence(
        definition.BasicType('uint8')))})
    module = types.ModuleType('fake_nested_pkg.msg')
    module.Inner = inner
    monkeypatch.setitem(sys.modules, 'fake_nested_pkg', types.ModuleType('fake_nested_pkg'))
    monkeypatch.setitem(sys.modules, 'fake_nested_pkg.msg', module)
    ns = definition.NamespacedType(['fake_nested_pkg', 'msg'], 'Inner')
    outer = message_class('Outer', {'one': ('fake_nested_pkg/Inner', ns),
                                    'many': ('sequence<fake_nested_pkg/Inner>',
                                             definition.UnboundedSequence(ns))})
    buffer = Buffer('demo', bytearray(b'abc'))
    probe = inner()
    probe.data = buffer
    assert probe.data is not buffer  # not enabled yet: the stock setter copies
    assert enable_buffer_fields(outer) == ()  # no top-level uint8[] of its own
    probe.data = buffer
    assert probe.data is buffer
