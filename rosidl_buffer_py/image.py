"""numpy views and copies of ``sensor_msgs/Image``, over CPU or buffer-backend storage.

The four operations of a conversions package (allocate / writable view / readable view or copy /
copy-in), for numpy:

- :func:`allocate_image_msg`: fill the metadata and size ``msg.data`` in the chosen backend;
- :func:`from_output_msg`: a writable array over the message's own bytes (publisher side);
- :func:`from_input_msg`: an independent copy, or a read-only view (subscriber side);
- :func:`to_msg`: copy an existing array into the message's storage and refresh its metadata.

``msg.data`` may be an ``array.array('B')`` (stock rclpy, backend ``cpu``) or a
:class:`~rosidl_buffer_py.Buffer` whose memory is host-addressable. Nothing here walks the pixels
in Python: views are numpy arrays laid over the storage (``step`` padding becomes a row stride),
copies are a single numpy copy.

Byte order: a message's multi-byte pixels are read with the byte order ``is_bigendian`` names.
:func:`allocate_image_msg` sets ``is_bigendian`` to the host's byte order for multi-byte
encodings (so views are native-endian) and to 0 for 8-bit encodings, where it is meaningless.
"""
import array as _pyarray
import re
import sys
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy
from sensor_msgs.msg import Image

from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.message_support import enable_buffer_fields
from rosidl_buffer_py.registry import get_backend, get_installed_backends

__all__ = [
    'EncodingInfo',
    'allocate_image_msg',
    'encoding_info',
    'from_input_msg',
    'from_output_msg',
    'supported_encodings',
    'to_msg',
]

enable_buffer_fields(Image)  # ``msg.data = buffer`` must keep the Buffer (idempotent)

_HOST_IS_BIG_ENDIAN = sys.byteorder == 'big'
_UINT32_MAX = 2 ** 32 - 1


@dataclass(frozen=True)
class EncodingInfo:
    """What an encoding means in memory: numpy element type (native order) and channel count."""

    encoding: str
    dtype: numpy.dtype
    channels: int

    @property
    def bytes_per_pixel(self) -> int:
        """Bytes one pixel takes (``dtype.itemsize * channels``)."""
        return self.dtype.itemsize * self.channels


def _named_encodings() -> Dict[str, Tuple[str, int]]:
    table = {
        'mono8': ('u1', 1), 'mono16': ('u2', 1),
        'rgb8': ('u1', 3), 'bgr8': ('u1', 3), 'rgba8': ('u1', 4), 'bgra8': ('u1', 4),
        'rgb16': ('u2', 3), 'bgr16': ('u2', 3), 'rgba16': ('u2', 4), 'bgra16': ('u2', 4),
        # packed YUV 4:2:2: two bytes a pixel, as cv_bridge maps them (8UC2)
        'yuv422': ('u1', 2), 'yuv422_yuy2': ('u1', 2), 'uyvy': ('u1', 2), 'yuyv': ('u1', 2),
    }
    for pattern in ('rggb', 'bggr', 'gbrg', 'grbg'):
        table[f'bayer_{pattern}8'] = ('u1', 1)
        table[f'bayer_{pattern}16'] = ('u2', 1)
    return table


#: Named encodings of ``sensor_msgs/image_encodings.hpp``: numpy type code and channel count.
_NAMED: Dict[str, Tuple[str, int]] = _named_encodings()

#: The generic OpenCV-style family ``<bits><U|S|F>C<channels>``, e.g. ``8UC3``, ``32FC1``.
_GENERIC = re.compile(r'^(8U|8S|16U|16S|32S|32F|64F)C([1-9][0-9]{0,2})$')
_GENERIC_DTYPES = {'8U': 'u1', '8S': 'i1', '16U': 'u2', '16S': 'i2', '32S': 'i4',
                   '32F': 'f4', '64F': 'f8'}
_DTYPE_TO_GENERIC = {numpy.dtype(code): depth for depth, code in _GENERIC_DTYPES.items()}
_MAX_GENERIC_CHANNELS = 512  # OpenCV's CV_CN_MAX

