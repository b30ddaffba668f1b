"""Discovery of buffer-aware endpoints, per DDS participant (one per rclpy Context).

The native tap (``_native.install_discovery``) records every DataWriter/DataReader discovery
event of the participant, local endpoints included. :class:`ParticipantDiscovery` turns them into
:class:`PeerEndpoint` records (``BUFBE:`` advertisement parsed) and dispatches them, by DDS topic,
to the buffer-aware publishers and subscriptions that watch that topic. Processing happens in
Python threads only (publish(), executor callbacks), never in DDS threads.

Fast DDS cannot replay USER_DATA of endpoints discovered before the tap was installed. So a
buffer-aware endpoint re-announces its USER_DATA while the channel of a buffer-aware peer whose
QoS matches its own stays unmatched (that peer may have missed it: soon after the peer
appeared, then once a second, see :mod:`rosidl_buffer_py.reannounce`); the peer sees it as a
'changed' event. Nothing else re-announces: each re-announce makes DDS re-check
matching at every peer, and stock endpoints with incompatible QoS report it again.

When the context's last node is destroyed (rmw destroys the participant with it, in
``destroy_node()``, before the context shuts down), when the context shuts down, and at
interpreter exit, the participant stops listening to discovery
(``_native.silence_discovery``): rmw destroys a participant with an unbounded wait for
running discovery callbacks that can spin forever in the PyPI build of Fast DDS (see
src/native/README.md, "Discovery tap"), and a participant that no longer listens has none.
"""
import atexit
import functools
import threading
import weakref
from dataclasses import dataclass, field
from typing import Dict, List, Mapping, Optional, Protocol

from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.logging import get_logger

from rosidl_buffer_py import _dds, advertisement
from rosidl_buffer_py import rclpy_seams_7_1 as seams
from rosidl_buffer_py._native import (
    add_discovery_wakeup, install_discovery, remove_discovery_wakeup, silence_discovery,
    silence_discovery_if_last_node)
from rosidl_buffer_py.backend import EndpointInfo, EndpointKind
from rosidl_buffer_py.channel import is_channel_topic

_logger = get_logger('rosidl_buffer_py.discovery')

_KINDS = {'writer': EndpointKind.PUBLISHER, 'reader': EndpointKind.SUBSCRIPTION}
_GONE = ('removed', 'ignored')


@dataclass
class PeerEndpoint:
    """A discovered endpoint of a watched topic and what it advertises."""

    gid: bytes
    kind: EndpointKind
    dds_topic: str
    type_name: str
    backends: Optional[Mapping[str, str]]  #: None for a legacy endpoint
    local: bool
    new: bool = False  #: True on the event that first reports it (not on 'changed'/'known')

    @property
    def buffer_aware(self) -> bool:
        return self.backends is not None

    def endpoint_info(self, ros_topic: str) -> EndpointInfo:
        return EndpointInfo(gid=self.gid, topic_name=ros_topic, endpoint_kind=self.kind)


class Watcher(Protocol):
    """What :meth:`ParticipantDiscovery.watch` dispatches a topic's events to (with the
    discovery's lock held, on the thread that processes discovery)."""

    def on_peer(self, peer: PeerEndpoint) -> None:
        """An endpoint of the topic appeared or changed (its advertisement, say)."""

    def on_peer_gone(self, gid: bytes) -> None:
        """The endpoint ``gid`` of the topic went away."""


@dataclass
class _Watch:
    watchers: 'weakref.WeakSet' = field(default_factory=weakref.WeakSet)


