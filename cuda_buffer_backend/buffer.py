"""CudaBuffer: a Buffer whose bytes live in GPU memory, handed to torch and CuPy by DLPack or
``__cuda_array_interface__`` without a copy, with the stream semantics both specify."""
import ctypes
from typing import Any, Optional, Tuple

from demo_buffer_backend.mappings import Hold
from demo_buffer_backend.slots import Pin
from rosidl_buffer_py._native import dlpack_capsule
from rosidl_buffer_py.buffer import Buffer

from cuda_buffer_backend import driver as cuda
from cuda_buffer_backend import lifecycle
from cuda_buffer_backend.memory import DeviceRange

BACKEND_TYPE = 'cuda'
#: DLPack device types.
KDLCPU = 1
KDLCUDA = 2
#: DLPack's stream argument: ``-1`` asks for no synchronization.
NO_SYNC = -1


class _Private:
    """Device memory of one Buffer outside the pool (``cuMemAlloc``): freed with it."""

    __slots__ = ('device', 'address')

    def __init__(self, device: int, nbytes: int) -> None:
        drv = cuda.load()
        self.device = device
        with drv.on(device):
            self.address = drv.mem_alloc(nbytes)

    def __del__(self) -> None:
        try:
            drv = cuda.load()
            with drv.on(self.device):
                drv.mem_free(self.address)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


def _stream_of(stream: Any) -> int:
    """A DLPack / CUDA Array Interface stream argument as a driver stream handle."""
    if stream is None:
        return cuda.STREAM_LEGACY  # DLPack: None means the legacy default stream
    handle = getattr(stream, 'cuda_stream', None)  # a torch.cuda.Stream
    if handle is None:
        handle = getattr(stream, 'ptr', None)  # a cupy.cuda.Stream
    if handle is None:
        handle = stream
    if isinstance(handle, bool) or not isinstance(handle, int):
        raise TypeError(f'stream must be None, an int (1 legacy default, 2 per-thread default, '
                        f'-1 no synchronization, or a stream handle) or a torch/CuPy stream, '
                        f'got {stream!r}')
    if handle == 0:
        raise BufferError('stream 0 is ambiguous (DLPack disallows it for CUDA): pass 1 for '
                          'the legacy default stream, 2 for the per-thread default stream, or '
                          "a stream's handle")
    if handle < NO_SYNC:
        raise ValueError(f'stream must be -1, 1, 2 or a stream handle, got {handle}')
    return handle