_SUPPORTED_TEXT = (', '.join(_NAMED) + ', and <depth>C<channels> with depth one of '
                   + ', '.join(_GENERIC_DTYPES) + f' and 1..{_MAX_GENERIC_CHANNELS} channels '
                   '(8UC1 .. 64FC4, ...)')


def supported_encodings() -> str:
    """Describe the accepted encodings (the text error messages use)."""
    return _SUPPORTED_TEXT


def encoding_info(encoding: str) -> EncodingInfo:
    """Return the memory layout of ``encoding``; ``ValueError`` names it and the supported ones."""
    if not isinstance(encoding, str):
        raise TypeError(f'encoding must be a str, got {type(encoding).__name__} {encoding!r}')
    named = _NAMED.get(encoding)
    if named is not None:
        return EncodingInfo(encoding, numpy.dtype(named[0]), named[1])
    match = _GENERIC.match(encoding)
    if match is not None and 1 <= int(match.group(2)) <= _MAX_GENERIC_CHANNELS:
        return EncodingInfo(encoding, numpy.dtype(_GENERIC_DTYPES[match.group(1)]),
                            int(match.group(2)))
    raise ValueError(f'unsupported image encoding {encoding!r}; supported: {_SUPPORTED_TEXT}')


def _element_dtype(info: EncodingInfo, is_bigendian: bool) -> numpy.dtype:
    """The element type with the byte order the message declares (8-bit types have none)."""
    if info.dtype.itemsize == 1:
        return info.dtype
    return info.dtype.newbyteorder('>' if is_bigendian else '<')


def _default_is_bigendian(info: EncodingInfo) -> int:
    """Host byte order for multi-byte encodings, 0 for 8-bit ones."""
    return int(_HOST_IS_BIG_ENDIAN and info.dtype.itemsize > 1)


def _cpu_zeros(nbytes: int) -> _pyarray.array:
    """Zeroed stock rclpy storage: an ``array.array('B')`` of ``nbytes``."""
    return _pyarray.array('B', bytes(1)) * nbytes


def _check_uint32(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, numpy.integer)):
        raise TypeError(f'{name} must be an int, got {type(value).__name__} {value!r}')
    value = int(value)
    if not 0 <= value <= _UINT32_MAX:
        raise ValueError(f'{name} must be in 0..{_UINT32_MAX}, got {value}')
    return value


def _resolve_step(info: EncodingInfo, width: int, step: Optional[int]) -> int:
    row_bytes = width * info.bytes_per_pixel
    if step is None:
        if row_bytes > _UINT32_MAX:
            raise ValueError(f'a row of {width} {info.encoding} pixels takes {row_bytes} bytes, '
                             f'more than step (uint32) can hold')
        return row_bytes
    step = _check_uint32('step', step)
    if step < row_bytes:
        raise ValueError(f'step {step} is smaller than a row of {width} {info.encoding} pixels '
                         f'({width} * {info.bytes_per_pixel} = {row_bytes} bytes); '
                         f'step must be >= {row_bytes}')
    return step


def _shape(info: EncodingInfo, height: int, width: int) -> Tuple[int, ...]:
    return (height, width) if info.channels == 1 else (height, width, info.channels)


def _strides(info: EncodingInfo, step: int) -> Tuple[int, ...]:
    itemsize = info.dtype.itemsize
    if info.channels == 1:
        return (step, itemsize)
    return (step, info.bytes_per_pixel, itemsize)


def _host_memory(msg: Image, *, writable: bool, purpose: str) -> memoryview:
    """A flat uint8 memoryview of ``msg.data`` (no copy), checked for the access asked for."""
    data = msg.data
    if isinstance(data, Buffer):
        if not data.host_addressable:
            raise ValueError(f'{purpose}: msg.data is {data!r}, whose memory is not '
                             'host-addressable, so numpy cannot see it')
        if writable and data.readonly:
            raise ValueError(f'{purpose}: msg.data is {data!r}, which is read-only (e.g. a '
                             'buffer received from another process); from_input_msg(msg) '
                             'gives a copy you can modify, allocate_image_msg() a new message')
        view = memoryview(data)
    elif isinstance(data, _pyarray.array):
        if data.typecode != 'B':
            raise TypeError(f"{purpose}: msg.data must be array.array('B'), got "
                            f'typecode {data.typecode!r}')
        view = memoryview(data)
    else:
        raise TypeError(f"{purpose}: msg.data must be an array.array('B') or a Buffer, got "
                        f'{type(data).__name__}')
    return view.cast('B') if view.format != 'B' else view


