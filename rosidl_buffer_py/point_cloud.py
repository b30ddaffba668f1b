"""numpy structured views of ``sensor_msgs/PointCloud2`` points, over CPU or buffer storage.

The operations of :mod:`rosidl_buffer_py.image`, for point clouds:

- :func:`allocate_point_cloud_msg`: the fields from a numpy structured dtype, ``data`` sized
  ``height * width`` points in the chosen backend;
- :func:`point_cloud_from_output_msg`: a writable ``(height, width)`` structured array over the
  message's own bytes (publisher side);
- :func:`point_cloud_from_input_msg`: an independent copy, or a read-only view (subscriber side);
- :func:`point_dtype`: the structured dtype a message's ``fields`` describe.

A point's fields sit at their ``offset`` within ``point_step`` bytes, rows are ``row_step``
bytes apart; the views are laid over the storage with those strides (no copy). ``count > 1``
gives a sub-array field. Multi-byte fields are read in the byte order ``is_bigendian`` names.
"""
import sys

import numpy
from sensor_msgs.msg import PointCloud2, PointField

from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.image import _allocate_storage, _host_memory
from rosidl_buffer_py.message_support import enable_buffer_fields

__all__ = [
    'allocate_point_cloud_msg',
    'point_cloud_from_input_msg',
    'point_cloud_from_output_msg',
    'point_dtype',
]

enable_buffer_fields(PointCloud2)

#: PointField datatype -> numpy type (native byte order), as sensor_msgs defines them.
_DATATYPES = {
    PointField.INT8: numpy.dtype(numpy.int8), PointField.UINT8: numpy.dtype(numpy.uint8),
    PointField.INT16: numpy.dtype(numpy.int16), PointField.UINT16: numpy.dtype(numpy.uint16),
    PointField.INT32: numpy.dtype(numpy.int32), PointField.UINT32: numpy.dtype(numpy.uint32),
    PointField.FLOAT32: numpy.dtype(numpy.float32),
    PointField.FLOAT64: numpy.dtype(numpy.float64),
}
_DATATYPE_OF = {dtype: code for code, dtype in _DATATYPES.items()}
_HOST_IS_BIG_ENDIAN = sys.byteorder == 'big'


def point_dtype(msg: PointCloud2) -> numpy.dtype:
    """The numpy structured dtype of one point of ``msg`` (itemsize ``point_step``).

    :raises ValueError: on an unknown datatype, a field past ``point_step`` or overlapping
        names.
    """
    order = '>' if msg.is_bigendian else '<'
    names, formats, offsets = [], [], []
    for field in msg.fields:
        base = _DATATYPES.get(field.datatype)
        if base is None:
            raise ValueError(f'PointCloud2 field {field.name!r} has datatype {field.datatype}; '
                             f'known: {sorted(_DATATYPES)}')
        base = base.newbyteorder(order)
        fmt = base if field.count == 1 else numpy.dtype((base, (field.count,)))
        if field.offset + fmt.itemsize > msg.point_step:
            raise ValueError(f'PointCloud2 field {field.name!r} (offset {field.offset}, '
                             f'{fmt.itemsize} bytes) does not fit in point_step '
                             f'{msg.point_step}')
        names.append(field.name)
        formats.append(fmt)
        offsets.append(field.offset)
    try:
        return numpy.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                            'itemsize': msg.point_step})
    except ValueError as exc:
        raise ValueError(f'PointCloud2 fields cannot form a point: {exc}') from None


def _check_cloud(msg, purpose: str) -> None:
    if not isinstance(msg, PointCloud2):
        raise TypeError(f'{purpose}: expected a sensor_msgs.msg.PointCloud2, got '
                        f'{type(msg).__name__}')


