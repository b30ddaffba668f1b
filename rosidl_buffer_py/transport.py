"""What the buffer-aware publisher and subscription share: peer bookkeeping and small helpers."""
import atexit
import copy
import threading
import time
import weakref
from typing import Dict, Mapping, Set

from rclpy.logging import get_logger
from rclpy.qos import (
    QoSCompatibility, QoSProfile, ReliabilityPolicy, qos_check_compatible,
    qos_policy_name_from_kind)

from rosidl_buffer_py.backend import BufferBackend, EndpointInfo, EndpointKind
from rosidl_buffer_py.channel import dds_topic
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.events import once_per_peer

_logger = get_logger('rosidl_buffer_py')

#: A channel unmatched this long means the peer probably missed our advertisement: re-announce
#: (at most this often). See BufferEndpoint._reannounce_if_unmatched.
UNMATCHED_REANNOUNCE_SECONDS = 1.0
_warned = set()
_warned_lock = threading.Lock()


#: How recently the re-announce timer must have run for the node to count as spinning.
SPIN_EVIDENCE_SECONDS = 2.5 * UNMATCHED_REANNOUNCE_SECONDS


def warn_unsupported_rmw(what: str, topic: str) -> None:
    """Say once per process why buffer-aware endpoints are plain rclpy pub/sub (CPU only): another
    middleware, or rmw_fastrtps libraries other than those the extension was built against
    (``_dds`` has already logged which)."""
    import rclpy
    from rosidl_buffer_py import _dds
    rmw = rclpy.get_rmw_implementation_identifier()
    with _warned_lock:
        if rmw in _warned:
            return
        _warned.add(rmw)
    if rmw == _dds.RMW_IMPLEMENTATION:
        return  # the ABI check warned once, naming the versions
    _logger.warning(f'{rmw} is not supported by rosidl_buffer_py (needs '
                    f'{_dds.RMW_IMPLEMENTATION}): the {what} on {topic} and every other one '
                    'use plain rclpy pub/sub on the main topic, CPU bytes only')


_live_endpoints: 'weakref.WeakSet' = weakref.WeakSet()


def track_endpoint(endpoint: 'BufferEndpoint') -> None:
    """Remember a live buffer-aware endpoint, to be torn down at interpreter exit at the latest.

    Channels and discovery wake-ups pin their node (rclpy defers destroying it). A script that
    ends without ``destroy_node()`` (Ctrl-C out of ``rclpy.spin``) would otherwise keep the DDS
    participant alive until the process dies, and Fast DDS's shared-memory files with it; stock
    rclpy frees everything when the interpreter exits, and so do we.
    """
    _live_endpoints.add(endpoint)


@atexit.register
def _teardown_live_endpoints() -> None:
    for endpoint in list(_live_endpoints):
        try:
            endpoint._teardown()
        except Exception as exc:  # exiting: report, never raise
            _logger.debug(f'teardown at exit: {type(exc).__name__}: {exc}')


def _endpoint_qos(node, topic: str):
    """GID -> QoS profile (as DDS uses it) of the topic's publishers and subscriptions."""
    try:
        publishers = node.get_publishers_info_by_topic(topic)
        subscriptions = node.get_subscriptions_info_by_topic(topic)
    except Exception:  # the node is being destroyed
        return {}, {}
    return ({bytes(i.endpoint_gid): i.qos_profile for i in publishers},
            {bytes(i.endpoint_gid): i.qos_profile for i in subscriptions})


def _incompatible(pub: QoSProfile, sub: QoSProfile) -> bool:
    return qos_check_compatible(pub, sub)[0] == QoSCompatibility.ERROR


def incompatible_peers(node, topic: str, own_gid: bytes, peer_kind: EndpointKind) -> Set[bytes]:
    """GIDs of the endpoints of the opposite kind whose QoS is incompatible with ours.

    Both profiles come from the ROS graph (what DDS uses: rclpy's "default" durations are
    resolved there); an endpoint the graph does not list yet is not in the set.
    """
    publishers, subscriptions = _endpoint_qos(node, topic)
    if peer_kind is EndpointKind.SUBSCRIPTION:
        own = publishers.get(own_gid)
        return set() if own is None else {
            gid for gid, qos in subscriptions.items() if _incompatible(own, qos)}
    own = subscriptions.get(own_gid)
    return set() if own is None else {
        gid for gid, qos in publishers.items() if _incompatible(qos, own)}


def reliable_subscription(node, topic: str, gid: bytes) -> bool:
    """Whether the ROS graph lists subscription ``gid`` of ``topic`` as RELIABLE (False when it
    does not list it yet)."""
    qos = _endpoint_qos(node, topic)[1].get(gid)
    return qos is not None and qos.reliability == ReliabilityPolicy.RELIABLE


