"""numpy conversions of sensor_msgs/Image: allocate, writable view, readable view/copy, copy-in."""
import array
import gc
import os
import struct
import sys
from typing import Optional

import numpy
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image

from rosidl_buffer_py import Buffer, BufferBackend, registry
from rosidl_buffer_py.image import (
    allocate_image_msg, encoding_info, from_input_msg, from_output_msg, to_msg)

HOST_BIG = sys.byteorder == 'big'

# encoding -> (numpy dtype, channels)
NAMED = {
    'mono8': ('u1', 1), 'mono16': ('u2', 1),
    'rgb8': ('u1', 3), 'bgr8': ('u1', 3), 'rgba8': ('u1', 4), 'bgra8': ('u1', 4),
    'rgb16': ('u2', 3), 'bgr16': ('u2', 3), 'rgba16': ('u2', 4), 'bgra16': ('u2', 4),
    'yuv422': ('u1', 2), 'yuv422_yuy2': ('u1', 2), 'uyvy': ('u1', 2), 'yuyv': ('u1', 2),
    **{f'bayer_{p}8': ('u1', 1) for p in ('rggb', 'bggr', 'gbrg', 'grbg')},
    **{f'bayer_{p}16': ('u2', 1) for p in ('rggb', 'bggr', 'gbrg', 'grbg')},
}
DEPTHS = {'8U': 'u1', '8S': 'i1', '16U': 'u2', '16S': 'i2', '32S': 'i4', '32F': 'f4',
          '64F': 'f8'}
GENERIC = {f'{d}C{c}': (t, c) for d, t in DEPTHS.items() for c in (1, 2, 3, 4)}
ALL_ENCODINGS = {**NAMED, **GENERIC}


def random_image(shape, dtype, seed=0) -> numpy.ndarray:
    """Random pixels covering every byte (floats from random bits, NaNs excluded)."""
    rng = numpy.random.default_rng(seed)
    dtype = numpy.dtype(dtype)
    if dtype.kind == 'f':
        return rng.standard_normal(shape).astype(dtype) * 1000
    info = numpy.iinfo(dtype)
    return rng.integers(info.min, info.max, size=shape, dtype=dtype, endpoint=True)


def expected_shape(h, w, channels):
    return (h, w) if channels == 1 else (h, w, channels)


def storage_bytes(msg) -> bytes:
    return bytes(memoryview(msg.data))


class BytearrayBackend(BufferBackend):
    """A real backend whose memory is a bytearray (stands in for shared memory)."""

    def __init__(self):
        self.allocated = []

    def get_backend_type(self) -> str:
        return 'testmem'

    def create_descriptor_with_endpoint(self, buffer, endpoint_info) -> Optional[bytes]:
        return None

    def from_descriptor_with_endpoint(self, descriptor, endpoint_info):
        raise ValueError('testmem has no descriptors')

    def allocate(self, nbytes: int) -> Buffer:
        memory = bytearray(nbytes)
        self.allocated.append(memory)
        return Buffer('testmem', memory)


class NoAllocBackend(BytearrayBackend):
    """A backend that keeps BufferBackend's default allocate() (NotImplementedError)."""

    def get_backend_type(self) -> str:
        return 'noalloc'

    allocate = BufferBackend.allocate


@pytest.fixture
def testmem(monkeypatch):
    """Install the bytearray backend (and one that cannot allocate) in the registry's cache."""
    backend = BytearrayBackend()
    backends = dict(registry.get_installed_backends())
    backends.update(testmem=backend, noalloc=NoAllocBackend())
    monkeypatch.setattr(registry, '_backends', backends)
    return backend


# --- encodings ------------------------------------------------------------------------------

@pytest.mark.parametrize('encoding', sorted(ALL_ENCODINGS))
@pytest.mark.parametrize('backend', ['cpu', 'testmem'])
def test_every_encoding_round_trips(encoding, backend, testmem):
    dtype, channels = ALL_ENCODINGS[encoding]
    msg = allocate_image_msg(5, 7, encoding, backend)
    itemsize = numpy.dtype(dtype).itemsize
    assert (msg.height, msg.width, msg.encoding) == (5, 7, encoding)
    assert msg.step == 7 * channels * itemsize
    assert len(msg.data) == 5 * msg.step
    assert msg.is_bigendian == int(HOST_BIG and itemsize > 1)
    if backend == 'cpu':
        assert isinstance(msg.data, array.array) and msg.data.typecode == 'B'
        assert not any(msg.data)
    else:
        assert isinstance(msg.data, Buffer) and msg.data.backend_type == 'testmem'

    out = from_output_msg(msg)
    assert out.shape == expected_shape(5, 7, channels)
    assert out.dtype.newbyteorder('=') == numpy.dtype(dtype)
    assert out.flags.writeable
    pixels = random_image(out.shape, dtype, seed=len(encoding))
    out[...] = pixels

    copy = from_input_msg(msg)
    numpy.testing.assert_array_equal(copy, pixels)
    assert copy.dtype == numpy.dtype(dtype)
    view = from_input_msg(msg, clone=False)
    numpy.testing.assert_array_equal(view, pixels)
    # the bytes in the message are the pixels, row-major, in the declared byte order
    assert storage_bytes(msg) == pixels.astype(out.dtype).tobytes()