class CudaBuffer(Buffer):
    """A ``cuda`` Buffer: ``nbytes`` of memory on one GPU.

    Make one with :meth:`allocate` (a pooled slot to fill in place, for example through
    ``torch.from_dlpack(buf)``) or :meth:`from_dlpack` (one device-to-device copy of a tensor);
    a subscriber gets a read-only one from ``CudaBackend.from_descriptor_with_endpoint``.

    - ``torch.from_dlpack(buf)``, ``cupy.from_dlpack(buf)``: a zero-copy 1-D uint8 view; the
      consumer's stream (DLPack's ``stream`` argument) first waits for the publisher's writes.
    - ``buf.__cuda_array_interface__`` (version 3): the same view for Numba, CuPy and others; its
      ``stream`` (the legacy default stream) waits for the publisher's writes.
    - ``buf.to_bytes()``: a host copy; ``numpy.asarray(buf)`` is refused (device memory).

    A publisher's writes are those queued, when it publishes, on :attr:`stream` (set it, or it is
    the stream last given to ``__dlpack__``; else the legacy default stream). A subscriber's
    slot goes back to its publisher once the Buffer and every view of it are gone *and* the reads
    queued on the streams it was exported to are complete. Received memory is mapped read-only:
    a kernel writing to it faults; clone it to modify.
    """

    def __init__(self, memory: DeviceRange, *, keepalive: Any = None,
                 readonly: bool = False) -> None:
        """Internal: wrap ``memory``; ``keepalive`` is the pool's pin or hold, or the private
        allocation. Use :meth:`allocate` or :meth:`from_dlpack`."""
        super().__init__(BACKEND_TYPE, None, size=memory.nbytes, keepalive=keepalive)
        self._memory = memory
        self._readonly = readonly
        self._pin = keepalive if isinstance(keepalive, Pin) else None
        self._hold = keepalive if isinstance(keepalive, Hold) else None
        #: the stream whose queued work writes the bytes (publisher side), None: legacy default
        self.stream: Optional[int] = None

    # --- making ---------------------------------------------------------------------------------
    @classmethod
    def allocate(cls, nbytes: int, device: int = 0) -> 'CudaBuffer':
        """A writable CudaBuffer of ``nbytes`` on ``device`` (contents unspecified), in a pooled
        slot when one can be had (else private device memory, which is sent as CPU bytes).
        ``MemoryError`` when the device has no memory for it; ``RuntimeError`` when this
        process cannot use CUDA (the reason is in the message)."""
        if isinstance(nbytes, bool) or not isinstance(nbytes, int):
            raise TypeError(f'nbytes must be an int, got {type(nbytes).__name__}')
        if nbytes < 0:
            raise ValueError(f'nbytes must be >= 0, got {nbytes}')
        pool = lifecycle.get_pool(device)
        got = pool.allocate(nbytes)
        if got is not None:
            memory, pin = got
            return cls(memory, keepalive=pin)
        try:
            private = _Private(device, nbytes)
        except cuda.OutOfMemory as exc:
            raise MemoryError(f'cannot allocate {nbytes} bytes on cuda:{device}: the device has '
                              f'no memory left ({exc})') from None
        return cls(DeviceRange(private.address, nbytes, device), keepalive=private)

    @classmethod
    def from_dlpack(cls, tensor: Any, *, stream: Any = None) -> 'CudaBuffer':
        """A CudaBuffer holding a copy of a C-contiguous CUDA tensor's bytes (torch, CuPy, any
        DLPack producer): one device-to-device copy into a pooled slot, queued on ``stream``
        (default: the legacy default stream) after the producer's work on it."""
        if not hasattr(tensor, '__dlpack__'):
            raise TypeError(f'CudaBuffer.from_dlpack needs a DLPack producer (a torch or CuPy '
                            f'CUDA tensor), got {type(tensor).__name__}')
        device_type, device = tensor.__dlpack_device__()
        if device_type != KDLCUDA:
            raise ValueError(f'CudaBuffer.from_dlpack needs a CUDA tensor (DLPack device type '
                             f'{KDLCUDA}), got device type {device_type}: copy it to the GPU '
                             'first (torch: tensor.cuda())')
        handle = _stream_of(stream)
        capsule = tensor.__dlpack__(stream=handle if handle != NO_SYNC else None)
        address, nbytes = _read_capsule(capsule)
        try:
            buf = cls.allocate(nbytes, device)
            drv = cuda.load()
            with drv.on(device):
                drv.copy_on_device(buf._memory.address, address, nbytes, handle
                                   if handle != NO_SYNC else cuda.STREAM_LEGACY)
        finally:
            _release_capsule(capsule)
        buf.stream = handle if handle != NO_SYNC else None
        return buf

    # --- what it is ------------------------------------------------------------------------------
    @property
    def device(self) -> int:
        """The CUDA device ordinal (in this process) holding the bytes."""
        return self._memory.device

    @property
    def address(self) -> int:
        """The device address of the first byte."""
        return self._memory.address

    @property
    def in_pool(self) -> bool:
        """True when the bytes live in a slot that subscribers can map (False: private memory,
        sent as CPU bytes)."""
        return self._pin is not None or self._hold is not None

    @property
    def pin(self) -> Optional[Pin]:
        """The publisher's pin on its slot (what ``CudaBackend`` describes), else None."""
        return self._pin

    @property
    def hold(self) -> Optional[Hold]:
        """A subscriber's hold on the received slot, else None."""
        return self._hold

    @property
    def generation(self) -> Optional[int]:
        claim = self._pin or self._hold
        return claim.generation if claim is not None else None

    def renew(self, timeout: Optional[float] = None) -> bool:
        """Wait until every subscriber is done with this published buffer (its descriptors
        taken or given up, its views gone and their reads complete), then make it a new frame
        in the same device memory: its address stays (a CUDA graph may keep writing there).
        False when ``timeout`` seconds passed first, for a received buffer, or for private
        memory."""
        if self._pin is None:
            return False
        return lifecycle.get_pool(self.device).renew(self._pin, timeout)

    def wait_released(self, timeout: Optional[float] = None) -> bool:
        """Wait until every subscriber is done with this published buffer (as :meth:`renew`,
        their reads on the GPU complete), without making it a new frame: True once they are,
        False when ``timeout`` seconds passed first (0: only checks). Private memory is never
        shared: True at once. A received buffer: False."""
        if self._pin is None:
            return self._hold is None
        return lifecycle.get_pool(self.device).released(self._pin, timeout)

    @property
    def released(self) -> bool:
        """Whether every subscriber is done with this published buffer now
        (``wait_released(0)``), as pyzmq's ``MessageTracker.done``."""
        return self.wait_released(0)

    # --- synchronization -------------------------------------------------------------------------
    def _export_to(self, handle: int) -> None:
        """The consumer's stream ``handle`` is about to read (or, publisher side, write)."""
        if self._hold is not None:
            if handle == NO_SYNC:
                return  # the consumer synchronizes itself (DLPack -1)
            drv = cuda.load()
            with drv.on(self.device):
                drv.stream_wait(handle, self._memory.event)
            readers = self._hold.readers
            if readers is None:
                readers = self._hold.readers = set()
            readers.add((self.device, handle))
        elif handle != NO_SYNC:
            self.stream = handle

    def record_writes(self) -> None:
        """Mark the writes queued on :attr:`stream` as what subscribers wait for (the
        publisher calls it before a descriptor leaves)."""
        if self._pin is not None:
            self._pin.slot.segment.record(self.stream or cuda.STREAM_LEGACY)

    # --- views -----------------------------------------------------------------------------------
    def __dlpack__(self, *, stream: Any = None, max_version: Optional[Tuple[int, int]] = None,
                   dl_device: Optional[Tuple[int, int]] = None, copy: Optional[bool] = None):
        """A zero-copy 1-D uint8 DLPack tensor on ``(kDLCUDA, device)``; ``stream`` (the
        consumer's: None or 1 legacy default, 2 per-thread default, a handle, or -1 for none)
        first waits for the publisher's writes."""
        if dl_device is not None and tuple(dl_device) != (KDLCUDA, self.device):
            raise BufferError(f'{self!r} lives on ({KDLCUDA}, {self.device}) (cuda:'
                              f'{self.device}), not {tuple(dl_device)!r}: copy it with '
                              'to_bytes() or in the consumer')
        if copy:
            raise BufferError('CudaBuffer exports its memory without a copy (copy=True is not '
                              'supported): clone the consumer\'s tensor instead')
        self._export_to(_stream_of(stream))
        versioned = max_version is not None and tuple(max_version)[0] >= 1
        return dlpack_capsule(self._memory.address, self._size, KDLCUDA, self.device, self,
                              versioned)

    def __dlpack_device__(self) -> Tuple[int, int]:
        return (KDLCUDA, self.device)

    @property
    def __cuda_array_interface__(self) -> dict:
        """CUDA Array Interface version 3: the bytes as a 1-D ``|u1`` array, valid on the legacy
        default stream (which waits for the publisher's writes)."""
        self._export_to(cuda.STREAM_LEGACY)
        return {'shape': (self._size,), 'typestr': '|u1', 'version': 3, 'strides': None,
                'data': (self._memory.address, self._readonly), 'stream': cuda.STREAM_LEGACY}

    def __array__(self, dtype: Any = None, copy: Any = None):
        raise TypeError(f'{self!r} is GPU memory (cuda:{self.device}): numpy needs host '
                        'memory. Use torch.from_dlpack(buf) or cupy.from_dlpack(buf) on the '
                        'GPU, or numpy.frombuffer(buf.to_bytes(), numpy.uint8) for a host copy')

    # --- host copies -----------------------------------------------------------------------------
    def host_bytes(self) -> memoryview:
        """The bytes on the host, after the writes (or the publisher's) complete: one
        device-to-host copy, into the slot's page-locked staging memory for a publisher's slot
        (shared by every CPU peer of a message)."""
        drv = cuda.load()
        if self._pin is not None:
            stream = self.stream or cuda.STREAM_LEGACY
            return self._pin.slot.segment.host_copy(self._size, stream)
        out = bytearray(self._size)
        if self._size:
            with drv.on(self.device):
                stream = cuda.STREAM_LEGACY
                if self._hold is not None:
                    drv.stream_wait(stream, self._memory.event)
                elif self.stream:
                    stream = self.stream
                target = (ctypes.c_char * self._size).from_buffer(out)
                drv.copy_to_host(ctypes.addressof(target), self._memory.address, self._size,
                                 stream)
                drv.stream_synchronize(stream)
                del target
        return memoryview(out)

    def to_bytes(self) -> bytes:
        """A copy of the bytes on the host."""
        return bytes(self.host_bytes())

    def __repr__(self) -> str:
        access = 'read-only' if self._readonly else 'writable'
        return f'CudaBuffer(cuda:{self.device}, nbytes={self._size}, {access})'