def incompatible_qos_once_per_peer(event_callbacks, node, endpoint_impl, kind: EndpointKind,
                                   gid: bytes, topic_as_passed: str):
    """A copy of rclpy ``event_callbacks`` whose incompatible-QoS callback (the user's, or one
    logging rclpy's default warning, which names the topic as it was passed, as rclpy's does)
    fires once per incompatible peer (see :func:`rosidl_buffer_py.events.once_per_peer`)."""
    callback = event_callbacks.incompatible_qos
    if callback is None and not event_callbacks.use_default_callbacks:
        return event_callbacks
    resolved = endpoint_impl.get_topic_name()
    topic = topic_as_passed
    if callback is None:
        logger = get_logger(endpoint_impl.get_logger_name())
        if kind is EndpointKind.PUBLISHER:
            text = (f"New subscription discovered on topic '{topic}', requesting incompatible "
                    'QoS. No messages will be sent to it. Last incompatible policy: {}')
        else:
            text = (f"New publisher discovered on topic '{topic}', offering incompatible QoS. "
                    'No messages will be received from it. Last incompatible policy: {}')

        def callback(info):
            logger.warn(text.format(qos_policy_name_from_kind(info.last_policy_kind)))
    peer_kind = (EndpointKind.SUBSCRIPTION if kind is EndpointKind.PUBLISHER
                 else EndpointKind.PUBLISHER)
    event_callbacks = copy.copy(event_callbacks)
    event_callbacks.incompatible_qos = once_per_peer(
        callback, lambda: incompatible_peers(node, resolved, gid, peer_kind))
    return event_callbacks


