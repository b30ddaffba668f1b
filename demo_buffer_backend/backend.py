"""DemoBackend: the ``demo`` buffer backend plugin (entry point
``demo = demo_buffer_backend:DemoBackend``)."""
import threading
from typing import Dict, List, Mapping, Optional, Sequence, Set, Tuple

from rosidl_buffer_py.backend import BufferBackend, EndpointInfo
from rosidl_buffer_py.buffer import Buffer

from demo_buffer_backend import pool, presence, shm
from demo_buffer_backend.buffer import BACKEND_TYPE, DemoBuffer


_UNKNOWN = object()


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
        self._domain = shm.domain_metadata()
        self._lock = threading.Lock()
        #: Compatible peers: gid -> presence token of their process (None: none advertised).
        self._peers: Dict[bytes, Optional[str]] = {}
        pool.get_state().start()

    def get_backend_type(self) -> str:
        return BACKEND_TYPE

    def get_backend_metadata(self) -> str:
        """``<domain>.<token>``: the shm domain ``shm1.<boot id>.<st_dev>.<st_ino of
        /dev/shm>.<euid>`` (hex; equal domains open the same segments), then this process's
        presence token ``<pid>_<16 hex>`` (see :mod:`.presence`; its presence file is created
        here). Just the domain when the presence file cannot be created."""
        token = pool.get_state().presence_token()
        return f'{self._domain}.{token}' if token else self._domain

    def parse_metadata(self, metadata: Optional[str]) -> Tuple[bool, Optional[str]]:
        """``(same shm domain, presence token or None)`` of a peer's metadata."""
        if not isinstance(metadata, str):
            return False, None
        if metadata == self._domain:
            return True, None  # a peer that advertises no token (it is never taken for dead)
        domain, _, token = metadata.rpartition('.')
        token = presence.parse_token(token)
        if domain != self._domain or token is None:
            return False, None
        return True, token

    def on_discovering_endpoint(
            self, endpoint_info: EndpointInfo, existing_endpoints: Sequence[EndpointInfo],
            endpoint_supported_backends: Mapping[str, str]) -> Tuple[bool, List[Set[int]]]:
        """Compatible iff the peer's shm domain is ours (its token may differ: it names its
        process); its token is remembered to address its descriptors."""
        compatible, token = self.parse_metadata(endpoint_supported_backends.get(BACKEND_TYPE))
        with self._lock:
            if compatible:
                self._peers[endpoint_info.gid] = token
            else:
                self._peers.pop(endpoint_info.gid, None)
        return compatible, []

    def on_removing_endpoint(self, endpoint_info: EndpointInfo) -> None:
        """Forget the peer; its process's liveness is tested afresh the next time a slot with
        descriptors for it is considered. Descriptors still in flight to a live process keep
        their protection (this hook also runs when *our* endpoint goes away)."""
        with self._lock:
            token = self._peers.pop(endpoint_info.gid, None)
        if token is not None:
            pool.get_state().forget_liveness(token)

    def is_compatible(self, endpoint_info: EndpointInfo) -> bool:
        """Whether the endpoint was discovered and shares our shm domain."""
        return endpoint_info.gid in self._peers

    def peer_token(self, endpoint_info: EndpointInfo) -> Optional[str]:
        """The presence token a compatible peer advertised (None: unknown peer or no token)."""
        return self._peers.get(endpoint_info.gid)

    def create_descriptor_with_endpoint(self, buffer: Buffer,
                                        endpoint_info: EndpointInfo) -> Optional[bytes]:
        state = pool.get_state()
        recipient = self._peers.get(endpoint_info.gid, _UNKNOWN)
        if (recipient is _UNKNOWN
                or not isinstance(buffer, DemoBuffer) or not isinstance(buffer._keepalive,
                                                                         pool.Pin)):
            # Unknown or incompatible peer, private (fallback) memory, or a received buffer
            # (republishing one would let the original publisher reuse it under the new peer).
            state.decline()
            return None
        return state.describe(buffer._keepalive, recipient)

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