@pytest.mark.parametrize('bad', ['jpeg', 'MONO8', 'rgb', '8UC0', '32UC1', '16FC1', '8UC',
                                 'bayer_rggb32', ''])
def test_unsupported_encodings_are_named(bad):
    with pytest.raises(ValueError) as excinfo:
        allocate_image_msg(2, 2, bad)
    assert repr(bad) in str(excinfo.value) and 'mono8' in str(excinfo.value) \
        and '32F' in str(excinfo.value)
    msg = allocate_image_msg(2, 2, 'mono8')
    msg.encoding = bad
    for call in (from_output_msg, from_input_msg):
        with pytest.raises(ValueError, match='unsupported image encoding'):
            call(msg)
    with pytest.raises(ValueError, match='unsupported image encoding'):
        to_msg(msg, numpy.zeros((2, 2), numpy.uint8), encoding=bad)


def test_encoding_info():
    info = encoding_info('16SC3')
    assert (info.dtype, info.channels, info.bytes_per_pixel) == (numpy.dtype('i2'), 3, 6)
    assert encoding_info('8UC10').channels == 10


# --- step padding ---------------------------------------------------------------------------

@pytest.mark.parametrize('encoding,pad', [('rgb8', 5), ('mono16', 6), ('32FC3', 4),
                                          ('mono16', 1)])
def test_step_padding_is_skipped_and_untouched(encoding, pad):
    info = encoding_info(encoding)
    row = 4 * info.bytes_per_pixel
    msg = allocate_image_msg(3, 4, encoding, step=row + pad)
    assert msg.step == row + pad and len(msg.data) == 3 * (row + pad)
    memoryview(msg.data)[:] = b'\xab' * len(msg.data)  # sentinel everywhere

    out = from_output_msg(msg)
    assert out.strides[0] == row + pad
    pixels = random_image(out.shape, info.dtype, seed=pad)
    out[...] = pixels

    raw = storage_bytes(msg)
    for r in range(3):
        start = r * (row + pad)
        assert raw[start + row:start + row + pad] == b'\xab' * pad, f'padding of row {r} touched'
        assert raw[start:start + row] == pixels[r].astype(out.dtype).tobytes()

    copy = from_input_msg(msg)
    assert copy.flags.c_contiguous and copy.nbytes == 3 * row  # padding dropped
    numpy.testing.assert_array_equal(copy, pixels)
    numpy.testing.assert_array_equal(from_input_msg(msg, clone=False), pixels)


def test_step_too_small_is_rejected():
    with pytest.raises(ValueError, match=r'step 11 is smaller .* must be >= 12'):
        allocate_image_msg(2, 4, 'rgb8', step=11)
    msg = allocate_image_msg(2, 4, 'rgb8')
    msg.step = 11
    with pytest.raises(ValueError, match='msg.step 11 is smaller'):
        from_output_msg(msg)


def test_storage_shorter_than_height_times_step():
    msg = allocate_image_msg(3, 4, 'mono8')
    msg.data = array.array('B', bytes(11))
    for call in (from_output_msg, from_input_msg):
        with pytest.raises(ValueError, match=r'holds 11 bytes .* 12 bytes are needed'):
            call(msg)


# --- byte order -----------------------------------------------------------------------------

