"""Tests of rosidl_buffer_py.codec, the wire format of messages with a uint8[] payload.

The oracles are rclpy's own serializer (``serialize_message`` / ``deserialize_message``) and a
small, independent CDR writer in this file that also knows where the alignment padding is:
``serialize_message`` leaves its padding uninitialized (stale heap bytes), so comparisons with it
mask the padding, and the codec's output is also compared exactly with the zero-padded reference.
"""
import array
import itertools
import struct

import numpy
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosidl_parser import definition
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import MultiArrayDimension, String, UInt8MultiArray

from rosidl_buffer_py import Buffer, MAX_DESCRIPTOR_SIZE, enable_buffer_fields
from rosidl_buffer_py import _native, codec
from rosidl_buffer_py.codec import plans, walker, wire
from rosidl_buffer_py.codec import (
    CodecError, DESCRIPTOR_MARKER, Decoded, UnsupportedMessageTypeError, decode, encode,
    payload_field)


# --- an independent reference CDR writer (XCDR1, zero padding, padding positions recorded) ------

class CdrWriter:
    """Writes CDR the textbook way: align every primitive to its size relative to the origin."""

    def __init__(self, little: bool = True) -> None:
        self.e = '<' if little else '>'
        self.out = bytearray(b'\x00\x01\x00\x00' if little else b'\x00\x00\x00\x00')
        self.pads = []  # absolute (start, end) of every padding range

    def align(self, n: int) -> None:
        rel = len(self.out) - 4
        gap = -rel % n
        if gap:
            self.pads.append((len(self.out), len(self.out) + gap))
            self.out += bytes(gap)

    def prim(self, fmt: str, value) -> None:
        size = struct.calcsize(fmt)
        self.align(size)
        self.out += struct.pack(self.e + fmt, value)

    def string(self, text: str) -> None:
        data = text.encode('utf-8') + b'\x00'
        self.prim('I', len(data))
        self.out += data

    def u8_seq(self, data: bytes) -> None:
        self.prim('I', len(data))
        self.out += data

    def descriptor(self, backend: str, desc: bytes) -> None:
        self.prim('I', DESCRIPTOR_MARKER)
        self.string(backend)
        self.prim('I', len(desc))
        self.out += desc

    def header(self, header) -> None:
        self.prim('i', header.stamp.sec)
        self.prim('I', header.stamp.nanosec)
        self.string(header.frame_id)


def ref_image(msg, little=True, descriptor=None) -> CdrWriter:
    w = CdrWriter(little)
    w.header(msg.header)
    w.prim('I', msg.height)
    w.prim('I', msg.width)
    w.string(msg.encoding)
    w.prim('B', msg.is_bigendian)
    w.prim('I', msg.step)
    if descriptor:
        w.descriptor(*descriptor)
    else:
        w.u8_seq(bytes(msg.data))
    return w


def ref_compressed(msg, little=True, descriptor=None) -> CdrWriter:
    w = CdrWriter(little)
    w.header(msg.header)
    w.string(msg.format)
    w.descriptor(*descriptor) if descriptor else w.u8_seq(bytes(msg.data))
    return w


def ref_multiarray(msg, little=True, descriptor=None) -> CdrWriter:
    w = CdrWriter(little)
    w.prim('I', len(msg.layout.dim))
    for dim in msg.layout.dim:
        w.string(dim.label)
        w.prim('I', dim.size)
        w.prim('I', dim.stride)
    w.prim('I', msg.layout.data_offset)
    w.descriptor(*descriptor) if descriptor else w.u8_seq(bytes(msg.data))
    return w


def ref_pointcloud(msg, little=True, descriptor=None) -> CdrWriter:
    w = CdrWriter(little)
    w.header(msg.header)
    w.prim('I', msg.height)
    w.prim('I', msg.width)
    w.prim('I', len(msg.fields))
    for field in msg.fields:
        w.string(field.name)
        w.prim('I', field.offset)
        w.prim('B', field.datatype)
        w.prim('I', field.count)
    w.prim('B', msg.is_bigendian)
    w.prim('I', msg.point_step)
    w.prim('I', msg.row_step)
    w.descriptor(*descriptor) if descriptor else w.u8_seq(bytes(msg.data))
    w.prim('B', msg.is_dense)
    return w


REFERENCE = {Image: ref_image, CompressedImage: ref_compressed,
             UInt8MultiArray: ref_multiarray, PointCloud2: ref_pointcloud}


def masked(raw: bytes, pads) -> bytes:
    out = bytearray(raw)
    for start, end in pads:
        out[start:end] = bytes(end - start)
    return bytes(out)


def check_cpu_encoding(msg) -> bytearray:
    """encode(msg) == zero-padded reference == serialize_message(msg) with padding masked."""
    ref = REFERENCE[type(msg)](msg)
    enc = encode(msg)
    assert isinstance(enc, bytearray)
    stock = serialize_message(msg)
    assert len(enc) == len(stock)
    assert bytes(enc) == bytes(ref.out)
    assert bytes(enc) == masked(stock, ref.pads)
    return enc


# --- message factories -------------------------------------------------------------------------

def make_image(data=b'', frame_id='', encoding='rgb8', is_bigendian=0, sec=0, nanosec=0,
               height=0, width=0, step=0):
    msg = Image(height=height, width=width, encoding=encoding, is_bigendian=is_bigendian,
                step=step)
    msg.header.frame_id = frame_id
    msg.header.stamp.sec = sec
    msg.header.stamp.nanosec = nanosec
    msg.data = data
    return msg


def make_compressed(data=b'', fmt='jpeg', frame_id='cam'):
    msg = CompressedImage(format=fmt)
    msg.header.frame_id = frame_id
    msg.data = data
    return msg


def make_multiarray(data=b'', labels=('height', 'width', 'channel'), data_offset=0):
    msg = UInt8MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=label, size=i + 1, stride=7 * i)
                      for i, label in enumerate(labels)]
    msg.layout.data_offset = data_offset
    msg.data = data
    return msg


def make_pointcloud(data=b'', names=('x', 'y', 'z', 'rgb'), is_dense=True, frame_id='lidar'):
    msg = PointCloud2(height=1, width=len(data) // 16, is_bigendian=False, point_step=16,
                      row_step=len(data), is_dense=is_dense)
    msg.header.frame_id = frame_id
    msg.fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, name in enumerate(names)]
    msg.data = data
    return msg


def pattern(n: int) -> bytes:
    return bytes((i * 7 + 3) % 256 for i in range(n))


def set_payload(msg, value) -> None:
    """Store any object in the payload slot (stock setters would convert it to array.array)."""
    setattr(msg, '_' + payload_field(type(msg)), value)


# --- payload_field -----------------------------------------------------------------------------

@pytest.mark.parametrize('msg_type', [Image, CompressedImage, UInt8MultiArray, PointCloud2])
def test_payload_field_of_supported_types(msg_type):
    assert payload_field(msg_type) == 'data'


