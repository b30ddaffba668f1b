"""DemoBackend: the ``demo`` buffer backend plugin (entry point
``demo = demo_buffer_backend:DemoBackend``)."""
import threading
from typing import Dict, List, Mapping, Optional, Sequence, Set, Tuple

from rosidl_buffer_py.backend import BufferBackend, EndpointInfo
from rosidl_buffer_py.buffer import Buffer

from demo_buffer_backend import pool, presence, shm

_UNKNOWN = object()
from demo_buffer_backend.buffer import BACKEND_TYPE, DemoBuffer


def _depth_of(endpoint_info: EndpointInfo) -> int:
    """The KEEP_LAST depth that bounds what the peer can take on one channel; 0 for KEEP_ALL,
    unknown, or when the local publisher is not named (its window would count other channels'
    messages)."""
    if getattr(endpoint_info, 'local_gid', None) is None:
        return 0
    return getattr(endpoint_info, 'history_depth', None) or 0


def _ledger_key(endpoint_info: EndpointInfo) -> Tuple[bytes, Optional[bytes]]:
    """One ledger per (peer, local publisher) when the publisher is named."""
    return endpoint_info.gid, getattr(endpoint_info, 'local_gid', None)


class DemoBackend(BufferBackend):
    """Payloads in POSIX shared memory; a ~70-byte descriptor crosses the middleware.

    Every instance shares the process-wide pool and mapping cache (:mod:`.pool`). The keyword
    arguments, when given, set the process-wide limits (see :func:`demo_buffer_backend.configure`).
    Creating the first instance of a process removes segments left by dead processes and starts
    the housekeeping thread that keeps doing so.

    Fairness: every compatible peer has a ledger of its descriptors in flight (see
    :mod:`.pool`, "Fairness"). ``create_descriptor_with_endpoint`` returns None, so that this
    peer alone gets CPU bytes, when the peer is dead or not of our user, or has not taken
    anything for ``pool.IDLE_SECONDS``; descriptors past its share of the pool are reclaimed
    first when the pool is full. Its KEEP_LAST depth (``EndpointInfo.history_depth``, applied
    when the publisher also names itself in ``EndpointInfo.local_gid``) lets descriptors it can
    no longer take stop pinning their slots.
    """

    def __init__(self, *, max_pool_bytes: Optional[int] = None, max_slots: Optional[int] = None,
                 reclaim_timeout: Optional[float] = None,
                 max_inflight_per_peer: Optional[int] = None) -> None:
        if (max_pool_bytes, max_slots, reclaim_timeout, max_inflight_per_peer) != \
                (None, None, None, None):
            pool.configure(max_pool_bytes=max_pool_bytes, max_slots=max_slots,
                           reclaim_timeout=reclaim_timeout,
                           max_inflight_per_peer=max_inflight_per_peer)
        self._domain = shm.domain_metadata()
        self._lock = threading.Lock()
        #: Compatible peers: gid -> presence token of their process (None: none advertised).
        self._peers: Dict[bytes, Optional[str]] = {}
        #: Compatible peers: (gid, local publisher gid or None) -> ledger of their descriptors
        #: in flight (created on first use: discovery does not say which publisher asks).
        self._ledgers: Dict[Tuple[bytes, Optional[bytes]], pool.PeerLedger] = {}
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
                if self._peers.get(endpoint_info.gid, token) != token:
                    self._forget_ledgers(endpoint_info.gid)  # another process now
                self._peers[endpoint_info.gid] = token
            else:
                self._peers.pop(endpoint_info.gid, None)
                self._forget_ledgers(endpoint_info.gid)
        return compatible, []

    def _forget_ledgers(self, gid: bytes) -> None:
        for key in [key for key in self._ledgers if key[0] == gid]:
            del self._ledgers[key]

    def on_removing_endpoint(self, endpoint_info: EndpointInfo) -> None:
        """Forget the peer; its process's liveness is tested afresh the next time a slot with
        descriptors for it is considered. Descriptors still in flight to a live process keep
        their protection (this hook also runs when *our* endpoint goes away)."""
        with self._lock:
            token = self._peers.pop(endpoint_info.gid, None)
            self._forget_ledgers(endpoint_info.gid)
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
        """A descriptor for this peer, or None (CPU bytes for it): unknown or incompatible peer,
        private (fallback) memory, a received buffer (republishing one would let the original
        publisher reuse it under the new peer), or what the peer's ledger says (dead, share in
        flight, not taking)."""
        state = pool.get_state()
        token = self._peers.get(endpoint_info.gid, _UNKNOWN)
        if (token is _UNKNOWN
                or not isinstance(buffer, DemoBuffer) or not isinstance(buffer._keepalive,
                                                                         pool.Pin)):
            state.decline()
            return None
        key = _ledger_key(endpoint_info)
        depth = _depth_of(endpoint_info)
        with self._lock:
            ledger = self._ledgers.get(key)
            if ledger is None:
                ledger = self._ledgers[key] = pool.PeerLedger(
                    token, depth, per_channel=key[1] is not None)
        ledger.depth = depth
        return state.describe(buffer._keepalive, ledger=ledger)

    def peer_ledgers(self) -> Dict[str, dict]:
        """Per peer served so far (``<gid hex>`` or ``<gid hex>/<local publisher gid hex>``):
        its token, depth, messages, descriptors in flight (and past its share) and whether it
        is taken for not taking."""
        with self._lock:
            ledgers = dict(self._ledgers)
        return {gid.hex() + (f'/{local.hex()}' if local else ''): ledger.summary()
                for (gid, local), ledger in ledgers.items()}

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
