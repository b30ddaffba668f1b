"""Buffer: the public API, zero-copy host access and the uint8[] setter extension."""
import array
import gc

import numpy
import pytest
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import UInt8MultiArray

import rosidl_buffer_py
from rosidl_buffer_py import Buffer, enable_buffer_fields


def test_api_of_a_host_buffer():
    storage = bytearray(b'\x01\x02\x03\x04\x05')
    buf = Buffer('demo', storage)
    assert buf.backend_type == 'demo'
    assert buf.is_cpu is False
    assert Buffer('cpu', b'').is_cpu is True
    assert len(buf) == 5
    assert buf.to_bytes() == b'\x01\x02\x03\x04\x05'
    assert buf.host_addressable and not buf.readonly


def test_repr_names_backend_and_length_never_the_payload():
    buf = Buffer('demo', bytes(range(200)) * 100)
    text = repr(buf)
    assert "'demo'" in text and 'nbytes=20000' in text
    assert len(text) < 100


def test_memoryview_and_numpy_alias_the_memory_without_copy():
    storage = bytearray(16)
    buf = Buffer('demo', storage)
    view = memoryview(buf)
    assert view.nbytes == 16 and view.format == 'B' and not view.readonly
    arr = numpy.asarray(buf)
    assert arr.dtype == numpy.uint8 and arr.shape == (16,)
    arr[3] = 77
    view[4] = 88
    assert storage[3] == 77 and storage[4] == 88
    assert numpy.shares_memory(arr, numpy.frombuffer(storage, dtype=numpy.uint8))


def test_read_only_memory_stays_read_only():
    buf = Buffer('demo', b'abc')
    assert buf.readonly
    assert memoryview(buf).readonly
    assert not numpy.asarray(buf).flags.writeable
    with pytest.raises(TypeError, match='read-only'):
        memoryview(buf)[0:1] = b'x'


def test_multidimensional_host_memory_is_exported_as_flat_bytes():
    image = numpy.arange(24, dtype=numpy.uint8).reshape(2, 4, 3)
    buf = Buffer('demo', image)
    assert len(buf) == 24
    assert bytes(memoryview(buf)) == image.tobytes()
    with pytest.raises(ValueError, match='C-contiguous'):
        Buffer('demo', image[:, ::2])


def test_dlpack_is_zero_copy_and_on_the_host():
    storage = bytearray(range(10))
    buf = Buffer('demo', storage)
    assert buf.__dlpack_device__() == (1, 0)
    arr = numpy.from_dlpack(buf)
    assert arr.tolist() == list(range(10))
    storage[0] = 200
    assert arr[0] == 200
    ro = numpy.from_dlpack(Buffer('demo', bytes(3)))
    assert not ro.flags.writeable
    assert numpy.from_dlpack(Buffer('demo', b'')).shape == (0,)
    with pytest.raises(BufferError):
        buf.__dlpack__(dl_device=(2, 0))


def test_views_keep_the_buffer_and_its_keepalive_alive():
    released = []

    class Hold:
        def __del__(self):
            released.append(True)

    buf = Buffer('demo', bytearray(8), keepalive=Hold())
    arr = numpy.asarray(buf)
    view = memoryview(buf)
    del buf
    gc.collect()
    assert not released
    del arr
    gc.collect()
    assert not released
    view.release()
    del view
    gc.collect()
    assert released == [True]


def test_buffer_without_host_memory():
    buf = Buffer('gpu', size=1024)
    assert len(buf) == 1024 and not buf.host_addressable
    with pytest.raises(BufferError, match='no host-addressable memory'):
        memoryview(buf)
    with pytest.raises(BufferError):
        buf.__dlpack_device__()
    with pytest.raises(NotImplementedError, match="'gpu'"):
        buf.to_bytes()


@pytest.mark.parametrize('kwargs, error', [
    ({'backend_type': ''}, TypeError),
    ({'backend_type': 3}, TypeError),
    ({'backend_type': 'x'}, ValueError),  # neither host memory nor size
    ({'backend_type': 'x', 'size': -1}, ValueError),
    ({'backend_type': 'x', 'host': b'ab', 'size': 3}, ValueError),
])
def test_bad_construction_is_refused(kwargs, error):
    with pytest.raises(error):
        Buffer(**kwargs)


def test_setter_stores_a_buffer_as_is():
    msg = Image()
    buf = Buffer('demo', bytearray(6))
    msg.data = buf
    assert msg.data is buf
    msg.data = [1, 2, 3]
    assert msg.data == array.array('B', [1, 2, 3])


@pytest.mark.parametrize('check_fields', [False, True])
@pytest.mark.parametrize('value', [
    array.array('B', [1, 2]), b'\x00\xff', bytearray(b'ab'), [0, 255], (1, 2), range(3),
    numpy.arange(4, dtype=numpy.uint8), [256], [-1], 'abc', array.array('H', [1]), None, 3.5,
])
def test_setter_behaves_as_before_for_every_other_value(value, check_fields):
    """The extended setter and the stock one agree on the stored value or the exception."""
    stock_setter = Image.data.fset.__wrapped__

    def outcome(setter):
        msg = Image(check_fields=check_fields)
        try:
            setter(msg, value)
        except Exception as exc:  # compare the kind of failure
            return ('raised', type(exc))
        return ('stored', type(msg._data), msg._data.typecode, msg._data.tolist(),
                msg._data is value)

    assert outcome(Image.data.fset) == outcome(stock_setter)


def test_common_types_enabled_on_import_and_others_on_request():
    assert rosidl_buffer_py.buffer_fields(Image) == ('data',)
    buf = Buffer('demo', bytearray(2))
    c = CompressedImage()
    c.data = buf
    assert c.data is buf
    assert enable_buffer_fields(UInt8MultiArray) == ('data',)
    assert enable_buffer_fields(UInt8MultiArray) == ('data',)  # idempotent
    u = UInt8MultiArray()
    u.data = buf
    assert u.data is buf
    with pytest.raises(TypeError, match='not a generated ROS message'):
        enable_buffer_fields(int)


def test_every_message_type_is_enabled_after_import_even_imported_later():
    """A fresh interpreter: types imported before and after rosidl_buffer_py store Buffers."""
    import subprocess
    import sys
    code = '''
import array
from std_msgs.msg import UInt8MultiArray          # imported before
import rosidl_buffer_py
from sensor_msgs.msg import PointCloud2           # imported after
from std_msgs.msg import String                   # no uint8[] field: untouched
buf = rosidl_buffer_py.Buffer('demo', bytearray(4))
for cls in (UInt8MultiArray, PointCloud2):
    msg = cls()
    msg.data = buf
    assert msg.data is buf, cls
    msg.data = [1, 2]
    assert msg.data == array.array('B', [1, 2]), cls
assert not hasattr(String, '_rosidl_buffer_py_fields')
s = String(data='x')
assert s.data == 'x'
print('ok')
'''
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == 'ok', out.stderr