@pytest.mark.parametrize('is_bigendian,expected', [(1, 0x0102), (0, 0x0201)])
def test_is_bigendian_selects_the_byte_order(is_bigendian, expected):
    msg = allocate_image_msg(1, 2, 'mono16')
    msg.is_bigendian = is_bigendian
    memoryview(msg.data)[:] = b'\x01\x02\x01\x02'
    view = from_input_msg(msg, clone=False)
    assert view.dtype.byteorder in (('>',) if is_bigendian else ('<',)) + \
        (('=',) if bool(is_bigendian) == HOST_BIG else ())
    assert view.tolist() == [[expected, expected]]
    copy = from_input_msg(msg)
    assert copy.dtype.isnative and copy.tolist() == [[expected, expected]]
    out = from_output_msg(msg)
    out[0, 0] = 0x0a0b
    assert storage_bytes(msg)[:2] == (b'\x0a\x0b' if is_bigendian else b'\x0b\x0a')


def test_allocate_uses_host_order_for_multibyte_and_zero_for_bytes():
    assert allocate_image_msg(1, 1, 'mono8').is_bigendian == 0
    assert allocate_image_msg(1, 1, '64FC2').is_bigendian == int(HOST_BIG)


# --- aliasing and copies --------------------------------------------------------------------

def test_output_view_aliases_the_message_storage():
    msg = allocate_image_msg(2, 3, 'rgb8')
    out = from_output_msg(msg)
    out[1, 2] = (7, 8, 9)
    assert storage_bytes(msg)[15:18] == b'\x07\x08\x09'
    memoryview(msg.data)[0] = 200  # and the other way round
    assert out[0, 0, 0] == 200
    assert numpy.shares_memory(out, numpy.frombuffer(msg.data, numpy.uint8))


def test_views_pin_array_storage():
    msg = allocate_image_msg(2, 2, 'mono8')
    out = from_output_msg(msg)
    with pytest.raises(BufferError):
        msg.data.extend(b'\x00')  # a resize would leave the view dangling
    del out
    msg.data.extend(b'\x00')


def test_clone_is_independent():
    msg = allocate_image_msg(2, 3, 'mono16')
    from_output_msg(msg)[...] = 5
    copy = from_input_msg(msg)
    assert not numpy.shares_memory(copy, numpy.frombuffer(msg.data, numpy.uint8))
    copy[...] = 9
    assert (from_input_msg(msg) == 5).all()
    from_output_msg(msg)[...] = 1
    assert (copy == 9).all()


def test_input_view_of_array_storage_is_marked_read_only():
    msg = allocate_image_msg(2, 3, 'rgb8')
    view = from_input_msg(msg, clone=False)
    assert not view.flags.writeable
    with pytest.raises(ValueError):
        view[0, 0, 0] = 1
    memoryview(msg.data)[0] = 3
    assert view[0, 0, 0] == 3  # still a view, not a copy


def test_read_only_buffer_storage():
    msg = allocate_image_msg(2, 2, 'mono16')
    msg.data = Buffer('testmem', struct.pack('<4H', 1, 2, 3, 4))  # as received: read-only
    view = from_input_msg(msg, clone=False)
    assert view.tolist() == [[1, 2], [3, 4]]
    assert not view.flags.writeable
    with pytest.raises(ValueError):
        view.flags.writeable = True  # read-only at the memory level, not only by flag
    with pytest.raises(ValueError, match=r"read-only.*from_input_msg"):
        from_output_msg(msg)
    with pytest.raises(ValueError, match='read-only'):
        to_msg(msg, numpy.zeros((2, 2), numpy.uint16))
    copy = from_input_msg(msg)
    copy[0, 0] = 100
    assert copy.flags.writeable and view[0, 0] == 1


class DeviceBuffer(Buffer):
    """A Buffer without host memory whose backend can download it."""

    def __init__(self, payload: bytes):
        super().__init__('testdev', None, size=len(payload))
        self._payload = payload

    def to_bytes(self) -> bytes:
        return self._payload


def test_buffer_without_host_memory():
    msg = allocate_image_msg(1, 3, 'mono8')
    msg.data = DeviceBuffer(b'\x01\x02\x03')
    assert from_input_msg(msg).tolist() == [[1, 2, 3]]  # copied through to_bytes()
    for call in (from_output_msg, lambda m: from_input_msg(m, clone=False)):
        with pytest.raises(ValueError, match='not host-addressable'):
            call(msg)
    msg.data = Buffer('testdev', None, size=3)  # and no download either
    with pytest.raises(ValueError, match='cannot copy'):
        from_input_msg(msg)


# --- backends -------------------------------------------------------------------------------

def test_allocate_in_a_backend_writes_through_to_its_memory(testmem):
    msg = allocate_image_msg(2, 4, 'bgra8', 'testmem', step=20)
    assert isinstance(msg.data, Buffer) and not msg.data.readonly and len(msg.data) == 40
    (memory,) = testmem.allocated
    out = from_output_msg(msg)
    out[...] = numpy.arange(32, dtype=numpy.uint8).reshape(2, 4, 4)
    assert memory[:16] == bytes(range(16)) and memory[20:36] == bytes(range(16, 32))
    assert memory[16:20] == bytes(4) and memory[36:] == bytes(4)


