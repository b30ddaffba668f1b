"""The buffer backend plugin interface, mirroring upstream's C++ ``rosidl::BufferBackend``.

A backend owns a kind of memory (shared memory, GPU memory, ...) and knows how to describe a
Buffer of that memory in a small *descriptor* that a peer endpoint turns back into a Buffer.
Backends are Python classes registered as entry points (see :mod:`rosidl_buffer_py.registry`).
"""
import enum
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Callable, List, Mapping, Optional, Sequence, Set, Tuple

from rosidl_buffer_py.buffer import Buffer

#: Largest descriptor a backend may produce, in bytes (as upstream's kMaxBufferDescriptorSize).
MAX_DESCRIPTOR_SIZE = 4096

#: Length in bytes of an rmw GID, as rclpy's topic endpoint info reports it.
GID_SIZE = 16


class EndpointGone(Exception):
    """Raised by :meth:`BufferBackend.create_descriptor_with_endpoint` when the backend knows
    that the peer endpoint's process is gone (before DDS's lease says so).

    The publisher then writes nothing more to that peer (no descriptor, no CPU copy): its
    route ends as if the peer had unmatched. Returning ``None`` means something else: the peer
    is alive but cannot use this memory, and gets CPU bytes.
    """


class BackendUnavailable(Exception):
    """Raised by a backend's constructor when this machine cannot run it (no driver, no
    device): the registry leaves it out, logs the reason once (debug level), names it to whoever
    asks for the backend, and
    :func:`rosidl_buffer_py.registry.unavailable_backends` says why."""


class EndpointKind(enum.Enum):
    """Which side of a topic an endpoint is."""

    PUBLISHER = 'publisher'
    SUBSCRIPTION = 'subscription'


@dataclass(frozen=True)
class EndpointInfo:
    """What a backend learns about a local or remote endpoint (rmw_topic_endpoint_info_t).

    Three optional fields (not in upstream) describe a *peer* more closely, for backends that
    account per channel: ``history_depth``, the peer's QoS history as far as it bounds what it
    can still take (``N > 0`` for KEEP_LAST depth N, ``0`` for KEEP_ALL, ``None`` when unknown),
    ``local_gid``, the GID of the local endpoint on whose behalf the backend is called (the
    publisher whose channel to the peer carries the descriptor), and ``delivered``, a
    callable that tells whether the peer's reader has received everything sent to it on that
    channel so far (``None`` when the caller cannot tell). With them, a backend may stop
    reserving memory for a descriptor once N newer messages on that channel *reached* the
    peer's reader and so pushed it out of its history: a stopped process receives nothing, and
    still holds what it had.
    """

    gid: bytes
    topic_name: str
    endpoint_kind: EndpointKind
    node_name: str = ''
    node_namespace: str = ''
    history_depth: Optional[int] = None
    local_gid: Optional[bytes] = None
    delivered: Optional[Callable[[], bool]] = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.gid, (bytes, bytearray)) or len(self.gid) != GID_SIZE:
            raise ValueError(f'gid must be {GID_SIZE} bytes, got {self.gid!r}')
        if not isinstance(self.endpoint_kind, EndpointKind):
            raise TypeError(f'endpoint_kind must be an EndpointKind, got {self.endpoint_kind!r}')
        depth = self.history_depth
        if depth is not None and (isinstance(depth, bool) or not isinstance(depth, int)
                                  or depth < 0):
            raise ValueError('history_depth must be None (unknown), 0 (KEEP_ALL) or a KEEP_LAST '
                             f'depth > 0, got {depth!r}')
        if self.local_gid is not None:
            if not isinstance(self.local_gid, (bytes, bytearray)) or \
                    len(self.local_gid) != GID_SIZE:
                raise ValueError(f'local_gid must be None or {GID_SIZE} bytes, got '
                                 f'{self.local_gid!r}')
            object.__setattr__(self, 'local_gid', bytes(self.local_gid))
        object.__setattr__(self, 'gid', bytes(self.gid))

    @property
    def gid_hex(self) -> str:
        """The GID as 32 lowercase hex characters (as in per-endpoint channel names)."""
        return self.gid.hex()