def _points_over(memory, msg: PointCloud2, purpose: str) -> numpy.ndarray:
    dtype = point_dtype(msg)
    height, width, row_step = msg.height, msg.width, msg.row_step
    if row_step < width * msg.point_step:
        raise ValueError(f'{purpose}: row_step {row_step} is smaller than {width} points of '
                         f'{msg.point_step} bytes')
    flat = numpy.frombuffer(memory, dtype=numpy.uint8)
    needed = height * row_step
    if flat.size < needed:
        raise ValueError(f'{purpose}: msg.data holds {flat.size} bytes but height * row_step = '
                         f'{height} * {row_step} = {needed} bytes are needed')
    return numpy.ndarray((height, width), dtype=dtype, buffer=flat, offset=0,
                         strides=(row_step, msg.point_step))


def point_cloud_from_output_msg(msg: PointCloud2) -> numpy.ndarray:
    """A writable ``(height, width)`` structured array over ``msg.data`` itself (no copy).

    ``points['x'][...] = xs`` writes the message's bytes in place. The array keeps the storage
    alive.

    :raises ValueError: inconsistent fields or sizes, storage read-only or not host-addressable.
    """
    purpose = 'point_cloud_from_output_msg'
    _check_cloud(msg, purpose)
    return _points_over(_host_memory(msg, writable=True, purpose=purpose), msg, purpose)


def point_cloud_from_input_msg(msg: PointCloud2, clone: bool = True) -> numpy.ndarray:
    """The points of a received message, as a copy (default) or a read-only view.

    :param clone: ``True``: an independent ``(height, width)`` array, packed fields in native
        byte order (one copy; through ``Buffer.to_bytes()`` when the memory is not
        host-addressable). ``False``: a view over ``msg.data`` (no copy, strides and byte order
        as the message declares) marked non-writeable.
    :raises ValueError: inconsistent fields or sizes.
    """
    purpose = 'point_cloud_from_input_msg'
    _check_cloud(msg, purpose)
    data = msg.data
    if clone and isinstance(data, Buffer) and not data.host_addressable:
        memory = data.to_bytes()
    else:
        memory = _host_memory(msg, writable=False, purpose=purpose)
    view = _points_over(memory, msg, purpose)
    if not clone:
        view.flags.writeable = False
        return view
    packed = numpy.dtype([(name, view.dtype.fields[name][0].newbyteorder('='))
                          for name in view.dtype.names])
    out = numpy.empty(view.shape, dtype=packed)
    for name in view.dtype.names:
        out[name] = view[name]
    return out


def allocate_point_cloud_msg(height: int, width: int, dtype, backend: str = CPU_BACKEND, *,
                             frame_id: str = '', is_dense: bool = True) -> PointCloud2:
    """A new PointCloud2 whose ``fields`` describe ``dtype`` and whose ``data`` holds
    ``height * width`` points in ``backend`` (``"cpu"``: a zeroed ``array.array('B')``).

    :param dtype: A numpy structured dtype of fields of (sub-arrays of) int8 ... float64, e.g.
        ``numpy.dtype([('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('intensity', 'f4')])``. Its
        offsets and itemsize are kept (``point_step = dtype.itemsize``).
    :raises ValueError: a field type PointField cannot express, or a backend that cannot
        allocate.
    """
    dtype = numpy.dtype(dtype)
    if dtype.names is None:
        raise ValueError(f'dtype must be a structured dtype with named fields, got {dtype}')
    fields = []
    for name in dtype.names:
        field_dtype, offset = dtype.fields[name][:2]
        base, shape = field_dtype.base, field_dtype.shape
        code = _DATATYPE_OF.get(base.newbyteorder('='))
        if code is None or len(shape) > 1 or (base.itemsize > 1 and
                                              base.byteorder not in ('=', '|')):
            raise ValueError(f'field {name!r} of type {field_dtype} is not a PointField type '
                             '(native int8 ... float64, or a 1-d sub-array of one)')
        fields.append(PointField(name=name, offset=offset, datatype=code,
                                 count=shape[0] if shape else 1))
    msg = PointCloud2(height=height, width=width, fields=fields,
                      is_bigendian=_HOST_IS_BIG_ENDIAN, point_step=dtype.itemsize,
                      row_step=width * dtype.itemsize, is_dense=is_dense)
    msg.header.frame_id = frame_id
    msg.data = _allocate_storage(height * width * dtype.itemsize, backend)
    return msg