def _array_over(memory, info: EncodingInfo, height: int, width: int, step: int,
                is_bigendian: bool, purpose: str) -> numpy.ndarray:
    """Lay an (H, W[, C]) array over ``memory`` with row stride ``step`` (no copy).

    The flat ``frombuffer`` array in between holds a buffer export for as long as the result
    lives: that keeps a Buffer alive and stops an ``array.array`` from being resized under it
    (``numpy.ndarray(buffer=memoryview)`` alone would drop the export).
    """
    needed = height * step
    flat = numpy.frombuffer(memory, dtype=numpy.uint8)
    if flat.size < needed:
        raise ValueError(f'{purpose}: msg.data holds {flat.size} bytes but height * step = '
                         f'{height} * {step} = {needed} bytes are needed')
    return numpy.ndarray(_shape(info, height, width), dtype=_element_dtype(info, is_bigendian),
                         buffer=flat, offset=0, strides=_strides(info, step))


def _check_image(msg, purpose: str) -> None:
    """TypeError unless ``msg`` is a sensor_msgs/msg/Image (these helpers read its fields)."""
    if not isinstance(msg, Image):
        raise TypeError(f'{purpose}: expected a sensor_msgs.msg.Image, got '
                        f'{type(msg).__name__}')


def _message_layout(msg: Image, purpose: str) -> Tuple[EncodingInfo, int, int, int]:
    """Validated (encoding info, height, width, step) of ``msg``."""
    _check_image(msg, purpose)
    info = encoding_info(msg.encoding)
    height = _check_uint32('msg.height', msg.height)
    width = _check_uint32('msg.width', msg.width)
    step = msg.step
    row_bytes = width * info.bytes_per_pixel
    if step < row_bytes:
        raise ValueError(f'{purpose}: msg.step {step} is smaller than a row of {width} '
                         f'{info.encoding} pixels ({row_bytes} bytes)')
    return info, height, width, step


def allocate_image_msg(height: int, width: int, encoding: str, backend: str = CPU_BACKEND, *,
                       step: Optional[int] = None) -> Image:
    """Return a new Image with its metadata filled and ``data`` sized ``height * step``.

    Fill it in place through :func:`from_output_msg`, then publish it.

    :param height: Rows.
    :param width: Pixels per row.
    :param encoding: One of :func:`supported_encodings`.
    :param backend: ``"cpu"`` gives a zeroed ``array.array('B')`` (stock rclpy storage); any
        other name allocates a writable Buffer through that installed backend's ``allocate()``
        (contents as the backend leaves them).
    :param step: Bytes per row; default ``width * bytes_per_pixel``. A larger value leaves
        padding at the end of each row.
    :return: The message. ``is_bigendian`` is the host's byte order for multi-byte encodings and
        0 for 8-bit ones.
    :raises ValueError: Unsupported encoding, a step too small, a backend that is not installed
        or cannot allocate.
    """
    info = encoding_info(encoding)
    height = _check_uint32('height', height)
    width = _check_uint32('width', width)
    step = _resolve_step(info, width, step)
    nbytes = height * step
    msg = Image()
    msg.height = height
    msg.width = width
    msg.encoding = encoding
    msg.is_bigendian = _default_is_bigendian(info)
    msg.step = step
    msg.data = _allocate_storage(nbytes, backend)
    return msg


