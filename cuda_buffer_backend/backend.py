"""CudaBackend: the ``cuda`` buffer backend plugin (entry point
``cuda = cuda_buffer_backend:CudaBackend``)."""
import re
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Set, Tuple

from demo_buffer_backend import handover
from demo_buffer_backend.endpoints import ServedEndpoints
from rosidl_buffer_py.backend import (BackendUnavailable, BufferBackend, EndpointInfo,
                                      EndpointKind)
from rosidl_buffer_py.buffer import Buffer

from cuda_buffer_backend import driver as cuda
from cuda_buffer_backend import lifecycle
from cuda_buffer_backend.buffer import BACKEND_TYPE, CudaBuffer

#: One device a process advertises: ``<uuid hex>:<token>``.
_DEVICE = re.compile(r'^([0-9a-f]{32}):([1-9][0-9]{0,9}_[0-9a-f]{16})$')
#: Devices advertised at most (USER_DATA stays small).
MAX_DEVICES = 16


def parse_metadata(metadata: Optional[str], domain: str) -> Dict[bytes, str]:
    """``{device uuid: token}`` a peer advertises (from the network: anything malformed, or
    of another domain, gives ``{}``)."""
    if not isinstance(metadata, str):
        return {}
    parts = metadata.split('/')
    if parts[0] != domain or not 1 < len(parts) <= MAX_DEVICES + 1:
        return {}
    devices = {}
    for part in parts[1:]:
        match = _DEVICE.match(part)
        if match is None:
            return {}
        devices[bytes.fromhex(match.group(1))] = match.group(2)
    return devices