@pytest.mark.parametrize('bad', [String, int, None, 'sensor_msgs/Image', Image()])
def test_payload_field_rejects_unsupported(bad):
    with pytest.raises(UnsupportedMessageTypeError) as info:
        payload_field(bad)
    assert isinstance(info.value, CodecError) and isinstance(info.value, TypeError)


def test_payload_field_names_why_string_is_unsupported():
    with pytest.raises(CodecError, match=r'String has no top-level uint8\[\] field.*data: string'):
        payload_field(String)


def fake_message_type(name, fields):
    """A stand-in for a generated message class: fields is [(name, idl type string, slot type)]."""
    namespace = {
        '__slots__': ['_' + f for f, _, _ in fields],
        'SLOT_TYPES': tuple(t for _, _, t in fields),
        'get_fields_and_field_types': classmethod(lambda cls: {f: s for f, s, _ in fields}),
    }
    for field, _, _ in fields:
        slot = '_' + field
        namespace[field] = property(lambda self, s=slot: getattr(self, s),
                                    lambda self, v, s=slot: setattr(self, s, v))
    return type(name, (), namespace)


U8_SEQ = ('sequence<uint8>', definition.UnboundedSequence(definition.BasicType('uint8')))


def test_payload_field_is_the_last_uint8_sequence():
    fake = fake_message_type('TwoBlobs', [('first', *U8_SEQ), ('second', *U8_SEQ),
                                          ('flag', 'boolean', definition.BasicType('boolean'))])
    assert payload_field(fake) == 'second'


@pytest.mark.parametrize('after', [
    ('uint32', definition.BasicType('uint32')),
    ('string', definition.UnboundedString()),
    ('sequence<uint8, 3>', definition.BoundedSequence(definition.BasicType('uint8'), 3)),
])
def test_aligned_or_variable_fields_after_the_payload_take_the_general_path(after):
    fake = fake_message_type('Trailing', [('data', *U8_SEQ), ('tail', *after)])
    assert payload_field(fake) == 'data'
    assert plans.compiled(fake).plan is None  # the short path needs fixed alignment-1 fields
    assert codec.buffer_paths(fake) == (('data',),)


def test_payload_field_rejects_unsupported_basic_types():
    fake = fake_message_type('Wide', [('c', 'wchar', definition.BasicType('wchar')),
                                      ('data', *U8_SEQ)])
    with pytest.raises(UnsupportedMessageTypeError, match=r"'c' has type 'wchar'"):
        payload_field(fake)
    assert codec.buffer_paths(fake) == ()  # never raises


# --- CPU encoding: byte equality with serialize_message ----------------------------------------

def test_empty_image_matches_serialize_message():
    enc = check_cpu_encoding(Image())
    assert bytes(enc[:4]) == b'\x00\x01\x00\x00'


@pytest.mark.parametrize('frame_len,encoding_len,data_len',
                         list(itertools.product(range(5), range(5), range(5))))
def test_every_alignment_case(frame_len, encoding_len, data_len):
    check_cpu_encoding(make_image(pattern(data_len), frame_id='f' * frame_len,
                                  encoding='e' * encoding_len))


@pytest.mark.parametrize('encoding', [
    '', 'a', 'rgb8', 'rgba8', 'bgr8', 'bgra8', 'mono8', 'mono16', 'rgb16', 'bgra16', '8UC1',
    '8UC3', '16UC1', '32FC1', '64FC4', 'bayer_rggb8', 'bayer_gbrg16', 'yuv422', 'yuv422_yuy2',
    'nv21', 'x' * 255, 'e' * 1001, 'é漢字🙂', 'with space', 'tab\tand\nnewline'])
def test_every_encoding_string(encoding):
    check_cpu_encoding(make_image(pattern(13), encoding=encoding, height=1, width=13, step=13))


@pytest.mark.parametrize('frame_id', ['', 'camera', 'camera_color_optical_frame', 'f' * 4096,
                                      'καμερα/光学', 'a/b/c/d/e/f', '🙂' * 100])
@pytest.mark.parametrize('is_bigendian', [0, 1, 255])
def test_frame_ids_and_endianness_flag(frame_id, is_bigendian):
    check_cpu_encoding(make_image(pattern(33), frame_id=frame_id, is_bigendian=is_bigendian))


@pytest.mark.parametrize('sec,nanosec', [(0, 0), (-2**31, 0), (2**31 - 1, 999_999_999),
                                         (-1, 2**32 - 1), (1_700_000_000, 123_456_789)])
def test_stamps_at_extremes(sec, nanosec):
    check_cpu_encoding(make_image(b'xyz', sec=sec, nanosec=nanosec, height=2**32 - 1,
                                  width=2**32 - 1, step=2**32 - 1))


@pytest.mark.parametrize('size', [1, 2, 3, 5, 7, 8, 9, 1023, 4097, 65_535, 65_537, 1 << 20])
def test_payload_sizes(size):
    data = pattern(size)
    enc = check_cpu_encoding(make_image(data, height=1, width=size, step=size, encoding='mono8'))
    assert bytes(enc[-size:]) == data


@pytest.mark.parametrize('msg', [
    make_compressed(), make_compressed(pattern(1)), make_compressed(pattern(1001), 'png'),
    make_compressed(pattern(7), 'rgb8; jpeg compressed bgr8', 'f' * 3),
    make_multiarray(), make_multiarray(pattern(5), labels=()),
    make_multiarray(pattern(6), labels=('', 'a', 'ab', 'abc', 'abcd'), data_offset=9),
    make_pointcloud(), make_pointcloud(pattern(64)), make_pointcloud(pattern(17), is_dense=False),
    make_pointcloud(pattern(48), names=('intensity', 'ring', 't', 'reflectivity', 'ambient')),
    make_pointcloud(pattern(3), names=()),
], ids=lambda msg: type(msg).__name__)
def test_other_payload_types_match_serialize_message(msg):
    enc = check_cpu_encoding(msg)
    assert decode(enc, type(msg)).msg == msg


def test_encoding_padding_is_zero():
    msg = make_image(b'abc', frame_id='f', encoding='rgb8')
    ref = ref_image(msg)
    enc = encode(msg)
    assert ref.pads, 'this message has padding'
    for start, end in ref.pads:
        assert bytes(enc[start:end]) == bytes(end - start)


def test_encode_does_not_modify_the_message():
    msg = make_pointcloud(pattern(32))
    before = serialize_message(msg)
    encode(msg)
    encode(msg, ('demo', b'1234'))
    assert deserialize_message(before, PointCloud2) == msg


# --- payload representations -------------------------------------------------------------------

