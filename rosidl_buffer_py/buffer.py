"""The Buffer type: a uint8[] payload whose bytes live in backend (vendor) memory.

Mirrors upstream's Python ``rosidl_buffer.Buffer``: a lightweight wrapper with ``backend_type``,
``is_cpu``, ``to_bytes()``, ``len()`` and a short ``repr()``. When the backend's memory is
host-addressable (shared memory, pinned host memory) the bytes are also reachable without a copy
through the buffer protocol (``memoryview(buf)``, ``numpy.asarray(buf)``) and DLPack
(``numpy.from_dlpack(buf)``).

Subscribers never receive CPU data as a Buffer: it arrives as ``array.array('B')``, exactly as in
stock rclpy. A Buffer is what a non-CPU backend hands out.
"""
from typing import Any, Optional, Tuple

from rosidl_buffer_py._native import BufferBase

#: DLPack device type of host memory (``kDLCPU``).
DLPACK_CPU = 1


class Buffer(BufferBase):
    """A uint8 payload held by a buffer backend.

    :param backend_type: Name of the backend that owns the memory (``"cpu"``, ``"demo"``, ...).
    :param host: Host-addressable bytes (anything exporting the buffer protocol), or ``None``
        when the memory cannot be read from the CPU directly. It is exported as-is: a read-only
        object gives a read-only Buffer.
    :param size: Number of bytes; required when ``host`` is ``None``.
    :param keepalive: Any object that must live as long as this Buffer and every view of it
        (for example the backend's hold on a shared-memory slot).
    """

    def __init__(self, backend_type: str, host: Any = None, *, size: Optional[int] = None,
                 keepalive: Any = None) -> None:
        if not isinstance(backend_type, str) or not backend_type:
            raise TypeError(f'backend_type must be a non-empty str, got {backend_type!r}')
        view = None
        if host is not None:
            view = memoryview(host)
            if view.ndim != 1 or view.format != 'B' or not view.c_contiguous:
                view = view.cast('B') if view.c_contiguous else None
            if view is None:
                raise ValueError('host memory of a Buffer must be C-contiguous')
            if size is not None and size != view.nbytes:
                raise ValueError(f'size {size} does not match the {view.nbytes} host bytes')
            size = view.nbytes
        elif size is None or size < 0:
            raise ValueError(f'a Buffer without host memory needs size >= 0, got {size!r}')
        super().__init__(view)
        self._backend_type = backend_type
        self._size = int(size)
        self._readonly = True if view is None else view.readonly
        self._keepalive = keepalive

    @classmethod
    def over_view(cls, backend_type: str, view: memoryview, keepalive: Any = None,
                  **attributes: Any) -> 'Buffer':
        """What ``cls(backend_type, view, keepalive=keepalive)`` makes, without its checks, for
        a backend's receive path, where ``view`` is its own mapping's: a 1-D, C-contiguous
        memoryview of format ``'B'``. ``attributes``: a subclass's own, set on it too."""
        buffer = cls.__new__(cls)
        BufferBase.__init__(buffer, view)
        buffer.__dict__.update(_backend_type=backend_type, _size=view.nbytes,
                               _readonly=view.readonly, _keepalive=keepalive, **attributes)
        return buffer

    @property
    def backend_type(self) -> str:
        """Name of the backend that owns the memory."""
        return self._backend_type

    @property
    def is_cpu(self) -> bool:
        """True when this is plain CPU storage (backend ``"cpu"``)."""
        return self._backend_type == 'cpu'

    @property
    def readonly(self) -> bool:
        """True when the bytes cannot be written through this Buffer."""
        return self._readonly

    @property
    def host_addressable(self) -> bool:
        """True when ``memoryview(buf)`` gives the bytes without a copy."""
        return self._has_host_memory

    def __len__(self) -> int:
        return self._size

    def to_bytes(self) -> bytes:
        """Copy the payload into a new ``bytes`` (for diagnostics, logging and CPU fallback).

        Backends whose memory is not host-addressable override this with their own download.
        """
        if not self._has_host_memory:
            raise NotImplementedError(
                f'backend {self._backend_type!r} does not provide to_bytes() for '
                'non-host-addressable memory')
        return bytes(memoryview(self))

    def host_bytes(self) -> memoryview:
        """The payload on the host, for sending it as CPU bytes: the memory itself when it is
        host-addressable, else the backend's download (by default :meth:`to_bytes`; a backend
        may hand out a reusable staging area instead, valid until its next download)."""
        if self._has_host_memory:
            return memoryview(self)
        return memoryview(self.to_bytes())

    def __repr__(self) -> str:
        access = 'read-only' if self._readonly else 'writable'
        return (f'{type(self).__name__}(backend_type={self._backend_type!r}, '
                f'nbytes={self._size}, {access})')

    # DLPack (https://dmlc.github.io/dlpack/latest/python_spec.html): host memory only.
    def __dlpack__(self, *, stream: Any = None, max_version: Optional[Tuple[int, int]] = None,
                   dl_device: Optional[Tuple[int, int]] = None, copy: Optional[bool] = None):
        """Export the bytes as a 1-D uint8 DLPack tensor (host memory, no copy)."""
        if stream is not None:
            raise BufferError(f'host memory takes no stream, got stream={stream!r}')
        if dl_device is not None and tuple(dl_device) != (DLPACK_CPU, 0):
            raise BufferError(f'{self!r} lives on the host (device (1, 0)), not {dl_device!r}')
        import numpy
        array = numpy.frombuffer(self, dtype=numpy.uint8) if len(self) else \
            numpy.empty(0, dtype=numpy.uint8)
        kwargs = {}
        if max_version is not None:
            kwargs['max_version'] = max_version
        if copy is not None:
            kwargs['copy'] = copy
        return array.__dlpack__(**kwargs)

    def __dlpack_device__(self) -> Tuple[int, int]:
        """DLPack device of the bytes: always the host, ``(kDLCPU, 0)``."""
        if not self._has_host_memory:
            raise BufferError(f'{self!r} has no host-addressable memory')
        return (DLPACK_CPU, 0)