class CudaBackend(BufferBackend):
    """Payloads in GPU memory; a 52-byte descriptor crosses the middleware.

    Peers are compatible when they share our domain (same boot, namespaces and user, as the demo
    backend's) and a GPU (by UUID). The slots, ledgers, links, inbox and mappings are the demo
    backend's machinery over GPU memory (:mod:`.memory`), one pool per device. A peer that cannot
    map the memory (no GPU in common, a legacy or ``cpu`` subscription, another host or user)
    gets CPU bytes: one device-to-host copy per message, shared by all such peers.

    Constructing it raises :class:`~rosidl_buffer_py.backend.BackendUnavailable` where this
    process has no CUDA driver or device: the registry then reports it once and leaves it out.
    """

    def __init__(self) -> None:
        try:
            drv = cuda.load()
        except cuda.Unavailable as exc:
            raise BackendUnavailable(str(exc)) from None
        self._domain = 'cuda1.' + handover.domain()
        self._uuids = {drv.uuid(d): d for d in range(min(drv.device_count(), MAX_DEVICES))}
        #: per local device: the peers that see it, and their ledgers
        self._served: Dict[int, ServedEndpoints] = {d: ServedEndpoints()
                                                    for d in self._uuids.values()}

    def get_backend_type(self) -> str:
        return BACKEND_TYPE

    def get_backend_metadata(self) -> str:
        """``cuda1.<domain>/<uuid hex>:<token>/...``: per device, the token of this process's
        listener for it."""
        parts = [self._domain]
        for uuid, device in self._uuids.items():
            token = lifecycle.get_pool(device).advertise()
            if token:
                parts.append(f'{uuid.hex()}:{token}')
        return '/'.join(parts)

    def on_discovering_endpoint(
            self, endpoint_info: EndpointInfo, existing_endpoints: Sequence[EndpointInfo],
            endpoint_supported_backends: Mapping[str, str]) -> Tuple[bool, List[Set[int]]]:
        """Compatible iff the peer shares our domain and a GPU. A compatible publisher may
        hand this process slots of the GPUs both see."""
        devices = parse_metadata(endpoint_supported_backends.get(BACKEND_TYPE), self._domain)
        for uuid, device in self._uuids.items():
            token = devices.get(uuid)
            self._served[device].note(endpoint_info.gid, token)
            if endpoint_info.endpoint_kind is EndpointKind.PUBLISHER:
                pool = lifecycle.get_pool(device)
                if token is not None:
                    pool.expect(endpoint_info.gid, handover.token_pid(token))
                else:
                    pool.forget(endpoint_info.gid)
        return any(uuid in self._uuids for uuid in devices), []

    def on_removing_endpoint(self, endpoint_info: EndpointInfo) -> None:
        for device, served in self._served.items():
            served.forget(endpoint_info.gid)
            pool = lifecycle.get_pool(device)
            pool.forget(endpoint_info.gid)
            pool.sweep()

    def create_descriptor_with_endpoint(self, buffer: Buffer,
                                        endpoint_info: EndpointInfo) -> Optional[bytes]:
        """A descriptor for this peer, or None (CPU bytes for it): a peer that does not see the
        buffer's GPU, private (fallback) memory, a received buffer, a full queue or share.
        ``EndpointGone`` when the peer's process hung up its link."""
        pin = buffer.pin if isinstance(buffer, CudaBuffer) else None
        if pin is None:
            return None
        device = buffer.device
        pool = lifecycle.get_pool(device)
        ledger = self._served[device].ledger_of(endpoint_info)
        if ledger is None:
            pool.decline()
            return None
        buffer.record_writes()
        return pool.describe(pin, ledger)

    def steady_describer(self, endpoint_info: EndpointInfo
                         ) -> Optional[Callable[[Buffer], Optional[bytes]]]:
        """:meth:`create_descriptor_with_endpoint`'s steady case, for a publisher's lane: the
        writes recorded, then the pool's native describe (``Pool.steady_describer``) with the
        peer's ledger of each device resolved once; None for a peer that sees none of the
        devices whose pools this process made. A Buffer of another kind, of another device, or
        one the native describe declines gets None, the event aside (recording it again is
        what the full describe does first)."""
        describers = {}
        for device, pool in lifecycle.pools().items():
            ledger = self._served[device].ledger_of(endpoint_info)
            if ledger is not None:
                describers[device] = pool.steady_describer(ledger)
        if not describers:
            return None

        def describer(buffer: Buffer) -> Optional[bytes]:
            # (a Buffer without a pin records nothing, and the native describe declines it)
            describe = describers.get(buffer.device) if type(buffer) is CudaBuffer else None
            if describe is None:
                return None
            buffer.record_writes()  # before the descriptor leaves: readers wait for this
            return describe(buffer)
        return describer

    def steady_opener(self, endpoint_info: EndpointInfo
                      ) -> Optional[Callable[[bytes], Optional[CudaBuffer]]]:
        """:meth:`from_descriptor_with_endpoint`'s steady case, for a subscription's steady
        step: the native open (``Pool.open_steady``) of the pools this process made, resolved
        once as the demo backend's opener resolves its pool, made a read-only CudaBuffer; None,
        having opened nothing, where the full open is to run. None (the full open for every
        descriptor) while this process has no pool."""
        opens = tuple(pool.open_steady for pool in lifecycle.pools().values())
        if not opens:
            return None

        def opener(descriptor: bytes) -> Optional[CudaBuffer]:
            for open_steady in opens:
                opened = open_steady(descriptor)
                if opened is not None:
                    memory, hold = opened
                    return CudaBuffer(memory, keepalive=hold, readonly=True)
            return None
        return opener

    def from_descriptor_with_endpoint(self, descriptor: bytes,
                                      endpoint_info: EndpointInfo) -> CudaBuffer:
        pools = lifecycle.pools() or {0: lifecycle.get_pool(0)}
        error: Optional[ValueError] = None
        for device, pool in pools.items():
            try:
                memory, hold = pool.open_descriptor(descriptor)
            except ValueError as exc:
                error = exc
                continue
            return CudaBuffer(memory, keepalive=hold, readonly=True)
        raise error

    def allocate(self, nbytes: int) -> CudaBuffer:
        """A writable CudaBuffer on device 0 (``CudaBuffer.allocate(nbytes, device)`` for
        another)."""
        return CudaBuffer.allocate(nbytes)

    def peer_ledgers(self) -> Dict[str, dict]:
        """Per device and peer served so far: its token, depth, messages and descriptors in
        flight."""
        return {f'cuda:{device}/{key}': summary for device, served in self._served.items()
                for key, summary in served.summary().items()}

    def stats(self) -> dict:
        """Counters and gauges of each device's pool (see ``demo_buffer_backend.stats()``)."""
        return {f'cuda:{device}': pool.stats() for device, pool in lifecycle.pools().items()}

    def close(self) -> None:
        """Close every slot, link and listener of this process."""
        lifecycle.shutdown()
