"""The CUDA driver API through ``ctypes``: the calls this backend makes, nothing else.

The driver (``libcuda.so.1``) is the one stable binary interface every CUDA program shares: no
toolkit, no ``cuda-bindings`` wheel, no version of torch or CuPy is needed. Every call runs in
the device's *primary* context, the one torch, CuPy and the runtime API use, so that pointers,
streams and events are the same objects as theirs.

:func:`load` says once per process whether a driver and a device are there
(:class:`Unavailable` names why not); :class:`CudaError` names the failed call and the driver's
error.
"""
import ctypes
import threading
from typing import Dict, Optional

CUDA_SUCCESS = 0
CUDA_ERROR_OUT_OF_MEMORY = 2
CUDA_ERROR_NOT_READY = 600
#: ``CU_STREAM_LEGACY`` and ``CU_STREAM_PER_THREAD``: the same values as DLPack's stream 1 and 2.
STREAM_LEGACY = 1
STREAM_PER_THREAD = 2
EVENT_DISABLE_TIMING = 0x2
EVENT_INTERPROCESS = 0x4
STREAM_NON_BLOCKING = 0x1
MEM_ALLOCATION_TYPE_PINNED = 1
MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR = 1
MEM_LOCATION_TYPE_DEVICE = 1
MEM_ALLOC_GRANULARITY_MINIMUM = 0
MEM_ACCESS_PROT_READ = 1
MEM_ACCESS_PROT_READWRITE = 3
IPC_HANDLE_SIZE = 64
UUID_SIZE = 16


class Unavailable(Exception):
    """No CUDA driver or no device in this process (the message says which)."""


class CudaError(RuntimeError):
    """A driver call failed: ``call`` and ``code`` (a ``CUresult``) name it."""

    def __init__(self, call: str, code: int, name: str) -> None:
        super().__init__(f'{call} failed: {name} ({code})')
        self.call = call
        self.code = code


class OutOfMemory(CudaError, MemoryError):
    """The device has no memory for the request."""


class _Location(ctypes.Structure):
    _fields_ = [('type', ctypes.c_int), ('id', ctypes.c_int)]


class _AllocFlags(ctypes.Structure):
    _fields_ = [('compressionType', ctypes.c_ubyte), ('gpuDirectRDMACapable', ctypes.c_ubyte),
                ('usage', ctypes.c_ushort), ('reserved', ctypes.c_ubyte * 4)]


class _AllocationProp(ctypes.Structure):
    """``CUmemAllocationProp``."""

    _fields_ = [('type', ctypes.c_int), ('requestedHandleTypes', ctypes.c_int),
                ('location', _Location), ('win32HandleMetaData', ctypes.c_void_p),
                ('allocFlags', _AllocFlags)]


class _AccessDesc(ctypes.Structure):
    """``CUmemAccessDesc``."""

    _fields_ = [('location', _Location), ('flags', ctypes.c_int)]


class IpcEventHandle(ctypes.Structure):
    """``CUipcEventHandle``: 64 opaque bytes."""

    _fields_ = [('reserved', ctypes.c_char * IPC_HANDLE_SIZE)]


class _Uuid(ctypes.Structure):
    _fields_ = [('bytes', ctypes.c_char * UUID_SIZE)]


_u64 = ctypes.c_uint64
_size = ctypes.c_size_t
_ptr = ctypes.c_void_p
_int = ctypes.c_int
_uint = ctypes.c_uint