def test_unknown_backend_lists_installed_ones(testmem):
    with pytest.raises(ValueError, match=r"'nosuch' is not installed; installed: .*cpu.*testmem"):
        allocate_image_msg(2, 2, 'mono8', 'nosuch')


def test_backend_that_cannot_allocate(testmem):
    with pytest.raises(ValueError, match=r"backend 'noalloc' cannot allocate"):
        allocate_image_msg(2, 2, 'mono8', 'noalloc')


def test_backend_returning_wrong_buffer(testmem, monkeypatch):
    monkeypatch.setattr(testmem, 'allocate', lambda n: Buffer('testmem', bytes(n)))
    with pytest.raises(ValueError, match='expected a writable Buffer of 4 bytes'):
        allocate_image_msg(2, 2, 'mono8', 'testmem')


# --- to_msg ---------------------------------------------------------------------------------

def cdr_image(height, width, encoding, is_bigendian, step, data):
    """Expected CDR (little endian) of an Image with a default header, and a mask of the bytes
    that are alignment padding (their value is unspecified)."""
    out, pad = bytearray(b'\x00\x01\x00\x00'), [False] * 4

    def put(raw, align=1):
        while (len(out) - 4) % align:
            out.append(0)
            pad.append(True)
        out.extend(raw)
        pad.extend([False] * len(raw))

    def string(s):
        put(struct.pack('<I', len(s) + 1), 4)
        put(s.encode() + b'\x00')

    put(struct.pack('<iI', 0, 0), 4)  # stamp
    string('')  # frame_id
    put(struct.pack('<II', height, width), 4)
    string(encoding)
    put(struct.pack('<B', is_bigendian))
    put(struct.pack('<I', step), 4)
    put(struct.pack('<I', len(data)), 4)
    put(data)
    return bytes(out), pad


def assert_serialized(msg, height, width, encoding, is_bigendian, step, data):
    got = serialize_message(msg)
    want, pad = cdr_image(height, width, encoding, is_bigendian, step, data)
    assert len(got) == len(want)
    assert bytes(g for g, p in zip(got, pad) if not p) == bytes(w for w, p in zip(want, pad)
                                                               if not p)


def test_to_msg_refreshes_metadata_and_serializes():
    msg = allocate_image_msg(1, 1, 'mono8')
    pixels = numpy.arange(2 * 3 * 3, dtype=numpy.uint8).reshape(2, 3, 3)
    to_msg(msg, pixels)
    assert (msg.height, msg.width, msg.step, msg.encoding, msg.is_bigendian) == \
        (2, 3, 9, 'rgb8', 0)
    assert isinstance(msg.data, array.array) and len(msg.data) == 18
    assert_serialized(msg, 2, 3, 'rgb8', 0, 9, pixels.tobytes())
    back = deserialize_message(serialize_message(msg), Image)
    numpy.testing.assert_array_equal(from_input_msg(back), pixels)


def test_to_msg_with_step_and_big_endian_source_serializes():
    msg = allocate_image_msg(2, 2, 'mono16')
    pixels = numpy.array([[1, 2], [3, 0x0102]], dtype='>u2')
    to_msg(msg, pixels, step=6)
    assert (msg.step, msg.encoding, msg.is_bigendian) == (6, 'mono16', 1)
    raw = storage_bytes(msg)
    assert raw[0:4] == b'\x00\x01\x00\x02' and raw[6:10] == b'\x00\x03\x01\x02'
    assert_serialized(msg, 2, 2, 'mono16', 1, 6, raw)
    numpy.testing.assert_array_equal(from_input_msg(msg), pixels)


@pytest.mark.parametrize('shape,dtype,encoding', [
    ((4, 5), 'u1', 'mono8'), ((4, 5, 3), 'u1', 'rgb8'), ((4, 5, 4), 'u1', 'rgba8'),
    ((4, 5), 'u2', 'mono16'), ((4, 5), 'f4', '32FC1'), ((4, 5, 1), 'u1', 'mono8'),
    ((4, 5, 2), 'f8', '64FC2'), ((4, 5, 3), 'u2', '16UC3'), ((4, 5), 'i2', '16SC1'),
])
def test_to_msg_infers_the_encoding(shape, dtype, encoding):
    msg = Image()  # no encoding yet, empty storage
    pixels = random_image(shape, dtype)
    to_msg(msg, pixels)
    assert msg.encoding == encoding and msg.height == 4 and msg.width == 5
    numpy.testing.assert_array_equal(from_input_msg(msg), pixels.reshape(
        expected_shape(4, 5, encoding_info(encoding).channels)))