def _allocate_storage(nbytes: int, backend: str):
    """``nbytes`` of payload storage: a zeroed ``array.array('B')`` for ``"cpu"``, else a
    writable Buffer from the installed backend's ``allocate()``."""
    if not isinstance(backend, str):
        raise TypeError(f'backend must be a str such as "cpu" or "demo", got '
                        f'{type(backend).__name__} {backend!r}')
    if backend == CPU_BACKEND:
        return _cpu_zeros(nbytes)
    try:
        plugin = get_backend(backend)
    except KeyError:
        raise ValueError(f'buffer backend {backend!r} is not installed; installed: '
                         f'{", ".join(sorted(get_installed_backends()))}') from None
    try:
        buffer = plugin.allocate(nbytes)
    except NotImplementedError as exc:
        raise ValueError(f'buffer backend {backend!r} cannot allocate memory ({exc}); use a '
                         f'backend that implements allocate(), or "{CPU_BACKEND}"') from None
    if not isinstance(buffer, Buffer):
        raise TypeError(f'buffer backend {backend!r}: allocate({nbytes}) returned '
                        f'{type(buffer).__name__}, not a Buffer')
    if len(buffer) != nbytes or buffer.readonly:
        raise ValueError(f'buffer backend {backend!r}: allocate({nbytes}) returned {buffer!r}; '
                         f'expected a writable Buffer of {nbytes} bytes')
    return buffer


def from_output_msg(msg: Image) -> numpy.ndarray:
    """Return a writable array over ``msg.data`` itself, to fill an image in place (no copy).

    Shape is ``(height, width)`` for one channel and ``(height, width, channels)`` otherwise;
    rows are ``step`` bytes apart, so padding is skipped, never exposed. The element type comes
    from ``encoding``, in the byte order ``is_bigendian`` names. The array keeps the storage alive;
    while it exists an ``array.array`` storage cannot be resized.

    :raises ValueError: Unsupported encoding, inconsistent metadata, storage too small, or
        storage that is read-only or not host-addressable.
    """
    purpose = 'from_output_msg'
    info, height, width, step = _message_layout(msg, purpose)
    memory = _host_memory(msg, writable=True, purpose=purpose)
    return _array_over(memory, info, height, width, step, bool(msg.is_bigendian), purpose)


def from_input_msg(msg: Image, clone: bool = True) -> numpy.ndarray:
    """Return the image of a received message, as a copy (default) or a read-only view.

    :param clone: ``True``: an independent, C-contiguous, native-byte-order array (padding
        dropped) that outlives and never aliases the message; one copy. For a Buffer whose memory
        is not host-addressable this copies through ``Buffer.to_bytes()``. ``False``: a view over
        ``msg.data`` (no copy, byte order as the message declares, ``step`` as row stride) marked
        non-writeable, because a received payload may be shared with other subscribers; it is
        also read-only at the memory level when the storage is (e.g. shared memory received from
        another process).
    :raises ValueError: Unsupported encoding, inconsistent metadata or storage too small.
    """
    purpose = 'from_input_msg'
    info, height, width, step = _message_layout(msg, purpose)
    is_bigendian = bool(msg.is_bigendian)
    data = msg.data
    if clone and isinstance(data, Buffer) and not data.host_addressable:
        try:
            memory = data.to_bytes()
        except NotImplementedError as exc:
            raise ValueError(f'{purpose}: cannot copy {data!r} to the host: {exc}') from None
    else:
        memory = _host_memory(msg, writable=False, purpose=purpose)
    view = _array_over(memory, info, height, width, step, is_bigendian, purpose)
    if clone:
        return view.astype(view.dtype.newbyteorder('='), order='C', copy=True)
    view.flags.writeable = False
    return view


def _array_channels(array: numpy.ndarray) -> int:
    if array.ndim == 2:
        return 1
    if array.ndim == 3 and array.shape[2] >= 1:
        return array.shape[2]
    raise ValueError(f'to_msg: the array must have shape (height, width) or (height, width, '
                     f'channels), got shape {array.shape}')


def _infer_encoding(base: numpy.dtype, channels: int, shape: Tuple[int, ...]) -> str:
    """The encoding an array of ``base`` elements and ``channels`` channels most plainly is."""
    plain = {('u1', 1): 'mono8', ('u1', 3): 'rgb8', ('u1', 4): 'rgba8', ('u2', 1): 'mono16',
             ('f4', 1): '32FC1'}
    key = (base.str[1:], channels)
    if key in plain:
        return plain[key]
    depth = _DTYPE_TO_GENERIC.get(base)
    if depth is None or channels > _MAX_GENERIC_CHANNELS:
        raise ValueError(f'to_msg: no image encoding for an array of dtype {base} and shape '
                         f'{shape}; accepted dtypes: '
                         f'{", ".join(str(d) for d in _DTYPE_TO_GENERIC)}')
    return f'{depth}C{channels}'