class BufferEndpoint:
    """Peer bookkeeping of a buffer-aware endpoint (publisher or subscription).

    Peers are the buffer-aware endpoints of the opposite kind on our topic, each with a channel.
    Subclasses set ``_peer_kind`` and implement ``_announce()``, ``_add_peer(info, backends)``
    (create the record and its channel), and optionally ``_update_peer(record, compatible)``,
    ``_forget_peer(gid)`` and ``_release()`` (free the endpoint itself, under the lock).
    The subclass constructor sets ``_lock``, ``_peers``, ``_destroyed``, ``_backends``,
    ``_discovery``, ``_discovery_guard`` (woken by discovery events) and
    ``_topic_name``, and calls :func:`track_endpoint`.
    """

    _peer_kind: EndpointKind
    _lock: threading.RLock
    _peers: Dict[bytes, object]
    _backends: Mapping[str, BufferBackend]

    def _on_peer(self, peer) -> None:
        """Discovery: a peer of our topic appeared or changed its advertisement."""
        if peer.kind is not self._peer_kind:
            return
        with self._lock:
            if self._destroyed:
                return
            known = self._peers.get(peer.gid)
            if not peer.buffer_aware:
                if known is not None:  # it withdrew its advertisement: now a legacy endpoint
                    self._drop_peer(peer.gid)
                return
            info = EndpointInfo(peer.gid, self._topic_name, self._peer_kind)
            if known is None and peer.gid in incompatible_peers(
                    self._node, self._topic_name, self._gid, self._peer_kind):
                # stock endpoints would not communicate: neither do our channels (and an
                # unmatched channel would make both sides re-announce, and log, forever)
                return
            compatible = self._compatible_backends(info, peer.backends)
            if known is None:
                known = self._add_peer(info, dict(peer.backends))
                known.created_at = time.monotonic()
                self._peers[peer.gid] = known
                self._rearm_reannounce_timer()
                if not peer.local:
                    # a new buffer-aware peer whose QoS matches ours may have discovered us
                    # before its tap existed (its node was created well before its endpoint):
                    # announce once now rather than after a second of unmatched channel
                    self._announce()
            known.backends = dict(peer.backends)
            self._update_peer(known, compatible)

    def _start_reannounce_timer(self, node, callback_group) -> None:
        """Prepare the check, once a second, for channels that stay unmatched (see below).

        The timer exists only while some peer's channel is to be watched: it is created with
        the first peer, retires (cancels itself) once every channel is matched, and a new peer
        re-arms it. An endpoint without buffer-aware peers never wakes its executor, as a stock
        one; each wake-up costs a node about half a millisecond of CPU, which at camera rates
        was most of what a publisher spent beyond stock rclpy's.
        """
        self._announced_at = time.monotonic()
        self._spun_at = 0.0
        self._timer_retired = False
        self._reannounce_timer = None
        self._reannounce_timer_args = (node, callback_group)

    def _on_reannounce_timer(self) -> None:
        self._spun_at = time.monotonic()  # evidence that an executor spins our node
        self._reannounce_if_unmatched()
        with self._lock:
            if not self._destroyed and all(
                    peer.channel is None or peer.channel.matched_count() > 0
                    for peer in self._peers.values()):
                self._reannounce_timer.cancel()
                self._timer_retired = True

    def _rearm_reannounce_timer(self) -> None:
        """A new peer's channel is to be watched (under the lock, on the executor's thread:
        only a spun node retires its timer, and a spun node handles discovery there)."""
        if self._reannounce_timer is None:
            node, callback_group = self._reannounce_timer_args
            self._reannounce_timer = node.create_timer(
                UNMATCHED_REANNOUNCE_SECONDS, self._on_reannounce_timer, callback_group)
        elif self._timer_retired:
            self._timer_retired = False
            self._reannounce_timer.reset()

    def _spinning(self, now: float) -> bool:
        """Whether an executor runs our node: then discovery wakes us by itself.

        Evidence: the timer ran lately, or it retired itself (which only a spinning executor
        does). A node that stops spinning after that keeps its matched channels; peers that come
        later are served on the main topic until it spins again.
        """
        return self._timer_retired or now - self._spun_at < SPIN_EVIDENCE_SECONDS

    def _reannounce_if_unmatched(self) -> None:
        """Re-announce our USER_DATA if a known peer's channel stays unmatched.

        Both ends create the channel once each knows the other's advertisement. If one of them
        missed ours (discovery before its listener existed, or a lost update), our end of the
        channel stays unmatched: announcing again lets it see us as a 'changed' endpoint. Each
        side detects this on its own, so no back channel is needed.
        """
        with self._lock:
            if self._destroyed:
                return
            now = time.monotonic()
            if now - self._announced_at < UNMATCHED_REANNOUNCE_SECONDS:
                return
            for peer in self._peers.values():
                if (peer.channel is not None and peer.channel.matched_count() == 0 and
                        now - peer.created_at >= UNMATCHED_REANNOUNCE_SECONDS):
                    self._announced_at = now
                    self._announce()
                    return

    def _peer_node_names(self) -> Dict[bytes, str]:
        """GID -> fully qualified node name of the peers, from the ROS graph (diagnostics)."""
        graph = (self._node.get_subscriptions_info_by_topic
                 if self._peer_kind is EndpointKind.SUBSCRIPTION
                 else self._node.get_publishers_info_by_topic)
        try:
            infos = graph(self._topic_name)
        except Exception:  # the node is being destroyed
            return {}
        return {bytes(info.endpoint_gid): (info.node_namespace.rstrip('/') + '/' +
                                           info.node_name) for info in infos}

    def _compatible_backends(self, info: EndpointInfo, advertised: Mapping[str, str]) -> Set[str]:
        """Ask each backend both sides have whether it can serve this peer."""
        existing = [p.info for p in self._peers.values() if p.info.gid != info.gid]
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

    def _update_peer(self, record, compatible: Set[str]) -> None:
        """Hook: the peer's advertisement was (re)read; ``compatible`` backends can serve it."""

    def _on_peer_gone(self, gid: bytes) -> None:
        """Discovery: a peer went away."""
        with self._lock:
            self._drop_peer(gid)

    def _drop_peer(self, gid: bytes) -> None:
        self._forget_peer(gid)
        peer = self._peers.pop(gid, None)
        if peer is None:
            return
        if peer.channel is not None:
            peer.channel.destroy()
        for backend in self._backends.values():
            backend.on_removing_endpoint(peer.info)

    def _forget_peer(self, gid: bytes) -> None:
        """Hook: drop per-peer state kept outside ``_peers``."""

    def _teardown(self) -> None:
        """Destroy channels, stop discovery and free the endpoint (once).

        Lock order: discovery dispatch holds the discovery lock and then takes ours
        (``_on_peer``), so ours is never held while taking the discovery's.
        """
        with self._lock:
            if self._destroyed:
                return
            self._destroyed = True  # from here on _on_peer adds nothing
        self._discovery.unwatch(dds_topic(self._topic_name), self)
        self._discovery.remove_wakeup(self._discovery_guard)
        with self._lock:
            for gid in list(self._peers):
                self._drop_peer(gid)
            for entity in filter(None, self._node_entities()):
                try:
                    (self._node.destroy_timer if hasattr(entity, 'timer_period_ns')
                     else self._node.destroy_guard_condition)(entity)
                except Exception as exc:  # the node was destroyed first
                    self._logger.debug(f'destroying {entity!r}: {exc}')
            self._release()
        _live_endpoints.discard(self)

    def _node_entities(self) -> list:
        """The timers and guard conditions this endpoint created on its node."""
        return [self._reannounce_timer]

    def _release(self) -> None:
        """Hook: free what else the endpoint holds (called once, under the lock)."""