PAYLOAD_FORMS = {
    'array': lambda data: array.array('B', data),
    'bytes': bytes,
    'bytearray': bytearray,
    'memoryview': memoryview,
    'list': list,
    'tuple': tuple,
    'numpy': lambda data: numpy.frombuffer(data, dtype=numpy.uint8),
    'numpy_hwc': lambda data: numpy.frombuffer(data, dtype=numpy.uint8).reshape(3, 5, 3),
    'numpy_strided': lambda data: numpy.repeat(numpy.frombuffer(data, numpy.uint8), 2)[::2],
    'buffer_host': lambda data: Buffer('demo', bytearray(data)),
    'buffer_readonly': lambda data: Buffer('demo', bytes(data)),
    'buffer_device': lambda data: DeviceBuffer(data),
}


class DeviceBuffer(Buffer):
    """A Buffer whose memory is not host-addressable: it must be downloaded with to_bytes()."""

    def __init__(self, data: bytes) -> None:
        super().__init__('fake_gpu', size=len(data))
        self.downloads = 0
        self._device = bytes(data)

    def to_bytes(self) -> bytes:
        self.downloads += 1
        return self._device


@pytest.mark.parametrize('form', sorted(PAYLOAD_FORMS))
@pytest.mark.parametrize('msg_factory', [make_image, make_pointcloud])
def test_payload_forms_encode_as_cpu_bytes(form, msg_factory):
    data = pattern(45)
    expected = encode(msg_factory(data))
    msg = msg_factory(data)
    set_payload(msg, PAYLOAD_FORMS[form](data))
    assert encode(msg) == expected


def test_buffer_stored_through_the_setter_encodes_as_cpu_bytes():
    enable_buffer_fields(Image)
    data = pattern(100)
    msg = make_image(encoding='mono8', height=10, width=10, step=10)
    device = DeviceBuffer(data)
    msg.data = device
    assert msg.data is device
    assert encode(msg) == encode(make_image(data, encoding='mono8', height=10, width=10, step=10))
    assert device.downloads == 1
    msg.data = Buffer('demo', bytearray(data))
    decoded = decode(encode(msg), Image)
    assert decoded.backend_type is None and decoded.msg.data == array.array('B', data)


def test_buffer_payload_of_a_type_enabled_by_the_codec():
    assert payload_field(UInt8MultiArray) == 'data'  # compiling the plan enables Buffer storage
    msg = make_multiarray()
    msg.data = Buffer('demo', bytearray(b'\x01\x02\x03'))
    assert isinstance(msg.data, Buffer)
    assert encode(msg) == encode(make_multiarray(b'\x01\x02\x03'))


class NoDownloadBuffer(Buffer):
    def __init__(self) -> None:
        super().__init__('opaque', size=4)


@pytest.mark.parametrize('value,match', [
    (numpy.zeros(4, dtype=numpy.float32), r"format 'f'"),
    (numpy.zeros(4, dtype=numpy.uint16), r"format 'H'"),
    (array.array('i', [1, 2]), r"format 'i'"),
    ('abc', r'cannot send a str'),
    (12, r'cannot send a int'),
    (None, r'cannot send a NoneType'),
    ([1, 256], r'ints in \[0, 255\]'),
    ([1, -1], r'ints in \[0, 255\]'),
    ([1, 'a'], r'ints in \[0, 255\]'),
    (NoDownloadBuffer(), r"'opaque'.*cannot be read as CPU bytes"),
])
def test_bad_payloads_raise_codec_error(value, match):
    msg = make_image()
    set_payload(msg, value)
    with pytest.raises(CodecError, match=match):
        encode(msg)


def test_unserializable_field_raises_codec_error():
    msg = make_image(b'abc')
    msg._height = -1  # bypasses the setter's check, as a careless caller could
    with pytest.raises(CodecError, match='cannot serialize Image'):
        encode(msg)


# --- legacy decode -----------------------------------------------------------------------------

LEGACY_MESSAGES = [
    Image(), make_image(b'\x00'), make_image(pattern(4095), 'cam', 'mono8', 1, -5, 7, 63, 65, 65),
    make_image(pattern(3), 'é漢', 'x' * 300), make_compressed(pattern(10)), make_multiarray(),
    make_multiarray(pattern(9), labels=('abc',)), make_pointcloud(pattern(32)),
    make_pointcloud(pattern(5), is_dense=False, names=('a', 'bb', 'ccc')),
]


@pytest.mark.parametrize('msg', LEGACY_MESSAGES, ids=lambda msg: type(msg).__name__)
def test_legacy_decode_equals_deserialize_message(msg):
    raw = serialize_message(msg)  # stock bytes, with whatever padding rclpy left in them
    decoded = decode(raw, type(msg))
    assert isinstance(decoded, Decoded)
    assert decoded.backend_type is None and decoded.descriptor is None
    assert not decoded.is_descriptor
    assert decoded.msg == deserialize_message(raw, type(msg)) == msg
    assert type(decoded.msg.data) is array.array and decoded.msg.data.typecode == 'B'


@pytest.mark.parametrize('wrap', [bytes, bytearray, memoryview,
                                  lambda raw: memoryview(b'??' + raw)[2:]])
def test_decode_accepts_bytes_like(wrap):
    msg = make_image(pattern(21), 'cam')
    assert decode(wrap(bytes(encode(msg))), Image).msg == msg


def test_decode_ignores_trailing_bytes_like_deserialize_message():
    raw = bytes(encode(make_pointcloud(pattern(16)))) + b'\x00\x00\x00'
    assert decode(raw, PointCloud2).msg == deserialize_message(raw, PointCloud2)


@pytest.mark.parametrize('msg', LEGACY_MESSAGES, ids=lambda msg: type(msg).__name__)
def test_big_endian_cdr_decodes(msg):
    raw = bytes(REFERENCE[type(msg)](msg, little=False).out)
    assert raw[:2] == b'\x00\x00'
    assert decode(raw, type(msg)).msg == msg == deserialize_message(raw, type(msg))


@pytest.mark.parametrize('msg', LEGACY_MESSAGES[:5], ids=lambda msg: type(msg).__name__)
def test_big_endian_descriptor_decodes(msg):
    raw = bytes(REFERENCE[type(msg)](msg, little=False, descriptor=('demo', b'd' * 9)).out)
    decoded = decode(raw, type(msg))
    assert (decoded.backend_type, decoded.descriptor) == ('demo', b'd' * 9)


def test_decoded_payload_is_a_copy():
    raw = bytearray(encode(make_image(b'abcd')))
    decoded = decode(raw, Image)
    raw[-4:] = b'wxyz'
    assert decoded.msg.data.tobytes() == b'abcd'


# --- descriptor path ---------------------------------------------------------------------------

@pytest.mark.parametrize('backend', ['d', 'de', 'dem', 'demo', 'cuda_ipc', 'b' * 63, 'ünï'])
@pytest.mark.parametrize('desc_len', [0, 1, 3, 4, 5, 64, MAX_DESCRIPTOR_SIZE])
def test_descriptor_round_trip_image(backend, desc_len):
    desc = pattern(desc_len)
    msg = make_image(pattern(50), frame_id='cam', encoding='rgb8', height=1, width=16, step=48)
    enc = encode(msg, (backend, desc))
    assert bytes(enc) == bytes(ref_image(msg, descriptor=(backend, desc)).out)
    decoded = decode(enc, Image, known_backends={backend, 'cpu'})
    assert decoded.is_descriptor
    assert (decoded.backend_type, decoded.descriptor) == (backend, desc)
    assert type(decoded.msg.data) is array.array and len(decoded.msg.data) == 0
    assert decoded.msg == make_image(b'', frame_id='cam', encoding='rgb8', height=1, width=16,
                                     step=48)


