"""The peers of a buffer-aware endpoint: the buffer-aware endpoints of the opposite kind on its
topic, each with a channel.

A :class:`PeerTable` is owned by one endpoint (publisher or subscription). It watches the
endpoint's topic in :mod:`rosidl_buffer_py.discovery`, keeps one record per buffer-aware peer,
asks the backends which of them can serve each peer, re-announces the endpoint while a peer's
channel stays unmatched (:class:`~rosidl_buffer_py.reannounce.Reannouncer`) and destroys the
channels at teardown (at interpreter exit at the latest, see :mod:`rosidl_buffer_py.teardown`).
What it needs from its owner is :class:`PeerHandlers`, the endpoint's callables for each event
(not hooks on the rclpy entity), and its ``announce``; what the owner keeps per peer (routes,
streams, counters) stays in the owner's records (:class:`PeerRecord`).
"""
import threading
import time
from typing import (Any, Callable, Dict, Generic, Iterator, Mapping, NamedTuple,
                    Optional, Protocol, Set, TypeVar)

from rosidl_buffer_py import discovery, teardown
from rosidl_buffer_py.backend import BufferBackend, EndpointInfo, EndpointKind
from rosidl_buffer_py.channel import dds_topic
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.qos import incompatible_peers
from rosidl_buffer_py.reannounce import Reannouncer


class PeerRecord(Protocol):
    """What the table reads and sets on an owner's per-peer record."""

    info: EndpointInfo
    backends: Dict[str, str]   #: the peer's advertisement (backend -> metadata)
    channel: Optional[object]  #: its ChannelPublisher/ChannelSubscription (``destroy()``)
    created_at: float          #: set by the table (time.monotonic()) when the record is added


R = TypeVar('R', bound=PeerRecord)


class PeerHandlers(NamedTuple):
    """What a :class:`PeerTable` does with its owner's records: the owner's own callables, one
    per event (an endpoint builds them from its methods; nothing of it is on the rclpy entity
    users hold).

    Every one is called with the table's lock held (the owner's lock, shared), on the thread
    that processes discovery (the executor's, or ``publish()``'s when the node is not spun).
    """

    #: ``()``: discovery: an endpoint of the peer kind on the topic appeared or changed, a
    #: legacy one too: what routes a message takes may change.
    peer_seen: Callable[[], None]
    #: ``()``: the re-announcer looked at the peers' channels (a few times a second while one
    #: is unmatched, and once when all are): one may have matched, which no DDS event tells
    #: the owner, so what depends on it (a publisher's routes) is due for a look.
    channels_checked: Callable[[], None]
    #: ``(info, backends) -> record``: a new buffer-aware peer: create its record and channel.
    add_peer: Callable[[EndpointInfo, Dict[str, str]], Any]
    #: ``(record, compatible)``: the peer's advertisement was (re)read; the ``compatible``
    #: backends can serve it.
    update_peer: Callable[[Any, Set[str]], None]
    #: ``(record)``: the record leaves the table (the peer left, withdrew its advertisement, or
    #: the endpoint is torn down); its channel is destroyed right after.
    forget_peer: Callable[[Any], None]
    #: ``(gid)``: discovery: an endpoint of the peer kind on the topic went away (a peer or a
    #: legacy endpoint). The owner calls :meth:`PeerTable.drop` when done with the channel.
    peer_gone: Callable[[bytes], None]
    #: ``()``: teardown, once, after every peer was dropped: free what else the endpoint holds
    #: (its own timers and guard conditions: see
    #: :func:`~rosidl_buffer_py.on_demand.destroy_node_entities`).
    release: Callable[[], None]


