"""The part a buffer-aware publisher and a buffer-aware subscription share.

Each endpoint is an rclpy entity (:class:`rosidl_buffer_py.publisher.Publisher`,
:class:`rosidl_buffer_py.subscription.Subscription`) around one :class:`EndpointCore`, which
holds what does not depend on the side: the endpoint's identity (GID, :class:`EndpointInfo`,
logger, lock), its advertisement and the backends behind it, its buffer-aware peers (a
:class:`~rosidl_buffer_py.peers.PeerTable`, with the re-announcer), the deadline monitor that
counts over every route, and teardown. What a side does with its peers (routes, streams) it
gives the core as :class:`~rosidl_buffer_py.peers.PeerHandlers`.

:func:`buffer_aware` is the one rule both ``create_*`` functions apply: anything else makes a
plain rclpy endpoint (:mod:`rosidl_buffer_py.plain`).
"""
import copy
import threading
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Mapping, NamedTuple, Optional, TypeVar

from rclpy.qos import QoSProfile

from rosidl_buffer_py import _dds, advertisement, codec
from rosidl_buffer_py._native import endpoint_gid, get_user_data, set_user_data
from rosidl_buffer_py.backend import BufferBackend, EndpointInfo, EndpointKind
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.events import DeadlineMonitor, finite
from rosidl_buffer_py.on_demand import destroy_node_entities
from rosidl_buffer_py.peers import PeerHandlers, PeerTable


def buffer_aware(msg_type) -> bool:
    """Whether ``msg_type`` gets a buffer-aware endpoint: it has a ``uint8[]`` field (at any
    depth) and the running rmw is the one the native layer supports. Otherwise a plain rclpy
    endpoint carries it, as CPU bytes, exactly as stock does."""
    return _dds.is_supported() and bool(codec.buffer_paths(msg_type))


class DeadlineSplit(NamedTuple):
    """rclpy event callbacks without the deadline one, and that one (None: rclpy keeps it)."""

    event_callbacks: Any
    deadline: Optional[Callable]


def split_deadline(event_callbacks, qos_profile: QoSProfile) -> DeadlineSplit:
    """Take the user's deadline callback out of (a copy of) ``event_callbacks`` when the QoS
    sets a deadline: the main topic's DDS entity sees only the messages that travel on it, so
    the endpoint counts misses over every route instead (:class:`DeadlineMonitor`)."""
    if not (event_callbacks.deadline and finite(qos_profile.deadline)):
        return DeadlineSplit(event_callbacks, None)
    deadline = event_callbacks.deadline
    event_callbacks = copy.copy(event_callbacks)
    event_callbacks.deadline = None
    return DeadlineSplit(event_callbacks, deadline)


def advertised_backends(backends: Mapping[str, BufferBackend], cpu_metadata: str
                        ) -> Dict[str, str]:
    """What an endpoint advertises: ``cpu`` with ``cpu_metadata``, then each other backend's
    metadata (in name order)."""
    advertised = {CPU_BACKEND: cpu_metadata}
    advertised.update({name: backend.get_backend_metadata()
                       for name, backend in sorted(backends.items()) if name != CPU_BACKEND})
    return advertised


def advertise(handle, kind: EndpointKind, advertised: Mapping[str, str]) -> bytes:
    """Append ``advertised`` to the USER_DATA of the DataWriter or DataReader behind
    ``handle`` (rmw's own entries kept) and set it; the USER_DATA set, which
    :meth:`EndpointCore.announce` sets again to re-announce."""
    user_data = advertisement.append(get_user_data(handle, kind.value), advertised)
    set_user_data(handle, kind.value, user_data)
    return user_data


T = TypeVar('T')


@dataclass
class ChannelPeer:
    """A buffer-aware peer and its channel, as both sides keep it (a
    :class:`~rosidl_buffer_py.peers.PeerRecord`); each side's record adds its own state."""

    info: EndpointInfo
    backends: Dict[str, str]                 #: its advertisement (backend -> metadata)
    channel: Optional[Any] = None            #: ChannelPublisher or ChannelSubscription
    channel_topic: str = ''
    created_at: float = 0.0                  #: set by the peer table when it is added
    backend_in_use: Optional[str] = None     #: of the last message (None before the first)


class EndpointCore:
    """Identity, advertisement, peers, deadline and teardown of one buffer-aware endpoint.

    ``handle`` is what rmw calls take for it (the rclpy Publisher, or the subscription's C
    reader); its USER_DATA already carries ``user_data`` (see :func:`advertise`). Nothing
    happens on the network until :meth:`open`.
    """

    def __init__(self, node, handle, kind: EndpointKind, *, topic_name: str,
                 backends: Mapping[str, BufferBackend], advertised: Mapping[str, str],
                 user_data: bytes, qos_profile: QoSProfile, callback_group,
                 deadline: Optional[Callable], handlers: PeerHandlers) -> None:
        self.node = node
        self.kind = kind
        self.backends = dict(backends)
        self.advertised = dict(advertised)
        #: the node's logger: what the endpoint logs reaches /rosout, as the node's own lines
        self.logger = node.get_logger().get_child('rosidl_buffer_py')
        #: held around every use of the peers (the peer table's lock too)
        self.lock = threading.RLock()
        self.gid = endpoint_gid(handle, kind.value)
        self.info = EndpointInfo(self.gid, topic_name, kind, node.get_name(),
                                 node.get_namespace())
        self._handle = handle
        self._user_data = user_data
        self._release_side = handlers.release
        self.deadline = (DeadlineMonitor(node, qos_profile.deadline, deadline, callback_group)
                         if deadline else None)
        peer_kind = (EndpointKind.SUBSCRIPTION if kind is EndpointKind.PUBLISHER
                     else EndpointKind.PUBLISHER)
        self.peers: PeerTable = PeerTable(
            handlers._replace(release=self._release), node, callback_group,
            announce=self.announce, lock=self.lock, peer_kind=peer_kind, topic_name=topic_name,
            gid=self.gid, backends=self.backends, logger=self.logger)

    def announce(self) -> None:
        """(Re-)set USER_DATA: peers discover, or re-discover, the advertisement."""
        set_user_data(self._handle, self.kind.value, self._user_data)

    def open(self) -> None:
        """Tell the backends the endpoint exists, then take in and watch its peers."""
        for backend in self.backends.values():
            backend.on_creating_endpoint(self.info)
        self.peers.open()

    def close(self) -> None:
        """Destroy the channels, stop discovery, release what the endpoint holds (once)."""
        self.peers.close()

    def peer_rows(self, row: Callable[[Any, Dict[str, Any]], T]) -> List[T]:
        """``row(record, common)`` for each peer, for diagnostics; ``common`` holds the fields
        both sides report (gid, node from the ROS graph, advertised backends, channel topic,
        backend in use)."""
        names = self.peers.node_names()
        with self.lock:
            return [row(peer, {
                'gid': peer.info.gid_hex, 'node': names.get(peer.info.gid, ''),
                'advertised_backends': dict(peer.backends), 'channel_topic': peer.channel_topic,
                'backend_in_use': peer.backend_in_use}) for peer in self.peers]

    def identity(self) -> Dict[str, Any]:
        """The statistics fields both sides report: gid, buffer_aware, advertised_backends."""
        return {'gid': self.gid.hex(), 'buffer_aware': True,
                'advertised_backends': dict(self.advertised)}

    def activity(self) -> None:
        """A message went out or was delivered: the deadline period restarts."""
        if self.deadline is not None:
            self.deadline.activity()

    def _release(self) -> None:
        self._release_side()
        destroy_node_entities(self.node, [self.deadline and self.deadline.timer], self.logger)