class ParticipantDiscovery:
    """Endpoints of one participant's view of the DDS graph, dispatched to watchers by topic.

    A watcher (a :class:`~rosidl_buffer_py.peers.PeerTable`) is a :class:`Watcher`.
    """

    def __init__(self, node) -> None:
        self._lock = threading.RLock()
        self._nodes: 'weakref.WeakSet' = weakref.WeakSet()
        self._endpoints: Dict[bytes, PeerEndpoint] = {}
        self._watches: Dict[str, _Watch] = {}
        self._installed = install_discovery(node) or True
        self._silenced = False
        self._nodes.add(node)
        for event in _dds.list_known_endpoints(node):
            self._apply(event)

    def attach_node(self, node) -> None:
        """Remember another node of the same participant (any live one can drain events)."""
        with self._lock:
            self._nodes.add(node)

    def watch(self, dds_topic: str, watcher: Watcher) -> List[PeerEndpoint]:
        """Start dispatching events of ``dds_topic`` to ``watcher``; return the known peers."""
        with self._lock:
            self._watches.setdefault(dds_topic, _Watch()).watchers.add(watcher)
            return [p for p in self._endpoints.values() if p.dds_topic == dds_topic]

    def unwatch(self, dds_topic: str, watcher: Watcher) -> None:
        with self._lock:
            watch = self._watches.get(dds_topic)
            if watch is not None:
                watch.watchers.discard(watcher)

    def remote_writers(self) -> Dict[str, str]:
        """DDS topic -> DDS type name of every known writer of other participants (what a
        recorder subscribes to, before the ROS graph cache may list it)."""
        with self._lock:
            return {p.dds_topic: p.type_name for p in self._endpoints.values()
                    if p.kind is EndpointKind.PUBLISHER and not p.local}

    def add_wakeup(self, node, guard_condition) -> None:
        """Trigger ``guard_condition`` whenever a discovery event arrives."""
        add_discovery_wakeup(node, guard_condition)

    def remove_wakeup(self, guard_condition) -> None:
        try:
            remove_discovery_wakeup(guard_condition)
        except Exception as exc:  # the participant may already be gone at shutdown
            _logger.debug(f'remove_discovery_wakeup: {exc}')

    def wake_with(self, node) -> None:
        """Process discovery on the executor that spins ``node``, whatever its endpoints.

        One guard condition per node, not per endpoint: each guard costs the executor a few
        hundred opcodes on every wake-up, a message's too. The tap triggers it whenever an event
        arrives. It is in a reentrant callback group of its own, so no callback of the node
        delays discovery (:meth:`process` serializes itself). rclpy destroys it after the
        node's endpoints, in ``destroy_node()``: its wakeup goes then, and the participant stops
        listening if the node is its context's last (rmw destroys the participant with it,
        before the context shuts down: see :meth:`silence_if_last`).
        """
        guard = node.create_guard_condition(self.process, ReentrantCallbackGroup())
        self.add_wakeup(node, guard)
        seams.before_guard_destroyed(guard, functools.partial(self._node_destroyed, node, guard))

    def _node_destroyed(self, node, guard) -> None:
        self.remove_wakeup(guard)
        self.silence_if_last(node)

    def nodes(self) -> List:
        """The live nodes of this participant that use it."""
        with self._lock:
            return list(self._nodes)

    def silence_if_last(self, node) -> None:
        """:meth:`silence`, when ``node`` is the last node of the participant's context: rmw
        destroys the participant with it, waiting without bound for running discovery
        callbacks (see the module docstring)."""
        with self._lock:
            if self._silenced:
                return
            try:
                if not silence_discovery_if_last_node(node):
                    return
            except Exception as exc:  # the node's handle is gone already
                _logger.debug(f'silence_discovery_if_last_node: {exc}')
                return
            self._silenced = True
        _forget(self)

    def silence(self) -> None:
        """The participant stops listening to discovery (its context shut down, or the process
        exits); nothing is dispatched from now on."""
        with self._lock:
            if self._silenced:
                return
            self._silenced = True
            nodes = list(self._nodes)
        _forget(self)  # a context initialized again gets a new participant, and a new tap
        for node in nodes:
            try:
                silence_discovery(node)
                return
            except Exception as exc:  # node destroyed: try another node of the participant
                _logger.debug(f'silence_discovery: {exc}')

    def process(self) -> None:
        """Drain pending events and dispatch them (cheap when nothing is pending)."""
        with self._lock:
            if self._silenced:
                return
            events = None
            for node in list(self._nodes):
                try:
                    events = _dds.drain_discovery_events(node)
                    break
                except Exception:  # node destroyed: try another node of the participant
                    self._nodes.discard(node)
            if not events:
                return
            dispatch = []
            for event in events:
                item = self._apply(event)
                if item is not None:
                    dispatch.append(item)
            for dds_topic, peer, gid in dispatch:
                watch = self._watches.get(dds_topic)
                for watcher in list(watch.watchers) if watch else ():
                    try:
                        if peer is not None:
                            watcher.on_peer(peer)
                        else:
                            watcher.on_peer_gone(gid)
                    except Exception as exc:  # one bad watcher must not starve the others
                        _logger.error(f'discovery dispatch to {watcher!r} failed: '
                                      f'{type(exc).__name__}: {exc}')

    def _apply(self, event: '_dds.EndpointEvent'):
        if is_channel_topic(event.topic) or event.kind not in _KINDS:
            return None
        if event.status in _GONE:
            if self._endpoints.pop(event.gid, None) is None:
                return None
            return (event.topic, None, event.gid)
        peer = PeerEndpoint(gid=event.gid, kind=_KINDS[event.kind], dds_topic=event.topic,
                            type_name=event.type_name,
                            backends=advertisement.decode(event.user_data), local=event.local,
                            new=event.status == 'discovered')
        self._endpoints[event.gid] = peer
        return (event.topic, peer, event.gid)


_registry_lock = threading.Lock()
_by_context: 'weakref.WeakKeyDictionary' = weakref.WeakKeyDictionary()


def for_node(node) -> ParticipantDiscovery:
    """The discovery of ``node``'s participant (created on first use)."""
    with _registry_lock:
        discovery = _by_context.get(node.context)
        if discovery is None:
            discovery = ParticipantDiscovery(node)
            _by_context[node.context] = discovery
            node.context.on_shutdown(discovery.silence)  # held weakly by the context
        elif node in discovery.nodes():
            return discovery
        else:
            discovery.attach_node(node)
    discovery.wake_with(node)
    return discovery


def registered() -> List[ParticipantDiscovery]:
    """The participants' discoveries in use (one per live, not shut down, context)."""
    with _registry_lock:
        return list(_by_context.values())


def _forget(discovery: ParticipantDiscovery) -> None:
    with _registry_lock:
        for context, known in list(_by_context.items()):
            if known is discovery:
                del _by_context[context]


@atexit.register
def _silence_all() -> None:
    """At exit, before nodes are collected (and rmw destroys their participants): every
    participant with a tap stops listening."""
    for discovery in registered():
        discovery.silence()