class PeerTable(Generic[R]):
    """The buffer-aware peers of one endpoint, and the discovery watch that finds them.

    ``lock`` is the owner's: hold it around every use of the records. ``announce()`` (re-)sets
    the endpoint's USER_DATA (peers discover, or re-discover, it: see the re-announcer).
    :meth:`open` starts watching; :meth:`close` ends it and destroys every channel (once;
    ``closed`` then).
    """

    def __init__(self, owner: PeerHandlers, node, callback_group, *, announce: Callable[[], None],
                 lock: threading.RLock, peer_kind: EndpointKind, topic_name: str, gid: bytes,
                 backends: Mapping[str, BufferBackend], logger) -> None:
        self.lock = lock
        self.peer_kind = peer_kind
        self.closed = False
        self._owner = owner
        self._node = node
        self._topic_name = topic_name
        self._gid = gid
        self._backends = backends
        self._logger = logger
        self._records: Dict[bytes, R] = {}
        #: moves whenever a record comes or goes (what a publisher's route signature reads)
        self.version = 0
        self._discovery = discovery.for_node(node)
        self.reannouncer = Reannouncer(node, callback_group, self, announce,
                                       owner.channels_checked, logger)

    # the records ----------------------------------------------------------------------------

    def __iter__(self) -> Iterator[R]:
        return iter(self._records.values())

    def __len__(self) -> int:
        return len(self._records)

    def __contains__(self, gid: bytes) -> bool:
        return gid in self._records

    def __getitem__(self, gid: bytes) -> R:
        return self._records[gid]

    def get(self, gid: bytes) -> Optional[R]:
        return self._records.get(gid)

    def node_names(self) -> Dict[bytes, str]:
        """GID -> fully qualified node name of the peers, from the ROS graph (diagnostics)."""
        graph = (self._node.get_subscriptions_info_by_topic
                 if self.peer_kind is EndpointKind.SUBSCRIPTION
                 else self._node.get_publishers_info_by_topic)
        try:
            infos = graph(self._topic_name)
        except Exception:  # the node is being destroyed
            return {}
        return {bytes(info.endpoint_gid): (info.node_namespace.rstrip('/') + '/' +
                                           info.node_name) for info in infos}

    # lifetime -------------------------------------------------------------------------------

    def open(self) -> None:
        """Start watching the topic (discovery wakes the executor that spins the node, see
        :meth:`~rosidl_buffer_py.discovery.ParticipantDiscovery.wake_with`) and take in the
        peers already known."""
        teardown.track(self)
        with self.lock:
            for peer in self._discovery.watch(dds_topic(self._topic_name), self):
                self.on_peer(peer)

    def poll(self) -> None:
        """Process discovery now (for a node no executor spins)."""
        self._discovery.process()
        self.reannouncer.reannounce_if_unmatched()

    def close(self) -> None:
        """Destroy the channels, stop discovery, release the owner (once).

        Lock order: discovery dispatch holds the discovery lock and then takes ours
        (``on_peer``), so ours is never held while taking the discovery's.
        """
        with self.lock:
            if self.closed:
                return
            self.closed = True  # from here on on_peer adds nothing
        self._discovery.unwatch(dds_topic(self._topic_name), self)
        with self.lock:
            for gid in list(self._records):
                self.drop(gid)
            self.reannouncer.close()
            self._owner.release()
        teardown.untrack(self)

    # discovery (a rosidl_buffer_py.discovery.Watcher) ---------------------------------------

    def on_peer(self, peer: discovery.PeerEndpoint) -> None:
        """Discovery: an endpoint of our topic appeared or changed its advertisement."""
        if peer.kind is not self.peer_kind:
            return
        with self.lock:
            if self.closed:
                return
            self._owner.peer_seen()
            known = self._records.get(peer.gid)
            if not peer.buffer_aware:
                if known is not None:  # it withdrew its advertisement: now a legacy endpoint
                    self.drop(peer.gid)
                return
            info = EndpointInfo(peer.gid, self._topic_name, self.peer_kind)
            if known is None and peer.gid in incompatible_peers(
                    self._node, self._topic_name, self._gid, self.peer_kind):
                # stock endpoints would not communicate: neither do our channels (and an
                # unmatched channel would make both sides re-announce, and log, forever)
                return
            compatible = self._compatible_backends(info, peer.backends)
            if known is None:
                known = self._owner.add_peer(info, dict(peer.backends))
                known.created_at = time.monotonic()
                self._records[peer.gid] = known
                self.version += 1
                # a new buffer-aware peer whose QoS matches ours may have discovered us before
                # its tap existed: the re-announcer announces once if its channel stays
                # unmatched (soon, but not now: see NEW_PEER_REANNOUNCE_SECONDS)
                self.reannouncer.rearm()
            known.backends = dict(peer.backends)
            self._owner.update_peer(known, compatible)

    def on_peer_gone(self, gid: bytes) -> None:
        """Discovery: an endpoint of our topic went away."""
        with self.lock:
            self._owner.peer_gone(gid)

    def drop(self, gid: bytes) -> None:
        """Forget a peer: its record leaves, its channel is destroyed, backends are told."""
        record = self._records.get(gid)
        if record is None:
            return
        self._owner.forget_peer(record)
        del self._records[gid]
        self.version += 1
        if record.channel is not None:
            record.channel.destroy()
        for backend in self._backends.values():
            backend.on_removing_endpoint(record.info)

    def _compatible_backends(self, info: EndpointInfo, advertised: Mapping[str, str]) -> Set[str]:
        """Ask each backend both sides have whether it can serve this peer."""
        existing = [p.info for p in self._records.values() if p.info.gid != info.gid]
        compatible = set()
        for name in advertised:
            backend = self._backends.get(name)
            if backend is None or name == CPU_BACKEND:
                continue
            try:
                ok, _groups = backend.on_discovering_endpoint(info, existing, advertised)
            except Exception as exc:  # a broken backend degrades this peer to CPU bytes
                self._logger.error(f'backend {name!r} on_discovering_endpoint failed: '
                                   f'{type(exc).__name__}: {exc}')
                ok = False
            if ok:
                compatible.add(name)
        return compatible
