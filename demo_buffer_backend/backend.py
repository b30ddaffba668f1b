"""DemoBackend: the ``demo`` buffer backend plugin (entry point
``demo = demo_buffer_backend:DemoBackend``)."""
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Set, Tuple

from rosidl_buffer_py.backend import BufferBackend, EndpointInfo, EndpointKind
from rosidl_buffer_py.buffer import Buffer

from demo_buffer_backend import handover, lifecycle, limits
from demo_buffer_backend.buffer import BACKEND_TYPE, DemoBuffer
from demo_buffer_backend.endpoints import ServedEndpoints


class DemoBackend(BufferBackend):
    """Payloads in sealed anonymous memory; a 52-byte descriptor crosses the middleware.

    Every instance shares the process-wide pool (:mod:`.pool`, made by :mod:`.lifecycle`). The
    keyword arguments, when given, set the process-wide limits (see
    :func:`demo_buffer_backend.configure`).

    Peers are compatible when they advertise our domain (same boot, network, mount and pid
    namespaces, same uid) and a token (the address of their listener). Each peer endpoint has a
    ledger of its descriptors in flight (see :mod:`.ledgers`).
    ``create_descriptor_with_endpoint`` returns None (CPU bytes for that peer) for peers that
    cannot use this memory, and raises ``EndpointGone`` for one whose process hung up.
    """

    def __init__(self, *, max_pool_bytes: Optional[int] = None, max_slots: Optional[int] = None,
                 reclaim_timeout: Optional[float] = None,
                 max_inflight_per_peer: Optional[int] = None) -> None:
        if (max_pool_bytes, max_slots, reclaim_timeout, max_inflight_per_peer) != \
                (None, None, None, None):
            limits.configure(max_pool_bytes=max_pool_bytes, max_slots=max_slots,
                             reclaim_timeout=reclaim_timeout,
                             max_inflight_per_peer=max_inflight_per_peer)
        self._domain = handover.domain()
        self._served = ServedEndpoints()

    def get_backend_type(self) -> str:
        return BACKEND_TYPE

    def get_backend_metadata(self) -> str:
        """``<domain>.<token>``: the domain ``mfd1.<boot id>.<net ns>.<mnt ns>.<pid ns>.<euid>``
        (hex), then this process's token ``<pid>_<16 hex>``, which names its listener. Just the
        domain (no peer will hand us memory) when the listener cannot be created."""
        token = lifecycle.get_pool().advertise()
        return f'{self._domain}.{token}' if token else self._domain

    def parse_metadata(self, metadata: Optional[str]) -> Tuple[bool, Optional[str]]:
        """``(compatible, token)`` of a peer's metadata."""
        if not isinstance(metadata, str):
            return False, None
        domain, _, token = metadata.rpartition('.')
        token = handover.parse_token(token)
        if domain != self._domain or token is None:
            return False, None
        return True, token

    def on_discovering_endpoint(
            self, endpoint_info: EndpointInfo, existing_endpoints: Sequence[EndpointInfo],
            endpoint_supported_backends: Mapping[str, str]) -> Tuple[bool, List[Set[int]]]:
        """Compatible iff the peer advertises our domain and a token. A compatible publisher's
        process may hand this one segments from now on (see :mod:`.inbox`)."""
        compatible, token = self.parse_metadata(endpoint_supported_backends.get(BACKEND_TYPE))
        self._served.note(endpoint_info.gid, token if compatible else None)
        if endpoint_info.endpoint_kind is EndpointKind.PUBLISHER:
            pool = lifecycle.get_pool()
            if compatible:
                pool.expect(endpoint_info.gid, handover.token_pid(token))
            else:
                pool.forget(endpoint_info.gid)
        return compatible, []

    def on_removing_endpoint(self, endpoint_info: EndpointInfo) -> None:
        """Forget the peer and its ledgers (what it was sent settles through its link), and
        close the segments nobody can use any more: a publisher gone from DDS (its lease
        expired) is the moment an idle subscriber learns that it will send nothing more, with
        no thread of ours to wait for it."""
        self._served.forget(endpoint_info.gid)
        pool = lifecycle.get_pool()
        pool.forget(endpoint_info.gid)
        pool.sweep()

    def is_compatible(self, endpoint_info: EndpointInfo) -> bool:
        """Whether the endpoint was discovered and shares our domain."""
        return endpoint_info.gid in self._served

    def peer_token(self, endpoint_info: EndpointInfo) -> Optional[str]:
        """The token a compatible peer advertised (None: unknown peer)."""
        return self._served.token(endpoint_info.gid)

    def steady_describer(self, endpoint_info: EndpointInfo
                         ) -> Optional[Callable[[Buffer], Optional[bytes]]]:
        """The pool's native describe of the steady case (:meth:`.pool.Pool.steady_describer`)
        with the peer's ledger resolved once; None for a peer not known to be compatible."""
        ledger = self._served.ledger_of(endpoint_info)
        if ledger is None:
            return None
        return lifecycle.get_pool().steady_describer(ledger)

    def steady_opener(self, endpoint_info: EndpointInfo
                      ) -> Optional[Callable[[bytes], Optional[Buffer]]]:
        """The pool's native open of the steady case (:meth:`.pool.Pool.open_steady`), its
        view and hold made a DemoBuffer, without the general open's Python frames."""
        open_steady = lifecycle.get_pool().open_steady
        received = DemoBuffer.received

        def opener(descriptor: bytes) -> Optional[DemoBuffer]:
            opened = open_steady(descriptor)
            return None if opened is None else received(*opened)
        return opener

    def create_descriptor_with_endpoint(self, buffer: Buffer,
                                        endpoint_info: EndpointInfo) -> Optional[bytes]:
        """A descriptor for this peer, or None (CPU bytes for it): unknown or incompatible peer,
        private (fallback) memory, a received buffer (republishing one would let the original
        publisher reuse it under the new peer), a listener not of our user, or a full queue to
        it. ``EndpointGone`` when the peer's process hung up its link."""
        pool = lifecycle.get_pool()
        ledger = self._served.ledger_of(endpoint_info)
        pin = buffer.pin if isinstance(buffer, DemoBuffer) else None
        if ledger is None or pin is None:
            pool.decline()
            return None
        return pool.describe(pin, ledger)

    def peer_ledgers(self) -> Dict[str, dict]:
        """Per peer served so far (``<gid hex>`` or ``<gid hex>/<local publisher gid hex>``):
        its token, depth, messages and descriptors in flight."""
        return self._served.summary()

    def from_descriptor_with_endpoint(self, descriptor: bytes,
                                      endpoint_info: EndpointInfo) -> DemoBuffer:
        view, hold = lifecycle.get_pool().open_descriptor(descriptor)
        return DemoBuffer.received(view, hold)

    def allocate(self, nbytes: int) -> DemoBuffer:
        return DemoBuffer.allocate(nbytes)

    def stats(self) -> dict:
        """Process-wide counters (see :func:`demo_buffer_backend.stats`)."""
        return lifecycle.stats()

    def close(self) -> None:
        """Close every segment, link and listener of this process (process-wide: shared by all
        instances; the backend stays usable and starts afresh on next use)."""
        lifecycle.shutdown()
