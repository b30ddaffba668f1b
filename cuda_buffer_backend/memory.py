"""GPU memory as a medium of the demo backend's machinery (:class:`CudaMedium`).

A slot is two things handed over together (two descriptors in one handover record):

- a *control* segment, a sealed memfd header as the demo backend makes them
  (:class:`demo_buffer_backend.memory.Segment` without data): it records the capacity, the
  generation and the bytes published, carries the hold locks (a subscriber's views keep a shared
  lock; the publisher reuses the slot only under the exclusive one), and holds this medium's
  record (:data:`RECORD`): the UUID of the device and the handle of the slot's interprocess event;
- the *device* allocation, made with ``cuMemCreate`` and exported as a POSIX file descriptor; a
  subscriber imports it, maps it read-only on its own address range and closes the descriptor
  (the mapping keeps the memory; the kernel and the driver free it with the last one).

The publisher records the slot's event after its writes (:meth:`DeviceSegment.record`); a reader
makes its stream wait for it before reading. A reader's hold is let go only once the reads it
queued are complete (:meth:`CudaMedium.fence`), so a slot is never rewritten under a kernel.
"""
import os
import struct
import threading
from typing import Dict, List, Optional, Sequence, Tuple

from demo_buffer_backend import memory

from cuda_buffer_backend import driver as cuda

#: This medium's record in the control header, after the demo header: device UUID, event handle.
RECORD = struct.Struct(f'<8s{cuda.UUID_SIZE}s{cuda.IPC_HANDLE_SIZE}s')
RECORD_OFFSET = 64
RECORD_MAGIC = b'RBPYCUDA'
#: Interprocess handle -> event, of the slots this process created: an in-process reader uses
#: the event itself (a process does not open its own handles).
_own_events: Dict[bytes, int] = {}


class DeviceRange:
    """``nbytes`` of device memory at ``address`` on ``device`` (a local ordinal): what a slot's
    ``data`` is; slicing gives a sub-range (as a memoryview's would)."""

    __slots__ = ('address', 'nbytes', 'device', 'event')

    def __init__(self, address: int, nbytes: int, device: int,
                 event: Optional[int] = None) -> None:
        self.address = address
        self.nbytes = nbytes
        self.device = device
        self.event = event  #: the event readers wait for (received memory), else None

    def __getitem__(self, index: slice) -> 'DeviceRange':
        start, stop, step = index.indices(self.nbytes)
        if step != 1:
            raise ValueError('device memory is sliced contiguously only')
        return DeviceRange(self.address + start, max(0, stop - start), self.device, self.event)

    def __len__(self) -> int:
        return self.nbytes