def test_to_msg_keeps_a_compatible_encoding_or_takes_the_keyword():
    msg = allocate_image_msg(2, 2, 'bgr8')
    to_msg(msg, numpy.zeros((2, 2, 3), numpy.uint8))
    assert msg.encoding == 'bgr8'
    to_msg(msg, numpy.zeros((2, 2), numpy.uint16))  # bgr8 no longer fits: inferred
    assert msg.encoding == 'mono16'
    to_msg(msg, numpy.zeros((2, 2), numpy.uint16), encoding='bayer_rggb16')
    assert msg.encoding == 'bayer_rggb16'
    to_msg(msg, numpy.zeros((2, 2), numpy.uint16))
    assert msg.encoding == 'bayer_rggb16'


def test_to_msg_copies_any_source_layout_in_one_go():
    source = random_image((6, 8, 3), 'u1')
    strided = source[::2, ::-1]  # non-contiguous, negative strides
    msg = allocate_image_msg(3, 8, 'rgb8')
    before = msg.data
    to_msg(msg, strided)
    assert msg.data is before  # right size: written in place
    numpy.testing.assert_array_equal(from_input_msg(msg), strided)
    strided[...] = 0
    assert from_input_msg(msg).any()  # copied, not aliased


def test_to_msg_into_a_padded_view_of_itself():
    msg = allocate_image_msg(2, 3, 'mono8', step=4)
    out = from_output_msg(msg)
    out[...] = [[1, 2, 3], [4, 5, 6]]
    to_msg(msg, out[:, ::-1].copy(), step=4)
    assert from_input_msg(msg).tolist() == [[3, 2, 1], [6, 5, 4]]


@pytest.mark.parametrize('array_,kwargs,message', [
    (numpy.zeros((2, 2), numpy.float32), {'encoding': 'mono8'},
     r"'mono8' holds 1 channel\(s\) of uint8, but the array has dtype float32"),
    (numpy.zeros((2, 2, 3), numpy.uint8), {'encoding': 'rgba8'}, r"'rgba8' holds 4 channel"),
    (numpy.zeros((2, 2), numpy.int64), {}, r'no image encoding for an array of dtype int64'),
    (numpy.zeros((2, 2), numpy.complex64), {}, r'accepted dtypes: uint8'),
    (numpy.zeros(4, numpy.uint8), {}, r'shape \(height, width\) .* got shape \(4,\)'),
    (numpy.zeros((1, 2, 2, 3), numpy.uint8), {}, r'got shape \(1, 2, 2, 3\)'),
    (numpy.zeros((2, 2, 0), numpy.uint8), {}, r'got shape \(2, 2, 0\)'),
    (numpy.zeros((2, 3), numpy.uint8), {'step': 2}, r'step 2 is smaller'),
])
def test_to_msg_rejects_mismatches(array_, kwargs, message):
    msg = allocate_image_msg(2, 2, 'mono8')
    with pytest.raises(ValueError, match=message):
        to_msg(msg, array_, **kwargs)
    assert (msg.height, msg.width, msg.encoding, len(msg.data)) == (2, 2, 'mono8', 4)


def test_to_msg_rejects_non_arrays():
    with pytest.raises(TypeError, match='numpy.ndarray'):
        to_msg(Image(), [[1, 2]])


def test_to_msg_too_small_buffer_names_both_sizes(testmem):
    msg = allocate_image_msg(2, 2, 'rgb8', 'testmem')
    with pytest.raises(ValueError, match=r'holds 12 bytes but the array needs 27'):
        to_msg(msg, numpy.zeros((3, 3, 3), numpy.uint8))
    assert (msg.height, msg.width) == (2, 2)


def test_to_msg_into_a_larger_buffer_leaves_the_tail(testmem):
    msg = allocate_image_msg(2, 4, 'mono8', 'testmem')
    (memory,) = testmem.allocated
    memory[:] = b'\xee' * 8
    buffer = msg.data
    to_msg(msg, numpy.full((1, 3), 7, numpy.uint8))
    assert msg.data is buffer
    assert (msg.height, msg.width, msg.step) == (1, 3, 3)
    assert memory == b'\x07\x07\x07' + b'\xee' * 5
    assert from_input_msg(msg).tolist() == [[7, 7, 7]]