@pytest.mark.parametrize('factory', [make_compressed, make_multiarray, make_pointcloud])
@pytest.mark.parametrize('desc_len', [0, 1, 2, 7])
def test_descriptor_round_trip_other_types(factory, desc_len):
    msg = factory(pattern(32))
    desc = pattern(desc_len)
    enc = encode(msg, ('demo', desc))
    assert bytes(enc) == bytes(REFERENCE[type(msg)](msg, descriptor=('demo', desc)).out)
    decoded = decode(enc, type(msg))
    expected = factory(pattern(32))
    expected.data = b''
    assert decoded.msg == expected
    assert decoded.descriptor == desc


def test_descriptor_keeps_fields_after_the_payload():
    for dense in (True, False):
        decoded = decode(encode(make_pointcloud(pattern(16), is_dense=dense), ('demo', b'x')),
                         PointCloud2)
        assert decoded.msg.is_dense is dense


def test_descriptor_prefix_is_the_cpu_prefix():
    msg = make_image(pattern(10), frame_id='frame', encoding='bgr8')
    cpu = encode(msg)
    desc = encode(msg, ('demo', b'abc'))
    offset = len(cpu) - 4 - 10
    assert desc[:offset] == cpu[:offset]
    assert desc[offset:offset + 4] == b'\xff\xff\xff\xff'
    assert struct.unpack_from('<I', cpu, offset)[0] == 10


def test_descriptor_accepts_bytes_like():
    msg = make_image(b'')
    expected = encode(msg, ('demo', b'abc'))
    for desc in (bytearray(b'abc'), memoryview(b'abc'), array.array('B', b'abc')):
        assert encode(msg, ('demo', desc)) == expected


def test_known_backends_rejects_unknown_backend():
    enc = encode(make_image(b'pixels'), ('gpu_ipc', b'handle'))
    with pytest.raises(CodecError, match=r"unknown backend 'gpu_ipc'.*known: cpu, demo"):
        decode(enc, Image, known_backends={'cpu', 'demo'})
    with pytest.raises(CodecError, match='unknown backend'):
        decode(enc, Image, known_backends=frozenset())
    assert decode(enc, Image, known_backends=['gpu_ipc']).backend_type == 'gpu_ipc'
    assert decode(enc, Image).backend_type == 'gpu_ipc'


def test_known_backends_does_not_affect_cpu_bytes():
    msg = make_image(b'pixels')
    assert decode(encode(msg), Image, known_backends=set()).msg == msg


@pytest.mark.parametrize('descriptor,match', [
    (('demo', bytes(MAX_DESCRIPTOR_SIZE + 1)), r'4097 bytes, more than MAX_DESCRIPTOR_SIZE'),
    (('', b'x'), 'non-empty str'),
    (('de\x00mo', b'x'), 'without NUL'),
    ((b'demo', b'x'), 'non-empty str'),
    (('demo', 'text'), 'bytes-like'),
    (('demo',), r'\(backend_type, descriptor_bytes\) pair'),
    (('\ud800', b'x'), 'not encodable as UTF-8'),
    ('demo', r'\(backend_type, descriptor_bytes\) pair'),
])
def test_bad_descriptor_raises_on_encode(descriptor, match):
    with pytest.raises(CodecError, match=match):
        encode(make_image(), descriptor)


# --- malformed input ---------------------------------------------------------------------------

VALID_ENCODINGS = {
    'image': (Image, lambda: encode(make_image(pattern(9), 'cam', 'rgb8'))),
    'image_descriptor': (Image, lambda: encode(make_image(b'', 'cam'), ('demo', b'desc!'))),
    'pointcloud': (PointCloud2, lambda: encode(make_pointcloud(pattern(16)))),
    'pointcloud_descriptor': (PointCloud2,
                              lambda: encode(make_pointcloud(pattern(16)), ('demo', b'12345'))),
    'multiarray': (UInt8MultiArray, lambda: encode(make_multiarray(pattern(3)))),
    'compressed': (CompressedImage, lambda: encode(make_compressed(pattern(3)))),
}


@pytest.mark.parametrize('name', sorted(VALID_ENCODINGS))
def test_every_truncation_raises_codec_error(name):
    msg_type, make = VALID_ENCODINGS[name]
    raw = bytes(make())
    decode(raw, msg_type)  # the whole message is fine
    for cut in range(len(raw)):
        with pytest.raises(CodecError):
            decode(raw[:cut], msg_type)


def test_truncation_messages_are_clear():
    raw = bytes(encode(make_image(pattern(9), 'cam')))
    with pytest.raises(CodecError, match='shorter than the 4-byte CDR encapsulation header'):
        decode(raw[:3], Image)
    with pytest.raises(CodecError, match=r'truncated message: header.stamp.sec needs 8 bytes'):
        decode(raw[:9], Image)
    with pytest.raises(CodecError, match=r'data claims 9 bytes at offset \d+ but only 8 are left'):
        decode(raw[:-1], Image)


def test_truncated_fields_after_the_payload():
    for descriptor in (None, ('demo', b'abc')):
        raw = bytes(encode(make_pointcloud(pattern(16)), descriptor))
        with pytest.raises(CodecError, match=r'truncated message: the fields after data needs 1'):
            decode(raw[:-1], PointCloud2)


def payload_length_offset(raw: bytes, data_len: int) -> int:
    return len(raw) - data_len - 4


@pytest.mark.parametrize('length', [10, 11, 2**16, 2**31, 0xFFFFFFFE])
def test_payload_length_past_the_end(length):
    raw = bytearray(encode(make_image(pattern(9), 'cam')))
    struct.pack_into('<I', raw, payload_length_offset(raw, 9), length)
    with pytest.raises(CodecError, match=rf'data claims {length} bytes'):
        decode(raw, Image)


def test_pointcloud_field_count_past_the_end():
    msg = make_pointcloud(pattern(16), names=('x',))
    raw = bytearray(encode(msg))
    offset = ref_pointcloud(msg).out.index(struct.pack('<I', 2) + b'x\x00') - 4
    struct.pack_into('<I', raw, offset, 2)  # the second element runs into the payload
    with pytest.raises(CodecError):
        decode(raw, PointCloud2)
    for count in (1000, 0xFFFFFFFF):
        struct.pack_into('<I', raw, offset, count)
        with pytest.raises(CodecError,
                           match=rf'sequence fields at offset \d+ claims {count} elements'):
            decode(raw, PointCloud2)