class DeviceSegment:
    """A slot this process created: its control segment and its device allocation, mapped
    read-write here, and the slot's interprocess event."""

    __slots__ = ('control', 'fd', 'map', 'capacity', 'data', 'device', 'handle', 'event',
                 'event_handle', 'staging', '_driver')

    def __init__(self, capacity: int, device: int, uuid: bytes, granularity: int) -> None:
        drv = cuda.load()
        self._driver = drv
        self.capacity = capacity
        self.device = device
        self.handle = self.event = self.event_handle = None
        self.staging: Optional[int] = None  #: page-locked host copy, made on first need
        self.control = memory.Segment(capacity, with_data=False)
        self.fd = self.control.fd
        self.map = self.control.map
        try:
            with drv.on(device):
                try:
                    self.handle = drv.mem_create(capacity, device)
                except cuda.OutOfMemory as exc:
                    raise MemoryError(f'no device memory for a {capacity}-byte slot: {exc}') \
                        from None
                address = drv.map(self.handle, capacity, device, granularity, readonly=False)
                self.data = DeviceRange(address, capacity, device)
                self.event = drv.event_create(interprocess=True)
                handle = self.event_handle = drv.ipc_event_handle(self.event)
                _own_events[handle] = self.event
        except BaseException:
            self.close()
            raise
        RECORD.pack_into(self.map, RECORD_OFFSET, RECORD_MAGIC, uuid, handle)

    def set_generation(self, generation: int, size: int) -> None:
        self.control.set_generation(generation, size)

    def reader_fds(self) -> List[int]:
        """A reader description of the control segment and a new descriptor of the device
        allocation (the caller closes both)."""
        fd = self.control.reader_fd()
        try:
            with self._driver.on(self.device):
                return [fd, self._driver.export_fd(self.handle)]
        except BaseException:
            os.close(fd)
            raise

    def record(self, stream: int) -> None:
        """Mark the writes queued on ``stream`` so far as what readers wait for."""
        with self._driver.on(self.device):
            self._driver.event_record(self.event, stream)

    def host_copy(self, nbytes: int, stream: int) -> memoryview:
        """The first ``nbytes`` copied to page-locked host memory after the writes queued on
        ``stream`` (one copy; the view is valid until the next call or the slot's removal)."""
        drv = self._driver
        with drv.on(self.device):
            if self.staging is None:
                self.staging = drv.host_alloc(self.capacity)
            drv.copy_to_host(self.staging, self.data.address, nbytes, stream)
            drv.stream_synchronize(stream)
        return _host_view(self.staging, nbytes)

    def close(self) -> None:
        drv = self._driver
        try:
            with drv.on(self.device):
                if getattr(self, 'data', None) is not None:
                    drv.unmap(self.data.address, self.capacity)
                    self.data = None
                if self.handle is not None:
                    drv.mem_release(self.handle)
                    self.handle = None
                if self.event is not None:
                    _own_events.pop(self.event_handle, None)
                    drv.event_destroy(self.event)
                    self.event = None
                if self.staging is not None:
                    drv.host_free(self.staging)
                    self.staging = None
        except cuda.CudaError:
            pass  # the context is gone (the process is exiting): the driver frees everything
        self.control.close()


class DeviceReceived:
    """A slot of another process (or ours), imported and mapped read-only on this process's
    device that has its UUID."""

    __slots__ = ('control', 'fd', 'map', 'capacity', 'data', 'device', '_driver', '_own_event')

    def __init__(self, fds: Sequence[int], capacity: int, devices: Dict[bytes, int],
                 granularity: int) -> None:
        control = memory.open_received(fds[0], capacity, with_data=False)
        magic, uuid, event_handle = RECORD.unpack_from(control.map, RECORD_OFFSET)
        if magic != RECORD_MAGIC:
            control.map.close()
            raise ValueError(f'its control header has no CUDA record (magic {magic!r})')
        device = devices.get(uuid)
        if device is None:
            control.map.close()
            raise ValueError(f'it lives on GPU {uuid.hex()}, which this process does not see')
        if capacity % granularity:
            control.map.close()
            raise ValueError(f'capacity {capacity} is not a multiple of the allocation '
                             f'granularity {granularity}')
        drv = self._driver = cuda.load()
        self.control = control
        self.fd = control.fd
        self.map = control.map
        self.capacity = capacity
        self.device = device
        self.data = None
        handle = None
        try:
            with drv.on(device):
                try:
                    handle = drv.import_fd(fds[1])
                    address = drv.map(handle, capacity, device, granularity, readonly=True)
                    own = _own_events.get(event_handle)
                    try:
                        event = own if own is not None else drv.ipc_open_event(event_handle)
                    except cuda.CudaError:
                        drv.unmap(address, capacity)
                        raise
                    self._own_event = own is not None
                finally:
                    if handle is not None:
                        drv.mem_release(handle)  # the mapping keeps the memory
        except cuda.OutOfMemory as exc:
            control.map.close()
            raise OSError(12, f'cannot map it on device {device}: {exc}') from None
        except cuda.CudaError as exc:
            control.map.close()
            raise ValueError(f'the driver refused it: {exc}') from None
        os.close(fds[1])
        self.data = DeviceRange(address, capacity, device, event)

    def close(self) -> None:
        drv = self._driver
        if self.data is not None:
            try:
                with drv.on(self.device):
                    drv.unmap(self.data.address, self.capacity)
                    if not self._own_event:
                        drv.event_destroy(self.data.event)
            except cuda.CudaError:
                pass  # the context is gone: the driver frees everything with it
            self.data = None
        self.control.close()