# --- reading a producer's DLPack capsule ---------------------------------------------------------

class _DLDevice(ctypes.Structure):
    _fields_ = [('device_type', ctypes.c_int32), ('device_id', ctypes.c_int32)]


class _DLDataType(ctypes.Structure):
    _fields_ = [('code', ctypes.c_uint8), ('bits', ctypes.c_uint8), ('lanes', ctypes.c_uint16)]


class _DLTensor(ctypes.Structure):
    _fields_ = [('data', ctypes.c_void_p), ('device', _DLDevice), ('ndim', ctypes.c_int32),
                ('dtype', _DLDataType), ('shape', ctypes.POINTER(ctypes.c_int64)),
                ('strides', ctypes.POINTER(ctypes.c_int64)), ('byte_offset', ctypes.c_uint64)]


class _DLManagedTensor(ctypes.Structure):
    pass


_DELETER = ctypes.CFUNCTYPE(None, ctypes.POINTER(_DLManagedTensor))
_DLManagedTensor._fields_ = [('dl_tensor', _DLTensor), ('manager_ctx', ctypes.c_void_p),
                             ('deleter', _DELETER)]
_api = ctypes.pythonapi
_api.PyCapsule_GetPointer.restype = ctypes.c_void_p
_api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
_api.PyCapsule_IsValid.restype = ctypes.c_int
_api.PyCapsule_IsValid.argtypes = [ctypes.py_object, ctypes.c_char_p]
_api.PyCapsule_SetName.restype = ctypes.c_int
_api.PyCapsule_SetName.argtypes = [ctypes.py_object, ctypes.c_char_p]
_USED = ctypes.c_char_p(b'used_dltensor')  # kept alive: the capsule keeps the pointer