@pytest.mark.parametrize('kind', [0x0002, 0x0003, 0x0006, 0x0007, 0x000a, 0x0100, 0xFFFF])
def test_bad_encapsulation_header(kind):
    raw = bytearray(encode(make_image(b'abc')))
    struct.pack_into('>H', raw, 0, kind)
    with pytest.raises(CodecError, match=rf'encapsulation 0x{kind:04x}; accepted: 0x0000 .* '
                                         r'and 0x0001'):
        decode(raw, Image)


def test_non_nul_terminated_strings():
    msg = make_image(b'abc', frame_id='cam', encoding='rgb8')
    raw = bytes(encode(msg))
    for text in (b'cam\x00', b'rgb8\x00'):
        bad = bytearray(raw)
        bad[raw.index(text) + len(text) - 1] = ord('!')
        with pytest.raises(CodecError, match='is not NUL-terminated'):
            decode(bad, Image)


def test_zero_length_string():
    raw = bytearray(encode(make_image(b'', frame_id='')))
    struct.pack_into('<I', raw, 12, 0)
    with pytest.raises(CodecError, match=r'header.frame_id at offset 12 has length 0'):
        decode(raw, Image)


def test_string_length_past_the_end():
    raw = bytearray(encode(make_image(b'', frame_id='')))
    struct.pack_into('<I', raw, 12, 1000)
    with pytest.raises(CodecError, match=r'header.frame_id at offset 12 claims 1000 bytes'):
        decode(raw, Image)


def descriptor_offsets(raw: bytes):
    marker = raw.index(b'\xff\xff\xff\xff')
    name_len = struct.unpack_from('<I', raw, marker + 4)[0]
    desc_len_at = marker + 8 + name_len
    desc_len_at += -(desc_len_at - 4) % 4
    return marker, desc_len_at


def test_oversized_descriptor_on_decode():
    raw = bytes(encode(make_image(b''), ('demo', b'')))
    _, at = descriptor_offsets(raw)
    big = bytearray(raw[:at]) + struct.pack('<I', MAX_DESCRIPTOR_SIZE + 1) + bytes(5000)
    with pytest.raises(CodecError, match=r'4097 bytes, more than MAX_DESCRIPTOR_SIZE \(4096\)'):
        decode(big, Image)
    ok = bytearray(raw[:at]) + struct.pack('<I', MAX_DESCRIPTOR_SIZE) + bytes(4096)
    assert len(decode(ok, Image).descriptor) == MAX_DESCRIPTOR_SIZE


def test_descriptor_length_past_the_end():
    raw = bytearray(encode(make_image(b''), ('demo', b'abcd')))
    _, at = descriptor_offsets(raw)
    struct.pack_into('<I', raw, at, 5)
    with pytest.raises(CodecError, match=r"descriptor of backend 'demo' claims 5 bytes"):
        decode(raw, Image)


def test_marker_with_bad_backend_string():
    raw = bytes(encode(make_image(b''), ('demo', b'abcd')))
    marker, _ = descriptor_offsets(raw)
    with pytest.raises(CodecError, match='backend name length'):
        decode(raw[:marker + 6], Image)
    for name_len, match in ((0, 'claims 0 bytes'), (100, 'claims 100 bytes'),
                            (4, 'not NUL-terminated')):
        bad = bytearray(raw)
        struct.pack_into('<I', bad, marker + 4, name_len)
        with pytest.raises(CodecError, match=match):
            decode(bad, Image)
    bad = bytearray(raw)
    bad[marker + 8] = 0xff  # not UTF-8
    with pytest.raises(CodecError, match='not UTF-8'):
        decode(bad, Image)


@pytest.mark.parametrize('raw', ['text', 42, None, [0, 1, 0, 0]])
def test_decode_rejects_non_bytes(raw):
    with pytest.raises(CodecError, match='raw must be bytes'):
        decode(raw, Image)


def test_decode_rejects_unsupported_type():
    with pytest.raises(UnsupportedMessageTypeError):
        decode(b'\x00\x01\x00\x00', int)
    with pytest.raises(CodecError, match='truncated message: the length of string data'):
        decode(b'\x00\x01\x00\x00', String)  # every message type is supported now
    assert decode(serialize_message(String(data='hi')), String).msg == String(data='hi')


# --- the walker agrees with rclpy's serializer on other layouts --------------------------------

def test_walker_finds_the_end_of_many_message_layouts():
    """Sanity check of the walker on layouts the payload types do not use (float64 alignment,
    nested sequences, fixed arrays): walking the fields of serialize_message bytes ends where
    the message ends (rclpy may append a few bytes of slack to its size estimate)."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from sensor_msgs.msg import CameraInfo, Imu, JointState
    from visualization_msgs.msg import Marker

    def walker_ops(msg_type):
        builder = walker.Builder()
        for name, slot_type in walker.message_fields(msg_type):
            walker.add_type(builder, slot_type, name, (msg_type,))
        return builder.freeze()

    joint = JointState(name=['a', 'bc'], position=[1.0], velocity=[], effort=[2.0, 3.0])
    joint.header.frame_id = 'abc'
    camera = CameraInfo(distortion_model='plumb_bob', d=[0.1] * 5)
    marker = Marker(ns='n', text='hello', points=[], mesh_resource='x')
    for msg in (joint, JointState(), camera, Imu(), marker, PoseWithCovarianceStamped()):
        raw = serialize_message(msg)
        body = memoryview(raw)[4:]
        end = walker.walk(walker_ops(type(msg)), body, 0, len(body),
                          struct.Struct('<I').unpack_from, None)
        assert len(raw) - 8 <= end + 4 <= len(raw)
        assert deserialize_message(raw[:end + 4], type(msg)) == msg
        if end + 4 > 4:
            with pytest.raises(CodecError):
                walker.walk(walker_ops(type(msg)), body, 0, end - 1,
                            struct.Struct('<I').unpack_from, None)


def test_op_fields_are_in_the_order_the_fast_path_reads():
    """src/native/codec_fast.cpp reads the walker's ops by position (PyTuple_GET_ITEM): the kind
    first, then each kind's fields where it looks for them. A reordered op fails here."""
    assert (walker.FIXED, walker.STRING, walker.PSEQ, walker.SEQ, walker.ARRAY, walker.BLOB,
            walker.WSTRING) == tuple(range(7))  # enum OpKind's values
    assert walker.FixedOp._fields == ('kind', 'align', 'size', 'inner_pads', 'label')
    assert walker.StringOp._fields == ('kind', 'bound', 'label')
    assert walker.PrimitiveSeqOp._fields == ('kind', 'align', 'itemsize', 'bound', 'label')
    assert walker.SeqOp._fields == ('kind', 'sub_ops', 'min_size', 'bound', 'label', 'path')
    assert walker.ArrayOp._fields == ('kind', 'sub_ops', 'count', 'label', 'path')
    assert walker.BlobOp._fields == ('kind', 'path', 'label')
    assert walker.WStringOp._fields == ('kind', 'bound', 'label')
    # what the builder gives are those tuples, each of the class of its kind, at any depth
    from test_msgs.msg import MultiNested, WStrings
    classes = {walker.FIXED: walker.FixedOp, walker.STRING: walker.StringOp,
               walker.PSEQ: walker.PrimitiveSeqOp, walker.SEQ: walker.SeqOp,
               walker.ARRAY: walker.ArrayOp, walker.BLOB: walker.BlobOp,
               walker.WSTRING: walker.WStringOp}
    seen = set()

    def check(ops):
        assert type(ops) is tuple
        for op in ops:
            assert isinstance(op, tuple) and type(op) is classes[op[0]], op
            seen.add(op.kind)
            if op.kind in (walker.SEQ, walker.ARRAY):
                check(op.sub_ops)
    for msg_type in (MultiNested, WStrings, Image):
        check(plans.compiled(msg_type).ops)
    check(plans.short_plan(Image).prefix_ops)
    assert seen == set(classes)