class Fence:
    """Events recorded on the streams that read a slot: done when all of them are."""

    __slots__ = ('events', '_driver')

    def __init__(self, drv: cuda.Driver, events: List[Tuple[int, int]]) -> None:
        self._driver = drv
        self.events = events  #: (device, event) pairs still pending

    def done(self) -> bool:
        drv = self._driver
        while self.events:
            device, event = self.events[-1]
            with drv.on(device):
                if not drv.event_done(event):
                    return False
            self.events.pop()
            _free_events.give(device, event)
        return True


class _EventStock:
    """Events for fences, reused (creating one costs more than recording it)."""

    def __init__(self) -> None:
        self._free: Dict[int, List[int]] = {}
        self._lock = threading.Lock()

    def take(self, drv: cuda.Driver, device: int) -> int:
        """An event of ``device``'s context (call it in that context)."""
        with self._lock:
            free = self._free.get(device)
            if free:
                return free.pop()
        return drv.event_create()

    def give(self, device: int, event: int) -> None:
        with self._lock:
            self._free.setdefault(device, []).append(event)


_free_events = _EventStock()


def _host_view(address: int, nbytes: int) -> memoryview:
    import ctypes
    return memoryview((ctypes.c_char * nbytes).from_address(address)).cast('B')


class CudaMedium:
    """Slots in one GPU's memory (see :class:`demo_buffer_backend.memory.SharedMemory` for
    what a medium is)."""

    name = 'cuda'
    descriptor_magic = b'RBCU'
    fds_per_segment = 2

    def __init__(self, device: int) -> None:
        """Device queries only: no CUDA context is made until a slot is (a process that only
        advertises the backend, or only listens, never pays for one)."""
        drv = cuda.load()
        self.device = device
        self._granularity: Optional[int] = None
        self.uuid = drv.uuid(device)
        #: every device this process sees, by UUID (a publisher's device is named by its UUID)
        self.devices = {drv.uuid(d): d for d in range(drv.device_count())}

    @property
    def granularity(self) -> int:
        """The device's VMM allocation granularity (its primary context made on first use)."""
        if self._granularity is None:
            drv = cuda.load()
            with drv.on(self.device):
                self._granularity = drv.granularity(self.device)
        return self._granularity

    def round_capacity(self, nbytes: int) -> int:
        g = self.granularity
        return max(g, -(-nbytes // g) * g)

    def fits(self, capacity: int, nbytes: int) -> bool:
        return nbytes <= capacity <= 2 * max(nbytes, self.granularity)

    def create(self, capacity: int) -> DeviceSegment:
        try:
            return DeviceSegment(capacity, self.device, self.uuid, self.granularity)
        except MemoryError as exc:
            raise OSError(12, str(exc)) from None  # ENOMEM: the pool falls back, counted
        except cuda.CudaError as exc:
            raise OSError(5, f'cannot create a device slot: {exc}') from None

    def open_received(self, fds: Sequence[int], capacity: int) -> DeviceReceived:
        return DeviceReceived(fds, capacity, self.devices, self.granularity)

    def fence(self, readers) -> Optional[Fence]:
        """Events recorded now on the streams in ``readers`` (``(device, stream)`` pairs)."""
        drv = cuda.load()
        events = []
        for device, stream in readers:
            with drv.on(device):
                event = _free_events.take(drv, device)
                drv.event_record(event, stream)
                events.append((device, event))
        return Fence(drv, events) if events else None
