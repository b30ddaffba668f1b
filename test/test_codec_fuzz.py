"""Property tests of rosidl_buffer_py.codec: random messages round-trip, and arbitrary or mutated
bytes only ever decode or raise CodecError (never another exception, never a bad read).

A legacy decode that succeeds is also checked against rclpy's deserialize_message.
"""
import struct

from hypothesis import HealthCheck, given, settings, strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import MultiArrayDimension, UInt8MultiArray

from rosidl_buffer_py import MAX_DESCRIPTOR_SIZE
from rosidl_buffer_py.codec import CodecError, DESCRIPTOR_MARKER, decode, encode

from test_codec import REFERENCE, masked

FUZZ = settings(deadline=None, max_examples=300,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
MSG_TYPES = [Image, CompressedImage, UInt8MultiArray, PointCloud2]

# ROS strings hold no NUL; surrogates cannot be UTF-8 encoded
characters = st.characters(min_codepoint=1, exclude_categories=('Cs',))
texts = st.text(characters, max_size=12)
uint32s = st.integers(0, 2**32 - 1)
payloads = st.binary(max_size=64)


@st.composite
def images(draw):
    msg = Image(height=draw(uint32s), width=draw(uint32s), encoding=draw(texts),
                is_bigendian=draw(st.integers(0, 255)), step=draw(uint32s))
    msg.header.frame_id = draw(texts)
    msg.header.stamp.sec = draw(st.integers(-2**31, 2**31 - 1))
    msg.header.stamp.nanosec = draw(uint32s)
    msg.data = draw(payloads)
    return msg


@st.composite
def compressed_images(draw):
    msg = CompressedImage(format=draw(texts))
    msg.header.frame_id = draw(texts)
    msg.data = draw(payloads)
    return msg


@st.composite
def multiarrays(draw):
    msg = UInt8MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=label, size=draw(uint32s), stride=draw(uint32s))
                      for label in draw(st.lists(texts, max_size=3))]
    msg.layout.data_offset = draw(uint32s)
    msg.data = draw(payloads)
    return msg


@st.composite
def pointclouds(draw):
    msg = PointCloud2(height=draw(uint32s), width=draw(uint32s),
                      is_bigendian=draw(st.booleans()), point_step=draw(uint32s),
                      row_step=draw(uint32s), is_dense=draw(st.booleans()))
    msg.header.frame_id = draw(texts)
    msg.fields = [PointField(name=name, offset=draw(uint32s), datatype=draw(st.integers(0, 255)),
                             count=draw(uint32s))
                  for name in draw(st.lists(texts, max_size=3))]
    msg.data = draw(payloads)
    return msg


messages = st.one_of(images(), compressed_images(), multiarrays(), pointclouds())
backends = st.text(characters, min_size=1, max_size=10)
descriptors = st.one_of(st.none(), st.tuples(backends, st.binary(max_size=40)))


def decode_or_codec_error(raw, msg_type):
    """Decode; only CodecError may escape. Cross-check successful legacy decodes with rclpy."""
    try:
        decoded = decode(raw, msg_type)
    except CodecError:
        return None
    if decoded.backend_type is None:
        assert decoded.msg == deserialize_message(bytes(raw), msg_type)
    else:
        assert len(decoded.descriptor) <= MAX_DESCRIPTOR_SIZE
        assert len(decoded.msg.data) == 0
    return decoded


@FUZZ
@given(messages, descriptors)
def test_round_trip(msg, descriptor):
    enc = encode(msg, descriptor)
    ref = REFERENCE[type(msg)](msg, descriptor=descriptor)
    assert bytes(enc) == bytes(ref.out)
    decoded = decode(enc, type(msg))
    if descriptor is None:
        assert bytes(enc) == masked(serialize_message(msg), ref.pads)
        assert decoded.msg == msg and decoded.backend_type is None
    else:
        assert (decoded.backend_type, decoded.descriptor) == descriptor
        msg.data = b''
        assert decoded.msg == msg


@FUZZ
@given(st.sampled_from(MSG_TYPES), st.binary(max_size=200))
def test_arbitrary_bytes(msg_type, raw):
    decode_or_codec_error(raw, msg_type)


@FUZZ
@given(st.sampled_from(MSG_TYPES), st.sampled_from([b'\x00\x01\x00\x00', b'\x00\x00\x00\x00']),
       st.lists(st.one_of(st.integers(0, 255).map(lambda b: bytes([b])),
                          st.sampled_from([0, 1, 2, 5, 0xFFFFFFFF, 0x7FFFFFFF, 4097])
                          .map(lambda n: struct.pack('<I', n))),
                max_size=40))
def test_arbitrary_words_behind_a_valid_header(msg_type, header, chunks):
    decode_or_codec_error(header + b''.join(chunks), msg_type)


mutations = st.lists(st.tuples(
    st.sampled_from(['byte', 'word', 'truncate', 'insert', 'delete']),
    st.integers(0, 10_000),
    st.sampled_from([0, 1, 2, 3, 4, 0xFF, 0x7FFFFFFF, 0xFFFFFFFF, DESCRIPTOR_MARKER - 1, 4096,
                     4097, 2**16])),
    min_size=1, max_size=4)


def _mutate(raw: bytearray, edits) -> None:
    """Apply ``mutations``' edits to an encoding, in place."""
    for kind, where, value in edits:
        at = where % (len(raw) + 1)
        if kind == 'byte' and at < len(raw):
            raw[at] = value & 0xFF
        elif kind == 'word':
            at &= ~3
            raw[at:at + 4] = struct.pack('<I', value)
        elif kind == 'truncate':
            del raw[at:]
        elif kind == 'insert':
            raw[at:at] = bytes([value & 0xFF])
        elif kind == 'delete':
            del raw[at:at + 1]


@FUZZ
@given(messages, descriptors, mutations, st.booleans())
def test_mutated_encodings(msg, descriptor, edits, as_memoryview):
    raw = bytearray(encode(msg, descriptor))
    _mutate(raw, edits)
    decode_or_codec_error(memoryview(raw) if as_memoryview else bytes(raw), type(msg))


# --- the general path: nested payloads, payloads in sequences of messages ----------------------

def _general_messages():
    from stereo_msgs.msg import DisparityImage
    from test_msgs.msg import MultiNested, UnboundedSequences
    from test_codec_general import messages_of
    return st.one_of(messages_of(DisparityImage), messages_of(UnboundedSequences),
                     messages_of(MultiNested))


@FUZZ
@given(_general_messages(), st.randoms(use_true_random=False), mutations)
def test_mutated_general_encodings(msg, rnd, edits):
    from rosidl_buffer_py.codec import FieldDescriptor, field_paths
    described = {path: (rnd.choice(['demo', 'gpu', 'x' * 9]), rnd.randbytes(rnd.randrange(9)))
                 for path in field_paths(msg) if rnd.random() < 0.5}
    raw = bytearray(encode(msg, described))
    decoded = decode(raw, type(msg))
    assert decoded.descriptors == {p: FieldDescriptor(*d) for p, d in described.items()}
    _mutate(raw, edits)
    try:
        decoded = decode(bytes(raw), type(msg))
    except CodecError:
        return
    for described in decoded.descriptors.values():
        assert len(described.descriptor) <= MAX_DESCRIPTOR_SIZE
    if not decoded.descriptors:
        # compared as bytes (the codec's, zero padding): a mutated float may be NaN, which
        # compares unequal to itself field by field
        assert encode(decoded.msg) == encode(deserialize_message(bytes(raw), type(msg)))