def test_to_msg_resizes_cpu_storage():
    msg = allocate_image_msg(1, 1, 'mono8')
    old = msg.data
    old_view = from_output_msg(msg)
    to_msg(msg, numpy.ones((4, 4), numpy.uint8))
    assert isinstance(msg.data, array.array) and len(msg.data) == 16 and msg.data is not old
    assert old_view[0, 0] == 0  # the old storage is left alone
    to_msg(msg, array=numpy.ones((1, 2), numpy.uint8))
    assert len(msg.data) == 2  # shrunk too: data is exactly height * step
    assert_serialized(msg, 1, 2, 'mono8', 0, 2, b'\x01\x01')


# --- the demo (shared-memory) backend -------------------------------------------------------

def _demo_mappings() -> set:
    with open('/proc/self/maps') as f:
        return {line for line in f if '/memfd:rbpy_demo' in line}


@pytest.fixture
def demo():
    """The registry's demo backend over a fresh process-wide pool; nothing left afterwards."""
    import demo_buffer_backend
    demo_buffer_backend.shutdown()
    gc.collect()
    before = _demo_mappings()  # an earlier test file's (one process under `colcon test`)
    backend = registry.get_backend('demo')
    yield backend
    gc.collect()
    demo_buffer_backend.shutdown()
    # its memory is memfds: none left open or mapped, nothing of ours in /dev/shm
    assert not _demo_mappings() - before
    assert not [n for n in os.listdir('/dev/shm')
                if n.startswith('rbpy_') and f'_{os.getpid()}_' in n]


@pytest.mark.parametrize('encoding', ['mono8', 'bgr8', 'mono16', 'rgba16', '32FC1', '64FC3'])
def test_demo_backend_allocates_shared_memory_to_fill_in_place(demo, encoding):
    from demo_buffer_backend import DemoBuffer
    info = encoding_info(encoding)
    msg = allocate_image_msg(6, 5, encoding, 'demo', step=5 * info.bytes_per_pixel + 3)
    assert isinstance(msg.data, DemoBuffer) and msg.data.in_shm and not msg.data.readonly
    assert len(msg.data) == 6 * msg.step
    out = from_output_msg(msg)
    pixels = random_image(out.shape, info.dtype, seed=7)
    out[...] = pixels
    assert numpy.shares_memory(out, numpy.asarray(msg.data))
    numpy.testing.assert_array_equal(from_input_msg(msg), pixels)
    numpy.testing.assert_array_equal(from_input_msg(msg, clone=False), pixels)
    del out


def test_demo_backend_received_buffer_is_a_read_only_view(demo):
    from rosidl_buffer_py import EndpointInfo, EndpointKind
    endpoint = EndpointInfo(b'\x22' * 16, '/image_test', EndpointKind.SUBSCRIPTION)
    assert demo.on_discovering_endpoint(
        endpoint, [], {'demo': demo.get_backend_metadata()})[0]
    sent = allocate_image_msg(4, 3, 'rgb8', 'demo')
    out = from_output_msg(sent)
    out[...] = numpy.arange(36, dtype=numpy.uint8).reshape(4, 3, 3)
    descriptor = demo.create_descriptor_with_endpoint(sent.data, endpoint)
    assert descriptor is not None

    received = Image(height=sent.height, width=sent.width, encoding=sent.encoding,
                     is_bigendian=sent.is_bigendian, step=sent.step)
    received.data = demo.from_descriptor_with_endpoint(descriptor, endpoint)
    assert received.data.readonly
    view = from_input_msg(received, clone=False)
    assert not view.flags.writeable
    numpy.testing.assert_array_equal(view, out)
    out[0, 0, 0] = 250  # same shared memory, no copy
    assert view[0, 0, 0] == 250
    with pytest.raises(ValueError, match='read-only'):
        from_output_msg(received)
    copy = from_input_msg(received)
    copy[...] = 0
    assert view[0, 0, 0] == 250
    del view, out


def test_a_message_that_is_not_an_image_is_a_type_error():
    from std_msgs.msg import String
    for call in (lambda: from_input_msg(String()), lambda: from_input_msg(String(), clone=False),
                 lambda: from_output_msg(String()),
                 lambda: to_msg(String(), numpy.zeros((2, 2), numpy.uint8))):
        with pytest.raises(TypeError, match='expected a sensor_msgs.msg.Image, got String'):
            call()