#: name -> argument types; each returns ``CUresult``. ``_v2`` names are the current ABI.
_SIGNATURES = {
    'cuInit': [_uint],
    'cuGetErrorName': [_int, ctypes.POINTER(ctypes.c_char_p)],
    'cuDeviceGetCount': [ctypes.POINTER(_int)],
    'cuDeviceGet': [ctypes.POINTER(_int), _int],
    'cuDeviceGetUuid': [ctypes.POINTER(_Uuid), _int],
    'cuDevicePrimaryCtxRetain': [ctypes.POINTER(_ptr), _int],
    'cuCtxPushCurrent_v2': [_ptr],
    'cuCtxPopCurrent_v2': [ctypes.POINTER(_ptr)],
    'cuMemGetAllocationGranularity': [ctypes.POINTER(_size), ctypes.POINTER(_AllocationProp),
                                      _int],
    'cuMemCreate': [ctypes.POINTER(_u64), _size, ctypes.POINTER(_AllocationProp), _u64],
    'cuMemRelease': [_u64],
    'cuMemExportToShareableHandle': [_ptr, _u64, _int, _u64],
    'cuMemImportFromShareableHandle': [ctypes.POINTER(_u64), _ptr, _int],
    'cuMemAddressReserve': [ctypes.POINTER(_u64), _size, _size, _u64, _u64],
    'cuMemAddressFree': [_u64, _size],
    'cuMemMap': [_u64, _size, _size, _u64, _u64],
    'cuMemUnmap': [_u64, _size],
    'cuMemSetAccess': [_u64, _size, ctypes.POINTER(_AccessDesc), _size],
    'cuMemAlloc_v2': [ctypes.POINTER(_u64), _size],
    'cuMemFree_v2': [_u64],
    'cuMemHostAlloc': [ctypes.POINTER(_ptr), _size, _uint],
    'cuMemFreeHost': [_ptr],
    'cuMemcpyDtoHAsync_v2': [_ptr, _u64, _size, _ptr],
    'cuMemcpyHtoDAsync_v2': [_u64, _ptr, _size, _ptr],
    'cuMemcpyDtoDAsync_v2': [_u64, _u64, _size, _ptr],
    'cuEventCreate': [ctypes.POINTER(_ptr), _uint],
    'cuEventDestroy_v2': [_ptr],
    'cuEventRecord': [_ptr, _ptr],
    'cuEventQuery': [_ptr],
    'cuEventSynchronize': [_ptr],
    'cuIpcGetEventHandle': [ctypes.POINTER(IpcEventHandle), _ptr],
    'cuIpcOpenEventHandle': [ctypes.POINTER(_ptr), IpcEventHandle],
    'cuStreamCreate': [ctypes.POINTER(_ptr), _uint],
    'cuStreamDestroy_v2': [_ptr],
    'cuStreamWaitEvent': [_ptr, _ptr, _uint],
    'cuStreamSynchronize': [_ptr],
}


#: Calls whose ``_v2`` symbol, where the driver has one, is the one to use.
_PREFER_V2 = frozenset({'cuDeviceGetUuid'})