# --- the C fast path (rosidl_buffer_py._native.encode_descriptor / decode_descriptor) -----------

def _python_only(monkeypatch):
    """Make the codec run its Python path only (the C one answers None: "cannot")."""
    class NoFastPath:
        @staticmethod
        def encode_descriptor(*args):
            return None

        @staticmethod
        def decode_descriptor(*args):
            return None
    from rosidl_buffer_py import _native
    monkeypatch.setattr(_native, 'encode_descriptor', NoFastPath.encode_descriptor)
    monkeypatch.setattr(_native, 'decode_descriptor', NoFastPath.decode_descriptor)


def _fast_path_cases():
    image = Image(height=3, width=70001, encoding='rgb8', is_bigendian=1, step=9)
    image.header.frame_id = 'camera'
    image.header.stamp.sec, image.header.stamp.nanosec = 1700000000, 123456789
    cloud = PointCloud2(fields=[PointField(name='x', offset=0, datatype=7, count=1)],
                        is_dense=True)
    array_msg = UInt8MultiArray()
    array_msg.layout.dim = [MultiArrayDimension(label='rows', size=3, stride=2)]
    return [(image, ('demo', bytes(range(70)))), (CompressedImage(format='jpeg'), ('x', b'')),
            (cloud, ('vendor_backend', b'\x01' * 9)), (array_msg, ('d', b'\xff' * 64))]


def test_fast_path_gives_the_python_path_bytes_and_messages(monkeypatch):
    from rosidl_buffer_py import _native
    for msg, descriptor in _fast_path_cases():
        plan = plans.short_plan(type(msg))
        fast = encode(msg, descriptor)
        assert _native.encode_descriptor(
            msg, plan.slots, plan.slot, wire.EMPTY_PAYLOAD, descriptor[0].encode(),
            descriptor[1], plan.suffix_size) == fast  # the C path did answer
        assert _native.decode_descriptor(fast, type(msg), plan.prefix_ops, plan.suffix_size,
                                         MAX_DESCRIPTOR_SIZE) is not None
        fast_decoded = decode(fast, type(msg))
        # malformed variants: the C path declines, the Python path names the problem
        variants = [fast[:cut] for cut in range(0, len(fast), 3)]
        variants += [fast[:i] + bytes([fast[i] ^ 0xA5]) + fast[i + 1:] for i in range(len(fast))]

        def outcome(raw):
            try:
                d = decode(raw, type(msg), known_backends={descriptor[0]})
                return d.msg, d.backend_type, d.descriptor
            except CodecError as exc:
                return str(exc)
        fast_outcomes = [outcome(bytes(v)) for v in variants]
        with monkeypatch.context() as m:
            _python_only(m)
            assert encode(msg, descriptor) == fast
            slow_decoded = decode(fast, type(msg))
            assert [outcome(bytes(v)) for v in variants] == fast_outcomes
        assert fast_decoded == slow_decoded
        assert type(getattr(fast_decoded.msg, plan.field)) is array.array


# --- slot programs: the decoded message built from its slots in C ------------------------------

def _slot_values(msg, seen=()):
    """Every slot of ``msg`` (nested messages too) with its value's type: what equality of two
    messages does not check."""
    out = {}
    for slot in type(msg).__slots__:
        value = getattr(msg, slot)
        if hasattr(type(value), 'SLOT_TYPES'):
            out[slot] = _slot_values(value)
        else:
            out[slot] = (type(value), value.tobytes() if isinstance(value, array.array) else value)
    return out


def _decoded_both_ways(raw, msg_type):
    """The descriptor message decoded by its slot program and by the type support."""
    plan = plans.short_plan(msg_type)
    program = plans.compiled(msg_type).program
    assert program is not None
    by_program = _native.decode_descriptor(raw, msg_type, plan.prefix_ops, plan.suffix_size,
                                           MAX_DESCRIPTOR_SIZE, program)
    by_support = _native.decode_descriptor(raw, msg_type, plan.prefix_ops, plan.suffix_size,
                                           MAX_DESCRIPTOR_SIZE)
    return by_program, by_support


def _random_messages(seed):
    """An Image, a CompressedImage and a MeshFile (the types with slot programs) with random
    field values, and a random generator for more."""
    import random
    from visualization_msgs.msg import MeshFile
    rng = random.Random(seed)
    texts = ['', 'camera', 'kamera_ü_日本', 'x' * rng.randrange(0, 300), '\U0001F600 frame']
    image = Image(height=rng.randrange(2 ** 32), width=rng.randrange(2 ** 32),
                  encoding=rng.choice(texts), is_bigendian=rng.randrange(256),
                  step=rng.randrange(2 ** 32), data=bytes(rng.randrange(0, 50)))
    image.header.stamp.sec = rng.randrange(-2 ** 31, 2 ** 31)
    image.header.stamp.nanosec = rng.randrange(2 ** 32)
    image.header.frame_id = rng.choice(texts)
    compressed = CompressedImage(format=rng.choice(texts))
    compressed.header = image.header
    return (image, compressed, MeshFile(filename=rng.choice(texts))), rng


@pytest.mark.parametrize('seed', range(20))
def test_slot_program_builds_the_message_the_type_support_builds(seed):
    messages, rng = _random_messages(seed)
    for msg in messages:
        descriptor = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 80)))
        raw = codec.encode(msg, ('demo', descriptor))
        by_program, by_support = _decoded_both_ways(raw, type(msg))
        assert by_program[1:] == by_support[1:] == ('demo', descriptor)
        assert by_program[0] == by_support[0]
        assert _slot_values(by_program[0]) == _slot_values(by_support[0])
        assert type(by_program[0].data) is array.array and len(by_program[0].data) == 0