class BufferBackend(ABC):
    """A buffer backend plugin.

    Required: :meth:`get_backend_type`, :meth:`create_descriptor_with_endpoint` and
    :meth:`from_descriptor_with_endpoint`. The other methods are optional hooks with defaults.
    Backend methods may be called from several threads (executor and discovery threads).
    """

    @abstractmethod
    def get_backend_type(self) -> str:
        """Return the backend's name: lowercase letters, digits and ``_`` (e.g. ``"demo"``)."""

    def get_backend_metadata(self) -> str:
        """Return backend-specific information advertised to peers (no ``;`` or ``=``).

        Peers receive it in ``on_discovering_endpoint(endpoint_supported_backends=...)``.
        """
        return ''

    @abstractmethod
    def create_descriptor_with_endpoint(self, buffer: Buffer,
                                        endpoint_info: EndpointInfo) -> Optional[bytes]:
        """Describe ``buffer`` for the peer ``endpoint_info``.

        Return the descriptor bytes (at most :data:`MAX_DESCRIPTOR_SIZE`), or ``None`` when this
        peer cannot use this backend: the message is then sent to it as CPU bytes. Raise
        :class:`EndpointGone` when the peer's process is known to be gone: nothing is sent.
        """

    def steady_describer(self, endpoint_info: EndpointInfo
                         ) -> Optional[Callable[[Buffer], Optional[bytes]]]:
        """Optional (not in upstream): a callable that describes Buffers for this peer on a
        publisher's hot path, while its routes are steady, or None (the default: every message
        asks :meth:`create_descriptor_with_endpoint`).

        The callable returns a descriptor where that is what
        :meth:`create_descriptor_with_endpoint` would return, having done the same; otherwise
        None, *with nothing changed*: the publisher then asks
        :meth:`create_descriptor_with_endpoint` for the same Buffer. It may be asked for any
        Buffer. A publisher asks for a new one whenever the peer's advertisement or its routes
        change; the callable may keep what it resolved for the peer until then.
        """
        return None

    def steady_opener(self, endpoint_info: EndpointInfo
                      ) -> Optional[Callable[[bytes], Optional[Buffer]]]:
        """Optional (not in upstream): a callable that opens this publisher's descriptors on a
        subscription's hot path, or None (the default: every descriptor goes to
        :meth:`from_descriptor_with_endpoint`).

        The callable returns the Buffer that :meth:`from_descriptor_with_endpoint` would
        return, having done the same; otherwise None, having opened nothing: the subscription
        then asks :meth:`from_descriptor_with_endpoint` for the same descriptor, which opens it
        or says why not (as it does when the callable raises). A subscription asks once per
        publisher and keeps the callable while the publisher is known.
        """
        return None

    @abstractmethod
    def from_descriptor_with_endpoint(self, descriptor: bytes,
                                      endpoint_info: EndpointInfo) -> Buffer:
        """Turn a descriptor received from the publisher ``endpoint_info`` into a Buffer.

        ``descriptor`` comes from the network: validate it and raise ``ValueError`` with a clear
        message when it is malformed or names memory this process cannot reach.
        """

    def allocate(self, nbytes: int) -> Buffer:
        """Return a new writable Buffer of ``nbytes`` in this backend's memory (not in upstream's
        C++ interface, which allocates through backend-specific buffer types).

        Used by :func:`rosidl_buffer_py.image.allocate_image_msg` to fill images in place.
        """
        raise NotImplementedError(f'buffer backend {self.get_backend_type()!r} cannot allocate')

    def on_creating_endpoint(self, endpoint_info: EndpointInfo) -> None:
        """Hook: a local buffer-aware endpoint is being created."""

    def on_discovering_endpoint(
            self, endpoint_info: EndpointInfo, existing_endpoints: Sequence[EndpointInfo],
            endpoint_supported_backends: Mapping[str, str]) -> Tuple[bool, List[Set[int]]]:
        """Hook: a remote buffer-aware endpoint was discovered (or its advertisement changed).

        :param endpoint_supported_backends: backend name -> metadata, as the peer advertises.
        :return: ``(compatible, groups)``: whether this backend can serve the peer, and groups of
            endpoint GID hashes that may share transport resources (upstream's contract; may be
            empty).
        """
        return self.get_backend_type() in endpoint_supported_backends, []

    def on_removing_endpoint(self, endpoint_info: EndpointInfo) -> None:
        """Hook (not in upstream): a remote endpoint went away; drop what was cached for it."""