class Driver:
    """The loaded driver: one method per call used, each raising :class:`CudaError`."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        self._lib = lib
        self._fn = {}
        for name, argtypes in _SIGNATURES.items():
            # the newest ABI of a call where the driver has several (cuDeviceGetUuid_v2)
            fn = getattr(lib, name + '_v2', None) if not name.endswith('_v2') else None
            fn = fn if fn is not None and name in _PREFER_V2 else getattr(lib, name)
            fn.argtypes = argtypes
            fn.restype = _int
            self._fn[name] = fn
        self._contexts: Dict[int, int] = {}
        self._lock = threading.Lock()

    def check(self, name: str, *args) -> None:
        code = self._fn[name](*args)
        if code != CUDA_SUCCESS:
            raise self.error(name, code)

    def error(self, name: str, code: int) -> CudaError:
        text = ctypes.c_char_p()
        if self._fn['cuGetErrorName'](code, ctypes.byref(text)) == CUDA_SUCCESS and text.value:
            label = text.value.decode(errors='replace')
        else:
            label = 'unknown error'
        kind = OutOfMemory if code == CUDA_ERROR_OUT_OF_MEMORY else CudaError
        return kind(name, code, label)

    # --- devices and contexts -------------------------------------------------------------------
    def device_count(self) -> int:
        count = _int()
        self.check('cuDeviceGetCount', ctypes.byref(count))
        return count.value

    def uuid(self, device: int) -> bytes:
        """The device's 16-byte UUID: what names it across processes, whatever their
        ``CUDA_VISIBLE_DEVICES``."""
        dev = _int()
        self.check('cuDeviceGet', ctypes.byref(dev), device)
        uuid = _Uuid()
        self.check('cuDeviceGetUuid', ctypes.byref(uuid), dev.value)
        return bytes(uuid.bytes).ljust(UUID_SIZE, b'\0')

    def context(self, device: int) -> int:
        """The device's primary context (retained once per process)."""
        ctx = self._contexts.get(device)
        if ctx is None:
            with self._lock:
                ctx = self._contexts.get(device)
                if ctx is None:
                    dev = _int()
                    self.check('cuDeviceGet', ctypes.byref(dev), device)
                    handle = _ptr()
                    self.check('cuDevicePrimaryCtxRetain', ctypes.byref(handle), dev.value)
                    ctx = self._contexts[device] = handle.value
        return ctx

    def on(self, device: int) -> '_Current':
        """``with driver.on(device):`` runs driver calls in the device's primary context."""
        return _Current(self, self.context(device))

    # --- virtual memory management (VMM) --------------------------------------------------------
    def _prop(self, device: int) -> _AllocationProp:
        prop = _AllocationProp()
        prop.type = MEM_ALLOCATION_TYPE_PINNED
        prop.requestedHandleTypes = MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR
        prop.location.type = MEM_LOCATION_TYPE_DEVICE
        prop.location.id = device
        return prop

    def granularity(self, device: int) -> int:
        size = _size()
        prop = self._prop(device)
        self.check('cuMemGetAllocationGranularity', ctypes.byref(size), ctypes.byref(prop),
                   MEM_ALLOC_GRANULARITY_MINIMUM)
        return size.value

    def mem_create(self, nbytes: int, device: int) -> int:
        handle = _u64()
        prop = self._prop(device)
        self.check('cuMemCreate', ctypes.byref(handle), nbytes, ctypes.byref(prop), 0)
        return handle.value

    def mem_release(self, handle: int) -> None:
        self.check('cuMemRelease', handle)

    def export_fd(self, handle: int) -> int:
        """A new file descriptor of the allocation (the caller closes it)."""
        fd = _int(-1)
        self.check('cuMemExportToShareableHandle', ctypes.addressof(fd), handle,
                   MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR, 0)
        return fd.value

    def import_fd(self, fd: int) -> int:
        """The allocation behind ``fd`` (the caller still closes ``fd``)."""
        handle = _u64()
        self.check('cuMemImportFromShareableHandle', ctypes.byref(handle), _ptr(fd),
                   MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR)
        return handle.value

    def map(self, handle: int, nbytes: int, device: int, alignment: int,
            readonly: bool) -> int:
        """Reserve an address range, map the allocation there and give ``device`` access to
        it (read-only when asked and supported); return its address."""
        address = _u64()
        self.check('cuMemAddressReserve', ctypes.byref(address), nbytes, alignment, 0, 0)
        try:
            self.check('cuMemMap', address.value, nbytes, 0, handle, 0)
            try:
                access = _AccessDesc()
                access.location.type = MEM_LOCATION_TYPE_DEVICE
                access.location.id = device
                access.flags = MEM_ACCESS_PROT_READ if readonly else MEM_ACCESS_PROT_READWRITE
                try:
                    self.check('cuMemSetAccess', address.value, nbytes, ctypes.byref(access), 1)
                except CudaError:
                    if not readonly:
                        raise
                    access.flags = MEM_ACCESS_PROT_READWRITE  # read-only is not supported here
                    self.check('cuMemSetAccess', address.value, nbytes, ctypes.byref(access), 1)
            except BaseException:
                self._fn['cuMemUnmap'](address.value, nbytes)
                raise
        except BaseException:
            self._fn['cuMemAddressFree'](address.value, nbytes)
            raise
        return address.value

    def unmap(self, address: int, nbytes: int) -> None:
        self.check('cuMemUnmap', address, nbytes)
        self.check('cuMemAddressFree', address, nbytes)

    # --- plain memory ----------------------------------------------------------------------------
    def mem_alloc(self, nbytes: int) -> int:
        address = _u64()
        self.check('cuMemAlloc_v2', ctypes.byref(address), max(1, nbytes))
        return address.value

    def mem_free(self, address: int) -> None:
        self.check('cuMemFree_v2', address)

    def host_alloc(self, nbytes: int) -> int:
        """Page-locked host memory (fast device-to-host copies)."""
        address = _ptr()
        self.check('cuMemHostAlloc', ctypes.byref(address), max(1, nbytes), 0)
        return address.value

    def host_free(self, address: int) -> None:
        self.check('cuMemFreeHost', address)

    def copy_to_host(self, dst: int, src: int, nbytes: int, stream: int) -> None:
        self.check('cuMemcpyDtoHAsync_v2', dst, src, nbytes, stream)

    def copy_to_device(self, dst: int, src: int, nbytes: int, stream: int) -> None:
        self.check('cuMemcpyHtoDAsync_v2', dst, src, nbytes, stream)

    def copy_on_device(self, dst: int, src: int, nbytes: int, stream: int) -> None:
        self.check('cuMemcpyDtoDAsync_v2', dst, src, nbytes, stream)

    # --- events and streams ----------------------------------------------------------------------
    def event_create(self, interprocess: bool = False) -> int:
        event = _ptr()
        flags = EVENT_DISABLE_TIMING | (EVENT_INTERPROCESS if interprocess else 0)
        self.check('cuEventCreate', ctypes.byref(event), flags)
        return event.value

    def event_destroy(self, event: int) -> None:
        self.check('cuEventDestroy_v2', event)

    def event_record(self, event: int, stream: int) -> None:
        self.check('cuEventRecord', event, stream)

    def event_done(self, event: int) -> bool:
        code = self._fn['cuEventQuery'](event)
        if code == CUDA_SUCCESS:
            return True
        if code == CUDA_ERROR_NOT_READY:
            return False
        raise self.error('cuEventQuery', code)

    def event_synchronize(self, event: int) -> None:
        self.check('cuEventSynchronize', event)

    def ipc_event_handle(self, event: int) -> bytes:
        handle = IpcEventHandle()
        self.check('cuIpcGetEventHandle', ctypes.byref(handle), event)
        return ctypes.string_at(ctypes.addressof(handle), IPC_HANDLE_SIZE)

    def ipc_open_event(self, raw: bytes) -> int:
        handle = IpcEventHandle.from_buffer_copy(raw)
        event = _ptr()
        self.check('cuIpcOpenEventHandle', ctypes.byref(event), handle)
        return event.value

    def stream_create(self) -> int:
        stream = _ptr()
        self.check('cuStreamCreate', ctypes.byref(stream), STREAM_NON_BLOCKING)
        return stream.value

    def stream_wait(self, stream: int, event: int) -> None:
        self.check('cuStreamWaitEvent', stream, event, 0)

    def stream_synchronize(self, stream: int) -> None:
        self.check('cuStreamSynchronize', stream)