def _read_capsule(capsule: Any) -> Tuple[int, int]:
    """``(address, nbytes)`` of a legacy DLPack capsule's compact tensor; ``ValueError`` for a
    strided one."""
    if not _api.PyCapsule_IsValid(capsule, b'dltensor'):
        raise ValueError('the producer did not return an unconsumed DLPack capsule')
    managed = _DLManagedTensor.from_address(_api.PyCapsule_GetPointer(capsule, b'dltensor'))
    t = managed.dl_tensor
    shape = [t.shape[i] for i in range(t.ndim)]
    itemsize = t.dtype.bits * t.dtype.lanes // 8
    if t.strides:
        expected = 1  # DLPack strides count elements
        for i in reversed(range(t.ndim)):
            if shape[i] != 1 and t.strides[i] != expected:
                raise ValueError(f'CudaBuffer.from_dlpack needs a C-contiguous tensor, got '
                                 f'shape {shape} strides {[t.strides[j] for j in range(t.ndim)]}'
                                 ': call .contiguous() first')
            expected *= shape[i]
    nbytes = itemsize
    for n in shape:
        nbytes *= n
    return (t.data or 0) + t.byte_offset, nbytes


def _release_capsule(capsule: Any) -> None:
    """Consume the capsule as a DLPack consumer does: its deleter runs now, once."""
    if not _api.PyCapsule_IsValid(capsule, b'dltensor'):
        return
    pointer = _api.PyCapsule_GetPointer(capsule, b'dltensor')
    _api.PyCapsule_SetName(capsule, _USED)
    managed = ctypes.cast(pointer, ctypes.POINTER(_DLManagedTensor))
    if managed.contents.deleter:
        managed.contents.deleter(managed)