def to_msg(msg: Image, array: numpy.ndarray, *, encoding: Optional[str] = None,
           step: Optional[int] = None) -> None:
    """Copy ``array`` into ``msg.data`` (one copy) and refresh height, width, step and encoding.

    :param msg: The message; its storage is reused when it can be.
    :param array: ``(height, width)`` or ``(height, width, channels)``, any strides and byte
        order. Its bytes are stored in its own byte order and ``is_bigendian`` is set to match
        (0 for 8-bit data).
    :param encoding: The encoding to store. Default: ``msg.encoding`` if it matches the array's
        dtype and channel count, otherwise inferred: uint8 (H, W) -> mono8, (H, W, 3) -> rgb8,
        (H, W, 4) -> rgba8, uint16 (H, W) -> mono16, float32 (H, W) -> 32FC1, and any other
        dtype/channel pair -> the generic ``<depth>C<channels>`` (e.g. float64 (H, W, 2) -> 64FC2).
    :param step: Bytes per row to write; default packed rows (``width * bytes_per_pixel``).
    :raises ValueError: An encoding that does not match the array, an unsupported dtype or shape,
        or Buffer storage that is too small (both sizes given) or read-only.

    Storage: an ``array.array`` whose size differs from ``height * step`` is replaced by a new
    ``array.array`` of exactly that size (views made earlier keep pointing at the old one). A
    Buffer is never replaced (that would change its backend): it must hold at least
    ``height * step`` bytes, and bytes past that are left untouched.
    """
    _check_image(msg, 'to_msg')
    if not isinstance(array, numpy.ndarray):
        raise TypeError(f'to_msg: expected a numpy.ndarray, got {type(array).__name__}')
    channels = _array_channels(array)
    base = array.dtype.newbyteorder('=')
    if encoding is not None:
        info = encoding_info(encoding)
    else:
        info = None
        if msg.encoding:
            try:
                current = encoding_info(msg.encoding)
            except ValueError:
                current = None
            if current is not None and current.dtype == base and current.channels == channels:
                info = current
        if info is None:
            info = encoding_info(_infer_encoding(base, channels, array.shape))
    if info.dtype != base or info.channels != channels:
        raise ValueError(f'to_msg: encoding {info.encoding!r} holds {info.channels} channel(s) '
                         f'of {info.dtype}, but the array has dtype {array.dtype} and shape '
                         f'{array.shape} ({channels} channel(s) of {base})')
    height = _check_uint32('array height', array.shape[0])
    width = _check_uint32('array width', array.shape[1])
    step = _resolve_step(info, width, step)
    nbytes = height * step
    is_bigendian = info.dtype.itemsize > 1 and (
        array.dtype.byteorder == '>' or (array.dtype.byteorder == '=' and _HOST_IS_BIG_ENDIAN))

    data = msg.data
    if isinstance(data, Buffer):
        memory = _host_memory(msg, writable=True, purpose='to_msg')
        if memory.nbytes < nbytes:
            raise ValueError(f'to_msg: msg.data ({data!r}) holds {memory.nbytes} bytes but the '
                             f'array needs {nbytes} (height {height} * step {step}); allocate a '
                             'larger message')
    else:
        memory = _host_memory(msg, writable=True, purpose='to_msg')
        if memory.nbytes != nbytes:
            memory.release()
            msg.data = _cpu_zeros(nbytes)
            memory = _host_memory(msg, writable=True, purpose='to_msg')
    destination = _array_over(memory, info, height, width, step, is_bigendian, 'to_msg')
    numpy.copyto(destination, array.reshape(destination.shape), casting='equiv')
    msg.height = height
    msg.width = width
    msg.step = step
    msg.encoding = info.encoding
    msg.is_bigendian = int(is_bigendian)