class _Current:
    """Pushes a context for the calls of a ``with`` block, and pops it after."""

    __slots__ = ('driver', 'ctx')

    def __init__(self, driver: Driver, ctx: int) -> None:
        self.driver = driver
        self.ctx = ctx

    def __enter__(self) -> None:
        self.driver.check('cuCtxPushCurrent_v2', self.ctx)

    def __exit__(self, *exc) -> None:
        popped = _ptr()
        self.driver.check('cuCtxPopCurrent_v2', ctypes.byref(popped))


_driver: Optional[Driver] = None
_unavailable: Optional[str] = None
_load_lock = threading.Lock()


def load() -> Driver:
    """The driver, loaded and initialised on first use; :class:`Unavailable` when this process
    has no CUDA driver or no device (decided once)."""
    global _driver, _unavailable
    if _driver is not None:
        return _driver
    with _load_lock:
        if _driver is None and _unavailable is None:
            try:
                lib = ctypes.CDLL('libcuda.so.1')
            except OSError as exc:
                _unavailable = f'no CUDA driver (libcuda.so.1: {exc})'
            else:
                try:
                    driver = Driver(lib)
                except AttributeError as exc:
                    _unavailable = f'the CUDA driver is too old for this backend: {exc}'
                else:
                    code = driver._fn['cuInit'](0)
                    if code != CUDA_SUCCESS:
                        _unavailable = f'CUDA driver not usable: {driver.error("cuInit", code)}'
                    elif driver.device_count() < 1:
                        _unavailable = 'the CUDA driver sees no device'
                    else:
                        _driver = driver
        if _driver is None:
            raise Unavailable(_unavailable)
        return _driver
