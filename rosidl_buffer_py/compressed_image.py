"""The compressed bytes of ``sensor_msgs/CompressedImage``, over CPU or buffer storage.

- :func:`compressed_data`: the bytes of a message as a read-only memoryview (no copy when the
  storage is host memory: an ``array.array('B')`` or a host-addressable Buffer);
- :func:`to_compressed_msg`: a new message holding given compressed bytes in the chosen backend
  (one copy).

Decoding the image (JPEG, PNG...) is left to the caller's codec library: both PIL's
``Image.open(io.BytesIO(view))`` and OpenCV's ``cv2.imdecode(numpy.frombuffer(view, 'u1'), ...)``
take the view as it is.
"""
from sensor_msgs.msg import CompressedImage

from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.image import _allocate_storage, _host_memory
from rosidl_buffer_py.message_support import enable_buffer_fields

__all__ = ['compressed_data', 'to_compressed_msg']

enable_buffer_fields(CompressedImage)


def compressed_data(msg: CompressedImage) -> memoryview:
    """The compressed bytes of ``msg``: a read-only flat memoryview of ``msg.data`` itself (no
    copy), or of ``Buffer.to_bytes()`` when the Buffer's memory is not host-addressable.

    The view keeps the storage alive; while it exists an ``array.array`` cannot be resized.
    """
    purpose = 'compressed_data'
    if not isinstance(msg, CompressedImage):
        raise TypeError(f'{purpose}: expected a sensor_msgs.msg.CompressedImage, got '
                        f'{type(msg).__name__}')
    data = msg.data
    if isinstance(data, Buffer) and not data.host_addressable:
        return memoryview(data.to_bytes())
    return _host_memory(msg, writable=False, purpose=purpose).toreadonly()


def to_compressed_msg(data, format: str, backend: str = CPU_BACKEND, *,  # noqa: A002
                      frame_id: str = '') -> CompressedImage:
    """A new CompressedImage holding a copy of ``data`` (bytes-like) in ``backend``'s memory
    (``"cpu"``: an ``array.array('B')``; another name: a Buffer from that backend's
    ``allocate()``, ready to be sent as a descriptor).

    :param format: The message's ``format`` (``"jpeg"``, ``"png"``, ``"rgb8; jpeg compressed
        bgr8"``...).
    :raises ValueError: a backend that is not installed or cannot allocate.
    """
    view = memoryview(data).cast('B')
    msg = CompressedImage(format=format)
    msg.header.frame_id = frame_id
    storage = _allocate_storage(view.nbytes, backend)
    memoryview(storage).cast('B')[:] = view
    msg.data = storage
    return msg