def test_slot_program_leaves_what_it_does_not_build_exactly_to_the_type_support():
    """A string that is not strict UTF-8 (convert_to_py replaces the bad bytes): the message
    comes from the generated code, the same as without a program."""
    image = Image(encoding='mono8')
    image.header.frame_id = 'camera'
    raw = bytearray(codec.encode(image, ('demo', b'd')))
    at = bytes(raw).index(b'camera')
    raw[at:at + 2] = b'\xff\xfe'
    by_program, by_support = _decoded_both_ways(bytes(raw), Image)
    assert by_program[0].header.frame_id == by_support[0].header.frame_id == '\ufffd\ufffdmera'
    assert _slot_values(by_program[0]) == _slot_values(by_support[0])


def test_slot_program_kinds_are_the_numbers_the_fast_path_reads():
    assert (plans.P_BOOL, plans.P_INT8, plans.P_UINT8, plans.P_INT16, plans.P_UINT16,
            plans.P_INT32, plans.P_UINT32, plans.P_INT64, plans.P_UINT64, plans.P_FLOAT32,
            plans.P_FLOAT64, plans.P_STRING, plans.P_MESSAGE, plans.P_PAYLOAD) == \
        tuple(range(14))  # enum SlotKind's values


def test_slot_program_is_none_for_kinds_it_does_not_build():
    assert plans.compiled(UInt8MultiArray).program is None  # a sequence of messages
    assert plans.slot_program(PointCloud2) is None
    from test_msgs.msg import BasicTypes, WStrings
    assert plans.slot_program(BasicTypes) is None  # byte and char
    assert plans.slot_program(WStrings) is None


class _AllKinds:
    """Slots of every kind a program builds, laid out as rosidl generates them."""

    __slots__ = ('_flag', '_i8', '_u8', '_i16', '_u16', '_i32', '_u32', '_i64', '_u64', '_f32',
                 '_f64', '_text', '_short', '_data', '_check_fields')


_ALL_KINDS = [  # (slot, rosidl type, struct format, value)
    ('_flag', definition.BasicType('boolean'), '?', True),
    ('_i8', definition.BasicType('int8'), 'b', -128),
    ('_u8', definition.BasicType('uint8'), 'B', 255),
    ('_i16', definition.BasicType('int16'), 'h', -32768),
    ('_u16', definition.BasicType('uint16'), 'H', 65535),
    ('_i32', definition.BasicType('int32'), 'i', -2 ** 31),
    ('_u32', definition.BasicType('uint32'), 'I', 2 ** 32 - 1),
    ('_i64', definition.BasicType('int64'), 'q', -2 ** 63),
    ('_u64', definition.BasicType('uint64'), 'Q', 2 ** 64 - 1),
    ('_f32', definition.BasicType('float'), 'f', 1.5),
    ('_f64', definition.BasicType('double'), 'd', -2.25e300),
    ('_text', definition.UnboundedString(), None, 'grüße'),
    ('_short', definition.BoundedString(3), None, 'abc'),
]


def _all_kinds_cdr(little: bool, values) -> bytes:
    order = '<' if little else '>'
    body = bytearray()

    def put(fmt, value):
        size = struct.calcsize(fmt)
        body.extend(bytes(-len(body) % size))
        body.extend(struct.pack(order + fmt, value))

    for (_, _, fmt, _), value in zip(_ALL_KINDS, values):
        if fmt is None:
            encoded = value.encode() + b'\0'
            put('I', len(encoded))
            body.extend(encoded)
        else:
            put('B' if fmt == '?' and type(value) is int else fmt, value)  # a raw bool byte
    put('I', 0xFFFFFFFF)
    put('I', 5)
    body.extend(b'demo\0')
    put('I', 3)
    body.extend(b'abc')
    return bytes([0, 1 if little else 0, 0, 0]) + bytes(body)


def _all_kinds_program():
    kinds = [plans.P_BOOL, plans.P_INT8, plans.P_UINT8, plans.P_INT16, plans.P_UINT16,
             plans.P_INT32, plans.P_UINT32, plans.P_INT64, plans.P_UINT64, plans.P_FLOAT32,
             plans.P_FLOAT64, plans.P_STRING, plans.P_STRING]
    args = [None] * 11 + [-1, 3]
    return (_AllKinds, True, tuple((slot, kind, arg) for (slot, _, _, _), kind, arg
                                   in zip(_ALL_KINDS, kinds, args)) +
            (('_data', plans.P_PAYLOAD, list),))


def _all_kinds_decode(raw):
    builder = walker.Builder()
    for slot, slot_type, _, _ in _ALL_KINDS:
        walker.add_type(builder, slot_type, slot, (_AllKinds,))
    # a class without type support: what the program does not build comes back as None
    return _native.decode_descriptor(raw, _AllKinds, builder.freeze(), 0, MAX_DESCRIPTOR_SIZE,
                                     _all_kinds_program())


@pytest.mark.parametrize('little', [True, False])
def test_slot_program_builds_every_kind_in_either_byte_order(little):
    values = [value for _, _, _, value in _ALL_KINDS]
    msg, backend, descriptor = _all_kinds_decode(_all_kinds_cdr(little, values))
    assert type(msg) is _AllKinds and (backend, descriptor) == ('demo', b'abc')
    for (slot, _, _, value) in _ALL_KINDS:
        assert getattr(msg, slot) == value and type(getattr(msg, slot)) is type(value), slot
    assert msg._data == [] and msg._check_fields is True


@pytest.mark.parametrize('slot, bad', [('_flag', 2), ('_short', 'abcd'), ('_text', 'a\0b')])
def test_slot_program_hands_values_it_does_not_build_to_the_type_support(slot, bad):
    """A bool byte other than 0 or 1, a string over its bound or with an inner NUL: the program
    gives up and the type support decides (this class has none: the codec's path, None)."""
    values = [bad if s == slot else value for s, _, _, value in _ALL_KINDS]
    assert _all_kinds_decode(_all_kinds_cdr(True, values)) is None


def _encoded_both_ways(msg, descriptor):
    plan = plans.short_plan(type(msg))
    args = (msg, plan.slots, plan.slot, b'', b'demo', descriptor, plan.suffix_size)
    return (_native.encode_descriptor(*args, plans.compiled(type(msg)).program),
            _native.encode_descriptor(*args))


@pytest.mark.parametrize('seed', range(20))
def test_slot_program_writes_the_bytes_the_type_support_writes(seed):
    messages, rng = _random_messages(seed)
    for msg in messages:
        descriptor = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 80)))
        by_program, by_support = _encoded_both_ways(msg, descriptor)
        assert type(by_program) is bytearray and by_program == by_support
        assert codec.decode(by_program, type(msg)).msg == \
            codec.decode(by_support, type(msg)).msg


