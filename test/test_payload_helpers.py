"""Tests of rosidl_buffer_py.point_cloud and rosidl_buffer_py.compressed_image.

Oracles: the stock message (``serialize_message`` / ``deserialize_message``) and numpy's own
structured arrays built independently from the same values.
"""
import array
import gc

import numpy
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CompressedImage, PointCloud2, PointField

from rosidl_buffer_py import Buffer, codec, registry
from rosidl_buffer_py.compressed_image import compressed_data, to_compressed_msg
from rosidl_buffer_py.point_cloud import (
    allocate_point_cloud_msg, point_cloud_from_input_msg, point_cloud_from_output_msg,
    point_dtype)

XYZI = numpy.dtype([('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('intensity', 'f4')])
RING = numpy.dtype({'names': ['x', 'ring', 'normal', 't'],
                    'formats': ['f8', 'u2', ('f4', (3,)), 'i1'],
                    'offsets': [0, 8, 12, 24], 'itemsize': 32})


@pytest.fixture
def demo():
    import demo_buffer_backend
    demo_buffer_backend.shutdown()
    yield registry.get_backend('demo')
    gc.collect()
    demo_buffer_backend.shutdown()


def random_points(dtype, shape, seed=0):
    rng = numpy.random.default_rng(seed)
    raw = rng.integers(0, 255, size=int(numpy.prod(shape)) * dtype.itemsize, dtype=numpy.uint8)
    points = numpy.frombuffer(raw.tobytes(), dtype=dtype).reshape(shape).copy()
    for name in dtype.names:  # no NaN: comparisons must hold
        if points[name].dtype.kind == 'f':
            points[name] = rng.standard_normal(points[name].shape)
    return points


@pytest.mark.parametrize('dtype', [XYZI, RING], ids=['xyzi', 'ring'])
def test_allocate_fill_and_read_back_through_the_wire(dtype):
    msg = allocate_point_cloud_msg(3, 5, dtype, frame_id='lidar')
    assert msg.point_step == dtype.itemsize and msg.row_step == 5 * dtype.itemsize
    assert isinstance(msg.data, array.array) and len(msg.data) == 15 * dtype.itemsize
    points = random_points(dtype, (3, 5))
    out = point_cloud_from_output_msg(msg)
    assert out.shape == (3, 5) and numpy.shares_memory(out, numpy.frombuffer(msg.data, 'u1'))
    out[...] = points
    received = deserialize_message(serialize_message(msg), PointCloud2)
    assert received.header.frame_id == 'lidar' and point_dtype(received) == dtype
    copy = point_cloud_from_input_msg(received)
    view = point_cloud_from_input_msg(received, clone=False)
    assert not view.flags.writeable
    for name in dtype.names:
        numpy.testing.assert_array_equal(copy[name], points[name])
        numpy.testing.assert_array_equal(view[name], points[name])
    copy['x'][...] = 0
    numpy.testing.assert_array_equal(view['x'], points['x'])


def test_fields_written_by_hand_and_row_padding():
    msg = PointCloud2(height=2, width=2, point_step=12, row_step=30, is_bigendian=True)
    msg.fields = [PointField(name='a', offset=0, datatype=PointField.UINT16, count=1),
                  PointField(name='b', offset=4, datatype=PointField.FLOAT64, count=1)]
    raw = bytearray(60)
    for row in range(2):
        for col in range(2):
            at = row * 30 + col * 12
            raw[at:at + 2] = (100 * row + col).to_bytes(2, 'big')
            raw[at + 4:at + 12] = numpy.array([row - col / 2], '>f8').tobytes()
    msg.data = bytes(raw)
    points = point_cloud_from_input_msg(msg)
    assert points['a'].tolist() == [[0, 1], [100, 101]]
    assert points['b'].tolist() == [[0.0, -0.5], [1.0, 0.5]]
    assert points.dtype['b'].byteorder in ('=', '<' if numpy.little_endian else '>')


@pytest.mark.parametrize('change,match', [
    (lambda m: setattr(m.fields[0], 'datatype', 9), 'datatype 9'),
    (lambda m: setattr(m.fields[0], 'offset', 14), 'does not fit in point_step'),
    (lambda m: setattr(m, 'row_step', 1), 'row_step 1 is smaller'),
    (lambda m: setattr(m, 'height', 7), 'bytes are needed'),
])
def test_inconsistent_clouds_are_value_errors(change, match):
    msg = allocate_point_cloud_msg(2, 2, XYZI)
    change(msg)
    with pytest.raises(ValueError, match=match):
        point_cloud_from_input_msg(msg)


def test_non_point_field_types_are_refused():
    for dtype in (numpy.dtype('f4'), numpy.dtype([('c', 'c16')]),
                  numpy.dtype([('m', 'f4', (2, 2))]), numpy.dtype([('x', '>f4' if
                                                                     numpy.little_endian
                                                                     else '<f4')])):
        with pytest.raises(ValueError):
            allocate_point_cloud_msg(1, 1, dtype)
    with pytest.raises(TypeError, match='expected a sensor_msgs.msg.PointCloud2'):
        point_cloud_from_output_msg(CompressedImage())


def test_point_cloud_in_demo_shared_memory_is_filled_in_place(demo):
    from demo_buffer_backend import DemoBuffer
    msg = allocate_point_cloud_msg(1, 8, XYZI, 'demo')
    assert isinstance(msg.data, DemoBuffer)
    points = random_points(XYZI, (1, 8), seed=3)
    out = point_cloud_from_output_msg(msg)
    out[...] = points
    assert numpy.shares_memory(out, numpy.asarray(msg.data))
    assert codec.encode(msg) == codec.encode(deserialize_message(
        bytes(codec.encode(msg)), PointCloud2))
    numpy.testing.assert_array_equal(point_cloud_from_input_msg(msg, clone=False), out)
    del out


def test_compressed_bytes_are_a_read_only_view_without_copy():
    msg = to_compressed_msg(b'\xff\xd8jpeg bytes\xff\xd9', 'jpeg', frame_id='cam')
    assert msg.format == 'jpeg' and msg.header.frame_id == 'cam'
    assert isinstance(msg.data, array.array)
    view = compressed_data(msg)
    assert view.readonly and bytes(view) == b'\xff\xd8jpeg bytes\xff\xd9'
    assert numpy.shares_memory(numpy.frombuffer(view, 'u1'), numpy.frombuffer(msg.data, 'u1'))
    assert deserialize_message(serialize_message(msg), CompressedImage) == msg
    buffer = Buffer('vendor', bytearray(b'png!'))
    msg.data = buffer
    assert bytes(compressed_data(msg)) == b'png!'


def test_compressed_bytes_of_a_device_buffer_are_downloaded():
    class Device(Buffer):
        def __init__(self):
            super().__init__('gpu', size=3)

        def to_bytes(self):
            return b'abc'
    msg = CompressedImage()
    msg.data = Device()
    assert bytes(compressed_data(msg)) == b'abc'
    with pytest.raises(TypeError, match='expected a sensor_msgs.msg.CompressedImage'):
        compressed_data(PointCloud2())


def test_compressed_message_in_demo_memory(demo):
    from demo_buffer_backend import DemoBuffer
    msg = to_compressed_msg(bytearray(range(200)), 'png', 'demo')
    assert isinstance(msg.data, DemoBuffer)
    assert bytes(compressed_data(msg)) == bytes(range(200))
    expected = CompressedImage(format='png', data=bytes(range(200)))
    assert codec.encode(msg) == codec.encode(expected)
