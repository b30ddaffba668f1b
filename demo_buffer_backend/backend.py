"""DemoBackend: the ``demo`` buffer backend plugin (entry point
``demo = demo_buffer_backend:DemoBackend``)."""
import threading
from typing import Dict, List, Mapping, Optional, Sequence, Set, Tuple

from rosidl_buffer_py.backend import BufferBackend, EndpointInfo
from rosidl_buffer_py.buffer import Buffer

from demo_buffer_backend import pool, shm
from demo_buffer_backend.buffer import BACKEND_TYPE, DemoBuffer


class DemoBackend(BufferBackend):
    """Payloads in POSIX shared memory; a ~70-byte descriptor crosses the middleware.

    Every instance shares the process-wide pool and mapping cache (:mod:`.pool`). The keyword
    arguments, when given, set the process-wide limits (see :func:`demo_buffer_backend.configure`).
    Creating the first instance of a process removes segments left by dead processes.
    """

    def __init__(self, *, max_pool_bytes: Optional[int] = None, max_slots: Optional[int] = None,
                 reclaim_timeout: Optional[float] = None) -> None:
        if (max_pool_bytes, max_slots, reclaim_timeout) != (None, None, None):
            pool.configure(max_pool_bytes=max_pool_bytes, max_slots=max_slots,
                           reclaim_timeout=reclaim_timeout)
        self._metadata = shm.domain_metadata()
        self._lock = threading.Lock()
        self._compatible: Dict[bytes, bool] = {}
        pool.get_state().start()

    def get_backend_type(self) -> str:
        return BACKEND_TYPE

    def get_backend_metadata(self) -> str:
        """``shm1.<boot id>.<st_dev>.<st_ino of /dev/shm>.<euid>`` (hex): equal metadata means the
        peer opens the same segments."""
        return self._metadata

    def on_discovering_endpoint(
            self, endpoint_info: EndpointInfo, existing_endpoints: Sequence[EndpointInfo],
            endpoint_supported_backends: Mapping[str, str]) -> Tuple[bool, List[Set[int]]]:
        compatible = endpoint_supported_backends.get(BACKEND_TYPE) == self._metadata
        with self._lock:
            self._compatible[endpoint_info.gid] = compatible
        return compatible, []

    def on_removing_endpoint(self, endpoint_info: EndpointInfo) -> None:
        with self._lock:
            self._compatible.pop(endpoint_info.gid, None)

    def is_compatible(self, endpoint_info: EndpointInfo) -> bool:
        """Whether the endpoint was discovered and shares our shm domain."""
        return self._compatible.get(endpoint_info.gid, False)

    def create_descriptor_with_endpoint(self, buffer: Buffer,
                                        endpoint_info: EndpointInfo) -> Optional[bytes]:
        state = pool.get_state()
        if (not self._compatible.get(endpoint_info.gid, False)
                or not isinstance(buffer, DemoBuffer) or not isinstance(buffer._keepalive,
                                                                         pool.Pin)):
            # Unknown or incompatible peer, private (fallback) memory, or a received buffer
            # (republishing one would let the original publisher reuse it under the new peer).
            state.decline()
            return None
        return state.describe(buffer._keepalive)

    def from_descriptor_with_endpoint(self, descriptor: bytes,
                                      endpoint_info: EndpointInfo) -> DemoBuffer:
        view, hold = pool.get_state().open_descriptor(descriptor)
        return DemoBuffer(view, keepalive=hold)

    def allocate(self, nbytes: int) -> DemoBuffer:
        return DemoBuffer.allocate(nbytes)

    def stats(self) -> dict:
        """Process-wide counters (see :func:`demo_buffer_backend.stats`)."""
        return pool.stats()

    def close(self) -> None:
        """Remove every segment this process created and close every mapping (process-wide:
        shared by all instances; the backend stays usable and starts afresh on next use)."""
        pool.shutdown()