@pytest.mark.parametrize('field, value', [
    ('height', 2 ** 32 + 5),     # out of range: the generated code truncates it
    ('height', True),            # not exactly an int
    ('encoding', 'a\0b'),        # an inner NUL: the generated code cuts the string there
    ('encoding', '\udc80'),      # not encodable as UTF-8
])
def test_slot_program_leaves_values_it_does_not_write_exactly_to_the_type_support(field, value):
    image = Image(encoding='mono8')
    image._check_fields = False  # values the setters would refuse
    setattr(image, field, value)
    plan = plans.short_plan(Image)
    args = (image, plan.slots, plan.slot, b'', b'demo', b'd', plan.suffix_size)
    assert _native.encode_descriptor(*args, plans.compiled(Image).program) == \
        _native.encode_descriptor(*args)  # both the type support's answer (bytes or None)


def test_slot_program_writes_every_kind():
    msg = _AllKinds()
    for slot, _, _, value in _ALL_KINDS:
        setattr(msg, slot, value)
    msg._data = b''
    program = _all_kinds_program()
    out = _native.encode_descriptor(msg, _AllKinds.__slots__, '_data', b'', b'demo', b'abc', 0,
                                    program)
    expected = _all_kinds_cdr(struct.pack('=H', 1) == b'\x01\x00',
                              [value for _, _, _, value in _ALL_KINDS])
    assert out == expected
    msg._short = 'abcd'  # over its bound: the type support's path (this class has none)
    assert _native.encode_descriptor(msg, _AllKinds.__slots__, '_data', b'', b'demo', b'abc', 0,
                                     program) is None


# --- slot programs: CPU bytes deserialized -----------------------------------------------------

_PROGRAM_PACKAGES = ('std_msgs', 'geometry_msgs', 'sensor_msgs', 'builtin_interfaces', 'nav_msgs',
                     'visualization_msgs', 'test_msgs', 'diagnostic_msgs', 'rcl_interfaces',
                     'lifecycle_msgs', 'rosgraph_msgs', 'type_description_interfaces')


def _types_with_programs():
    import importlib
    found = []
    for package in _PROGRAM_PACKAGES:
        module = importlib.import_module(package + '.msg')
        for name in sorted(dir(module)):
            cls = getattr(module, name)
            if isinstance(cls, type) and hasattr(cls, 'SLOT_TYPES') and \
                    codec.program_of(cls) is not None:
                found.append(cls)
    return found


def _random_fill(msg, program, rng):
    """Random values of every field the program names, of its kind's Python type and range."""
    ranges = {plans.P_INT8: (-2 ** 7, 2 ** 7), plans.P_UINT8: (0, 2 ** 8),
              plans.P_INT16: (-2 ** 15, 2 ** 15), plans.P_UINT16: (0, 2 ** 16),
              plans.P_INT32: (-2 ** 31, 2 ** 31), plans.P_UINT32: (0, 2 ** 32),
              plans.P_INT64: (-2 ** 63, 2 ** 63), plans.P_UINT64: (0, 2 ** 64)}
    for slot, kind, arg in program[2]:
        if kind == plans.P_BOOL:
            value = rng.random() < 0.5
        elif kind in ranges:
            value = rng.randrange(*ranges[kind])
        elif kind == plans.P_FLOAT32:
            value = struct.unpack('f', struct.pack('f', rng.uniform(-1e30, 1e30)))[0]
        elif kind == plans.P_FLOAT64:
            value = rng.choice([rng.uniform(-1e300, 1e300), 0.0, -0.0, float('inf')])
        elif kind == plans.P_STRING:
            text = rng.choice(['', 'frame', 'grüße 日本', '\U0001F600', 'y' * 70])
            value = text if arg < 0 else text[:arg]
            while len(value.encode()) > arg >= 0:
                value = value[:-1]
        elif kind == plans.P_MESSAGE:
            value = getattr(msg, slot)
            _random_fill(value, arg, rng)
        else:  # the payload
            value = array.array('B', bytes(rng.randrange(256)
                                           for _ in range(rng.randrange(0, 40))))
        setattr(msg, slot, value)


@pytest.mark.parametrize('msg_type', _types_with_programs(), ids=lambda t: t.__name__)
def test_deserialize_builds_what_deserialize_message_builds(msg_type):
    import random
    rng = random.Random(msg_type.__name__)
    program = codec.program_of(msg_type)
    for _ in range(5):
        msg = msg_type()
        _random_fill(msg, program, rng)
        raw = serialize_message(msg)
        ours, rclpys = codec.deserialize(raw, msg_type), deserialize_message(raw, msg_type)
        assert _native.deserialize(raw, program) is not None  # the program built it
        assert ours == rclpys == msg
        assert _slot_values(ours) == _slot_values(rclpys)


def test_deserialize_builds_a_payload_past_the_c_deserialize_limit():
    image = Image(height=1, width=300_000, encoding='mono8', step=300_000,
                  data=bytes(range(256)) * 1172)
    raw = serialize_message(image)
    ours = _native.deserialize(raw, codec.program_of(Image))
    assert ours == deserialize_message(raw, Image)
    assert type(ours.data) is array.array and ours.data.tobytes() == bytes(image.data)


def test_deserialize_leaves_malformed_bytes_to_rclpy():
    raw = serialize_message(String(data='hello'))
    program = codec.program_of(String)
    assert _native.deserialize(raw[:-3], program) is None     # the string runs past the end
    assert _native.deserialize(b'\x00\x07' + raw[2:], program) is None  # not XCDR1
    assert _native.deserialize(raw + b'\0\0\0', program) == String(data='hello')  # padding
    with pytest.raises(Exception):
        codec.deserialize(raw[:-3], String)  # rclpy's own error


@pytest.mark.parametrize('msg_type', _types_with_programs(), ids=lambda t: t.__name__)
def test_serialize_writes_what_encode_writes(msg_type):
    """The CDR written from the slots: codec.encode's bytes (serialize_message's, with zero
    padding), and what deserialize_message reads back."""
    import random
    rng = random.Random('serialize ' + msg_type.__name__)
    program = codec.program_of(msg_type)
    for _ in range(5):
        msg = msg_type()
        _random_fill(msg, program, rng)
        out = _native.serialize(msg, program)
        assert type(out) is bytearray and out == codec.encode(msg)
        assert deserialize_message(bytes(out), msg_type) == msg


@pytest.mark.parametrize('payload', [b'abc', bytearray(b'abc'), array.array('B', b'abc'),
                                     memoryview(b'xabc')[1:], numpy.frombuffer(b'abc', 'u1')])
def test_serialize_writes_any_buffer_as_the_payload(payload):
    image = Image(encoding='mono8')
    image._data = payload  # what the generated conversion copies through the buffer protocol
    assert _native.serialize(image, codec.program_of(Image)) == codec.encode(
        Image(encoding='mono8', data=b'abc'))


def test_serialize_leaves_what_it_does_not_write_exactly_to_the_type_support():
    program = codec.program_of(Image)
    image = Image(encoding='mono8')
    image._data = [1, 2, 3]  # a list of ints: the generated conversion iterates it
    assert _native.serialize(image, program) is None
    image = Image(encoding='mono8')
    image._height = 2 ** 32  # out of range: the generated conversion truncates it
    assert _native.serialize(image, program) is None
