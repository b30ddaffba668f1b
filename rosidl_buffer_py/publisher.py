"""The buffer-aware publisher.

It is an rclpy publisher (created by ``Node.create_publisher`` with ``publisher_class``, so the
node owns it: ``destroy_publisher``, ``destroy_node`` and rclpy's event handlers work as for any
publisher) whose DataWriter also advertises ``BUFBE:cpu=;<backend>=<meta>;...`` in USER_DATA. For
every buffer-aware subscription it discovers, it opens a channel ``rt/<topic>/_buf/<pub gid>_<sub
gid>`` below rcl and, once that channel is up (see ``Publisher._channel_ready``), serves the
subscription there: a descriptor when the backend accepts the peer, CPU bytes otherwise. The main
topic is written while some matched subscription is not served by a channel, and always for a
TRANSIENT_LOCAL publisher (its DataWriter keeps the history late joiners get). A main-topic
sample is kept from the subscriptions a channel serves (writer side: Fast DDS sends them a GAP
instead of the payload, see :func:`rosidl_buffer_py._dds.exclude_from_next_write`).

Each message has one designated route per subscription. Every copy of a message carries the same
explicit source timestamp, increasing per publisher. When a subscription starts being served on
its channel, a *route fence* precedes the first channel message: it names the last message that
went to that subscription on the main topic, which the subscription delivers first. So a
subscription delivers every message once and in publish order without waiting on a clock (see
:mod:`rosidl_buffer_py.subscription`).
"""
import copy
import dataclasses
import threading
import time
from dataclasses import dataclass, field
from typing import Dict, List, NamedTuple, Optional, Set, Tuple, Union

import functools
import struct

import rclpy.publisher
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.logging import get_logger
from rclpy.qos import (
    DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy)

from rosidl_buffer_py import _dds, advertisement, codec, discovery
from rosidl_buffer_py.backend import EndpointInfo, EndpointKind
from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.channel import FENCE_BACKEND, PROBE_BACKEND, channel_topic, dds_topic
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.events import DeadlineMonitor, finite
from rosidl_buffer_py.message_support import buffer_fields, enable_buffer_fields
from rosidl_buffer_py.registry import get_installed_backends
from rosidl_buffer_py.transport import (
    BufferEndpoint, incompatible_qos_once_per_peer, qos_of, reliable_subscription,
    track_endpoint, warn_unsupported_rmw)

_logger = get_logger('rosidl_buffer_py.publisher')

#: How long a channel must have been matched before it serves its subscription.
CHANNEL_SETTLE_SECONDS = 0.2
#: A channel whose reader has not acknowledged the probes yet gets one more at most this often.
PROBE_INTERVAL_SECONDS = 0.01
#: A RELIABLE KEEP_LAST channel up to this depth proves its reader matched by acknowledging
#: ``depth + 1`` probes (see ``Publisher._acknowledged``); a deeper one waits the settle time.
MAX_PROBE_DEPTH = 100
#: publish() of a node that is not spun polls discovery at most this often (spinning nodes are
#: woken by discovery and skip the poll).
DISCOVERY_POLL_SECONDS = 0.02
#: Cached routes are recomputed at least this often, whatever else says they are current.
ROUTES_RECHECK_SECONDS = 0.5
#: ... and this often while a served peer's channel is not known to reach its reader yet.
CONFIRM_RECHECK_SECONDS = 0.05


@dataclass
class _SubscriptionPeer:
    """A buffer-aware subscription of our topic and the channel that serves it."""

    info: EndpointInfo
    backends: Dict[str, str]
    compatible: Set[str] = field(default_factory=set)
    channel: Optional['_dds.ChannelPublisher'] = None
    channel_topic: str = ''
    created_at: float = 0.0
    sent_descriptor: int = 0
    sent_cpu: int = 0
    backend_in_use: Optional[str] = None
    matched_since: Optional[float] = None
    #: Served on the channel by the current routes.
    serving: bool = False
    #: A route fence must precede the next channel message (the peer was just switched to it).
    fence_pending: bool = False
    #: The channel's readiness is acknowledged (see ``Publisher._acknowledged``), not waited for.
    handshake: bool = False
    #: When the last probe was written (0: none yet), and whether the peer acknowledged them.
    probed_at: float = 0.0
    acknowledged: bool = False
    #: Source timestamp of the last message published when the acknowledgment was seen.
    acknowledged_after: int = 0
    #: The channel's reader is known to get what the channel carries (it acknowledged channel
    #: samples): only then are main-topic samples kept from the peer (see ``_current_routes``).
    reaches_reader: bool = False


class _Routes(NamedTuple):
    """Where a message goes: the peers served on their channels, and the main topic.

    Computing them asks the middleware for the main topic's matched subscriptions (tens of
    microseconds), so they are cached. They stay valid while ``signature`` (matched counts of
    the main topic and of every channel) is unchanged, until ``recheck_at`` (a channel
    finishing its settle time, or ``ROUTES_RECHECK_SECONDS``), and until a discovery event
    about our topic (see ``Publisher._on_peer``) drops them.
    """

    peers: Tuple[_SubscriptionPeer, ...]
    main: bool
    signature: tuple
    recheck_at: float
    #: GIDs of the matched subscriptions the main topic serves (not served by a channel).
    unserved: Tuple[bytes, ...]
    #: GIDs of the ``peers`` whose channel is known to reach them: main-topic samples are
    #: withheld from their main-topic readers.
    withheld: Tuple[bytes, ...]


class _Encoder:
    """The wire forms of one message, each made at most once per ``publish()``.

    A message whose payload is CPU memory is written as the message itself (rmw serializes it);
    serialized bytes and Buffer payloads go through the codec: the CPU bytes once, and the
    descriptor form once per distinct descriptor.
    """

    __slots__ = ('msg', 'payload', 'cpu_message', 'vendor', '_fields', '_cpu', '_described')

    def __init__(self, msg, serialized, payload, fields: Tuple[str, ...]) -> None:
        self.msg = msg
        self.payload = payload
        buffer = isinstance(payload, Buffer)
        self.cpu_message = serialized is None and not buffer
        self.vendor = payload.backend_type if buffer and not payload.is_cpu else None
        self._fields = fields
        self._cpu = serialized
        self._described = None

    @property
    def host_buffer(self) -> bool:
        """A message whose payload is a Buffer in host memory: its CPU form is the message
        itself, converted through the buffer protocol (other payload fields: plain data). Only
        asked when some target gets CPU data (a descriptor-only publish skips it)."""
        payload = self.payload
        return (isinstance(payload, Buffer) and payload.host_addressable
                and sum(isinstance(getattr(self.msg, f), Buffer) for f in self._fields) == 1)

    def cpu_bytes(self):
        if self._cpu is None:
            self._cpu = codec.encode(self.msg)
        return self._cpu

    def with_descriptor(self, vendor: str, descriptor: bytes) -> bytearray:
        described = self._described
        if described is None:
            described = self._described = {}
        data = described.get(descriptor)
        if data is None:
            data = described[descriptor] = codec.encode(self.msg, (vendor, descriptor))
        return data


class Publisher(rclpy.publisher.Publisher, BufferEndpoint):
    """Publish messages whose ``uint8[]`` payload may be a :class:`Buffer`.

    Create it with :func:`rosidl_buffer_py.create_publisher`. ``publish(msg)`` takes a message
    whose payload is CPU data (``array.array``, ``bytes``, ...) or a Buffer (for example a
    ``DemoBuffer``), or already serialized CDR ``bytes``.
    """

    def __init__(self, publisher_impl, msg_type, topic: str, qos_profile: QoSProfile, *,
                 event_callbacks: PublisherEventCallbacks, callback_group, node) -> None:
        self._field = codec.payload_field(msg_type)
        enable_buffer_fields(msg_type)
        self._buffer_fields = buffer_fields(msg_type)
        self._transport = _dds.is_supported()
        deadline_callback = None
        if self._transport and event_callbacks.deadline and finite(qos_profile.deadline):
            # counted over every route by a DeadlineMonitor (see rosidl_buffer_py.events)
            deadline_callback = event_callbacks.deadline
            event_callbacks = copy.copy(event_callbacks)
            event_callbacks.deadline = None
        if self._transport:
            event_callbacks = incompatible_qos_once_per_peer(
                event_callbacks, node, publisher_impl, EndpointKind.PUBLISHER,
                _dds.endpoint_gid(publisher_impl, 'publisher'))
        super().__init__(publisher_impl, msg_type, topic, qos_profile,
                         event_callbacks=event_callbacks, callback_group=callback_group)
        self._peer_kind = EndpointKind.SUBSCRIPTION
        self._node = node
        self._lock = threading.RLock()
        self._peers: Dict[bytes, _SubscriptionPeer] = {}
        self._last_timestamp = 0
        self._sent_main = 0
        #: main-topic samples kept from subscriptions served on channels (per subscription)
        self._withheld = 0
        #: None: writer-side exclusion not tried yet; False: this DataWriter cannot do it
        self._exclusions: Optional[bool] = None
        #: the last exclusion registered was not empty (the next main write must re-register)
        self._excluding = False
        self._routes: Optional[_Routes] = None
        #: GID -> source timestamp of the last message the main topic served that subscription
        self._main_timestamps: Dict[bytes, int] = {}
        self._peers_added = 0
        self._peers_removed = 0
        self._destroyed = False
        self._topic_name = super().topic_name  # usable after rclpy destroyed the handle
        if not self._transport:
            warn_unsupported_rmw('publisher', self._topic_name)
            return
        #: TRANSIENT_LOCAL: every message goes to the main DataWriter, whose history late
        #: joiners receive (as CPU bytes; their channels serve them from then on).
        self._main_always = qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        self._manual_liveliness = qos_profile.liveliness == LivelinessPolicy.MANUAL_BY_TOPIC
        self._deadline = (DeadlineMonitor(node, qos_profile.deadline, deadline_callback,
                                          callback_group)
                          if deadline_callback else None)
        self._gid = _dds.endpoint_gid(self)
        self._info = EndpointInfo(self._gid, self._topic_name, EndpointKind.PUBLISHER,
                                  node.get_name(), node.get_namespace())
        self._backends = get_installed_backends()
        advertised = {CPU_BACKEND: ''}
        advertised.update({name: backend.get_backend_metadata()
                           for name, backend in self._backends.items() if name != CPU_BACKEND})
        self._advertised = advertised
        self._handshake = (qos_profile.reliability != ReliabilityPolicy.BEST_EFFORT and
                           qos_profile.history != HistoryPolicy.KEEP_ALL and
                           qos_profile.depth <= MAX_PROBE_DEPTH)
        #: what ``_channel_ready`` writes to learn that a peer's channel reader matched
        self._probe = bytes(codec.encode(msg_type(), (PROBE_BACKEND, b'')))
        self._user_data = advertisement.append(_dds.get_user_data(self), advertised)
        self._discovery = discovery.for_node(node)
        self._announce()
        for backend in self._backends.values():
            backend.on_creating_endpoint(self._info)
        self._discovery_guard = node.create_guard_condition(self._discovery.process,
                                                            callback_group)
        self._discovery.add_wakeup(node, self._discovery_guard)
        self._start_reannounce_timer(node, callback_group)
        self._polled_at = 0.0
        track_endpoint(self)
        with self._lock:
            for peer in self._discovery.watch(dds_topic(self._topic_name), self):
                self._on_peer(peer)

    # rclpy.publisher.Publisher surface ------------------------------------------------------

    @property
    def topic_name(self) -> str:
        """Fully qualified topic name."""
        return self._topic_name

    def wait_for_all_acked(self, timeout: Duration = Duration(seconds=-1)) -> bool:
        """Wait until every subscription acknowledged every message, on every route.

        As rclpy's: a negative timeout waits forever, 0 only checks; True when all is
        acknowledged in time. Channels count: the main topic alone may carry nothing.
        """
        deadline = None if timeout.nanoseconds < 0 else time.monotonic() + timeout.nanoseconds / 1e9
        if not super().wait_for_all_acked(timeout):
            return False
        if not self._transport:
            return True
        with self._lock:
            channels = [p.channel for p in self._peers.values() if p.channel is not None]
        for channel in channels:
            left = -1.0 if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                if not channel.wait_for_all_acked(left):
                    return False
            except _dds.DdsError:  # the peer went away meanwhile: nothing left to acknowledge
                continue
        return True

    def destroy(self) -> None:
        """Destroy the channels, then the publisher (``Node.destroy_publisher`` calls this)."""
        if self._transport:
            self._teardown()
        super().destroy()

    def publish(self, msg) -> None:
        """Publish ``msg`` to every subscription, each by the cheapest route it can take.

        One pipeline: write to the routes the last call found (see :class:`_Routes`), then
        re-check them, off the path the subscribers' latency sees. A target that became needed
        meanwhile (a channel that settled, a new legacy subscriber) gets the message then, with
        the same source timestamp; a route no longer needed costs at most one extra copy, which
        buffer-aware subscriptions drop as a duplicate.
        """
        if isinstance(msg, (bytes, bytearray, memoryview)):
            serialized = msg
        elif isinstance(msg, self.msg_type):
            serialized = None
        else:
            raise TypeError(f'Expected {self.msg_type.__name__} or serialized bytes, '
                            f'got {type(msg).__name__}')
        if not self._transport:
            if serialized is None and isinstance(getattr(msg, self._field), Buffer):
                serialized = bytes(codec.encode(msg))  # stock rclpy cannot convert a Buffer
            super().publish(bytes(serialized) if serialized is not None else msg)
            return
        now = time.monotonic()
        if now - self._polled_at >= DISCOVERY_POLL_SECONDS and not self._spinning(now):
            self._polled_at = now
            self._discovery.process()
            self._reannounce_if_unmatched()
        payload = None if serialized is not None else getattr(msg, self._field)
        encoder = _Encoder(msg, serialized, payload, self._buffer_fields)
        with self._lock:
            if self._destroyed:
                raise RuntimeError(f'publisher of {self._topic_name} was destroyed')
            timestamp = self._next_timestamp()
            used = self._routes
            if used is None:
                used = self._routes = self._current_routes()
            self._write(encoder, timestamp, used.peers, used.main, used.withheld)
            routes = self._valid_routes()
            main = used.main
            if routes is not used:
                self._write(encoder, timestamp,
                            [p for p in routes.peers if not any(p is u for u in used.peers)],
                            routes.main and not used.main,
                            tuple(dict.fromkeys(used.withheld + routes.withheld)))
                main = main or routes.main
            if main:
                self._sent_main += 1
                # noted after both writes: a fence written in the re-check above names the
                # previous message, since this one also went on that peer's channel (the
                # subscription drops main-topic copies from the fence's own message on)
                for gid in (used if used.main else routes).unserved:
                    self._main_timestamps[gid] = timestamp
            elif self._manual_liveliness:
                self.assert_liveliness()  # what a write on the main DataWriter would do
        if self._deadline is not None:
            self._deadline.activity()

    def _write(self, encoder: '_Encoder', timestamp: int, peers, main: bool,
               withheld: Tuple[bytes, ...] = ()) -> None:
        """Write one message to ``peers``' channels (after their route fence, if pending) and,
        when ``main``, to the main topic, whose sample the ``withheld`` subscriptions (their
        channels carry this message) do not get."""
        for peer in peers:
            if peer.fence_pending:
                self._write_fence(peer, encoder.msg, timestamp)
        if encoder.cpu_message:
            # CPU payload: one conversion to C, rmw serializes into each target, as rclpy's
            # publish does (no Python-level CDR work)
            targets = [peer.channel for peer in peers] + ([self] if main else [])
            if main:
                self._exclude_from_main(withheld)
            if targets:
                _dds.write_message(encoder.msg, timestamp, targets)
            for peer in peers:
                peer.sent_cpu += 1
                peer.backend_in_use = CPU_BACKEND
            return
        vendor = encoder.vendor
        cpu_targets = []
        for peer in peers:
            if vendor is not None and vendor in peer.compatible:
                descriptor = self._describe(vendor, encoder.payload, peer)
                if descriptor is not None:
                    peer.channel.publish(encoder.with_descriptor(vendor, descriptor), timestamp)
                    peer.sent_descriptor += 1
                    peer.backend_in_use = vendor
                    continue
            cpu_targets.append(peer.channel)
            peer.sent_cpu += 1
            peer.backend_in_use = CPU_BACKEND
        if main:
            cpu_targets.append(self)
            self._exclude_from_main(withheld)
        if not cpu_targets:
            return
        if encoder.host_buffer:
            # a Buffer in host memory: converted to C through its buffer protocol and
            # serialized by rmw, as rclpy's publish does with an array (no Python-level CDR)
            _dds.write_message(encoder.msg, timestamp, cpu_targets)
            return
        data = encoder.cpu_bytes()
        for target in cpu_targets:
            if target is self:
                _dds.publish_serialized(self, data, timestamp)
            else:
                target.publish(data, timestamp)

    def _exclude_from_main(self, withheld: Tuple[bytes, ...]) -> None:
        """Keep the next main-topic sample from the subscriptions ``withheld`` (their channels
        carry it).

        Registered right before that write (for the DataWriter's next sequence number); an
        empty set is registered only to replace a non-empty one left by a write that failed.
        """
        if self._exclusions is False or not (withheld or self._excluding):
            return
        self._exclusions = _dds.exclude_from_next_write(self, withheld)
        self._excluding = bool(withheld) and self._exclusions
        if self._excluding:
            self._withheld += len(withheld)
        elif self._exclusions is False:
            _logger.warning(
                f'publisher of {self._topic_name}: this Fast DDS DataWriter cannot keep '
                'main-topic samples from subscriptions served on channels; they receive and '
                'drop them (costs CPU, loses nothing)', once=True)

    def _write_fence(self, peer: _SubscriptionPeer, msg, timestamp: int) -> None:
        """Tell a subscription just switched to its channel which main-topic message came last.

        Written on the channel right before the first channel message (same source timestamp),
        it carries the source timestamp of the last message the main topic served that
        subscription (0: none). The subscription delivers main-topic messages up to it first.
        """
        last_main = self._main_timestamps.get(peer.info.gid, 0)
        _logger.debug(f'route fence to {peer.info.gid_hex} (last main-topic message {last_main})')
        peer.channel.publish(codec.encode(msg, (FENCE_BACKEND, _FENCE.pack(last_main))),
                             timestamp)
        peer.fence_pending = False

    def _valid_routes(self) -> '_Routes':
        """The cached routes if they are still current, else freshly computed (and cached)."""
        routes = self._routes
        if (routes is None or time.monotonic() >= routes.recheck_at or
                self._route_signature() != routes.signature):
            routes = self._routes = self._current_routes()
        return routes

    def _route_signature(self) -> tuple:
        """Matched counts of the main topic and of every channel (cheap: no GID lists)."""
        return (self.get_subscription_count(),
                tuple(-1 if peer.channel is None else peer.channel.matched_count()
                      for peer in self._peers.values()))

    def _current_routes(self) -> '_Routes':
        """The channels that serve their peers now, and whether the main topic is needed.

        A peer that starts being served here gets a route fence before its next channel
        message (see :meth:`_write_fence`).
        """
        signature = self._route_signature()
        now = time.monotonic()
        recheck_at = now + ROUTES_RECHECK_SECONDS
        peers = []
        for peer in self._peers.values():
            ready = peer.channel is not None and self._channel_ready(peer)
            if ready:
                peers.append(peer)
                if not peer.serving:
                    peer.fence_pending = True
            elif peer.matched_since is not None:  # settling: ready at the end of it, or once
                recheck_at = min(recheck_at, now if peer.handshake else  # acknowledged
                                 peer.matched_since + CHANNEL_SETTLE_SECONDS)
            if ready and not peer.reaches_reader and peer.handshake:
                # served since the last routes (its fence is written) and every channel sample
                # acknowledged: its reader matched, and gets the rest
                peer.reaches_reader = peer.acknowledged or (
                    peer.serving and peer.channel.wait_for_all_acked(0.0))
                if not peer.reaches_reader:
                    recheck_at = min(recheck_at, now + CONFIRM_RECHECK_SECONDS)
            peer.serving = ready
        served = {peer.info.gid for peer in peers}
        unserved = tuple(gid for gid in _dds.matched_subscription_gids(self)
                         if gid not in served)
        main = bool(unserved) or self._main_always
        # Main-topic samples skip only peers whose channel is known to reach them: a channel
        # serving by its settle time alone may not yet (the reader matches the writer late),
        # and meanwhile the subscription still needs the main-topic copies.
        withheld = tuple(peer.info.gid for peer in peers if peer.reaches_reader)
        return _Routes(tuple(peers), main, signature, recheck_at, unserved, withheld)

    # diagnostics ----------------------------------------------------------------------------

    def buffer_peers(self) -> List[dict]:
        """The buffer-aware subscriptions this publisher serves, and how."""
        names = self._peer_node_names()
        with self._lock:
            return [{
                'gid': peer.info.gid_hex,
                'node': names.get(peer.info.gid, ''),
                'advertised_backends': dict(peer.backends),
                'compatible_backends': sorted(peer.compatible),
                'channel_topic': peer.channel_topic,
                'channel_matched': bool(peer.channel and peer.channel.matched_count()),
                'channel_serving': bool(peer.channel and self._channel_ready(peer)),
                'backend_in_use': peer.backend_in_use,
                'sent_as_descriptor': peer.sent_descriptor,
                'sent_as_cpu': peer.sent_cpu,
            } for peer in self._peers.values()]

    def statistics(self) -> dict:
        """Counters: messages written on the main topic, and per-peer counts."""
        with self._lock:
            return {'gid': self._gid.hex() if self._transport else None,
                    'buffer_aware': self._transport,
                    'advertised_backends': dict(getattr(self, '_advertised', {})),
                    'sent_on_main_topic': self._sent_main,
                    'main_topic_withheld': self._withheld,
                    'peers_added': self._peers_added, 'peers_removed': self._peers_removed,
                    'peers': self.buffer_peers()}

    # internals ------------------------------------------------------------------------------

    def _next_timestamp(self) -> int:
        now = time.time_ns()
        self._last_timestamp = now if now > self._last_timestamp else self._last_timestamp + 1
        return self._last_timestamp

    def _channel_ready(self, peer: _SubscriptionPeer) -> bool:
        """True once what the channel carries from now on reaches the peer's reader.

        The channel writer matches the peer's reader before, sometimes long before, that reader
        matches the writer: what is written meanwhile reaches the reader only if the writer
        still holds it when the reader asks (KEEP_LAST), so a route fence written too early can
        be lost. A RELIABLE reader proves that it matched by acknowledging the probes written
        once the writer matched it (see :meth:`_acknowledged`); otherwise the channel serves
        once it has been matched for ``CHANNEL_SETTLE_SECONDS``. Until then the main topic
        serves the peer, so bring-up loses nothing.
        """
        if peer.channel.matched_count() == 0:
            if peer.matched_since is not None:
                # its reader left; if it comes back, the channel settles: no probe may follow a
                # route fence (the subscription may take later samples as messages)
                peer.handshake = peer.acknowledged = peer.reaches_reader = False
            peer.matched_since = None
            return False
        if peer.serving:
            # Once its route fence is out, the channel carries every message while it stays
            # matched: the subscription drops main-topic copies from the fence's message on,
            # so serving the peer on the main topic again would lose those messages.
            return True
        now = time.monotonic()
        if peer.matched_since is None:
            peer.matched_since = now
            _logger.debug(f'channel to {peer.info.gid_hex} matched')
        if now - peer.matched_since >= CHANNEL_SETTLE_SECONDS:
            return True
        if not peer.acknowledged and not (peer.handshake and self._acknowledged(peer, now)):
            return False
        # The route fence names the last main-topic message written for the peer, which the
        # subscription waits for: none, or one written after the acknowledgment was seen. The
        # peer's main-topic reader had matched our writer by then (its discovery of our writer
        # came before that of the channel's, on the same path), so it gets that one; one
        # written before may be gone from our KEEP_LAST history when the new reader asks.
        last_main = self._main_timestamps.get(peer.info.gid)
        return last_main is None or last_main > peer.acknowledged_after

    def _acknowledged(self, peer: _SubscriptionPeer, now: float) -> bool:
        """Whether the peer's reader acknowledged the probes; writes them (or one more) first.

        A reader acknowledges only writers it matched, and only when a heartbeat asks, which
        Fast DDS sends with a write while its KEEP_LAST history is full (else every few
        seconds): so ``depth + 1`` probes go first, and one more at most every
        ``PROBE_INTERVAL_SECONDS`` while unacknowledged. Probes are the only channel samples
        before the route fence, so "all acknowledged" means the probes.
        """
        if peer.probed_at and peer.channel.wait_for_all_acked(0.0):
            peer.acknowledged = True
            peer.acknowledged_after = self._last_timestamp
            _logger.debug(f'channel to {peer.info.gid_hex} acknowledged '
                          f'{1000 * (now - peer.matched_since):.0f} ms after its match')
            return True
        if now - peer.probed_at >= PROBE_INTERVAL_SECONDS:
            timestamp = self._last_timestamp or time.time_ns()
            for _ in range(1 if peer.probed_at else self.qos_profile.depth + 1):
                peer.channel.publish(self._probe, timestamp)
            peer.probed_at = now
        return False

    def _describe(self, vendor: str, payload: Buffer, peer: _SubscriptionPeer) -> Optional[bytes]:
        try:
            return self._backends[vendor].create_descriptor_with_endpoint(payload, peer.info)
        except Exception as exc:  # a failing backend degrades to CPU bytes for this message
            _logger.error(f'backend {vendor!r} failed to describe a buffer for '
                          f'{peer.info.gid_hex}: {type(exc).__name__}: {exc}; sending CPU bytes',
                          throttle_duration_sec=5.0)
            return None

    def _announce(self) -> None:
        """(Re-)set USER_DATA: peers discover, or re-discover, our advertisement."""
        _dds.set_user_data(self, self._user_data)

    def _release(self) -> None:
        if self._exclusions:
            try:  # before rclpy destroys the DataWriter the filter sits on
                _dds.remove_write_exclusions(self)
            except Exception as exc:  # rclpy already destroyed it (exit): nothing left to do
                _logger.debug(f'removing the main-topic exclusions: {exc}')
        super()._release()

    def _node_entities(self) -> list:
        entities = [self._reannounce_timer, self._discovery_guard]
        if self._deadline is not None:
            entities.append(self._deadline.timer)
        return entities

    def _add_peer(self, info: EndpointInfo, backends: Dict[str, str]) -> _SubscriptionPeer:
        # backends account per channel: which local publisher serves this peer
        info = dataclasses.replace(info, local_gid=self._gid)
        record = _SubscriptionPeer(info=info, backends=backends)
        record.channel_topic = channel_topic(self._topic_name, self._gid, info.gid)
        record.channel = _dds.create_channel_publisher(
            self._node, self.msg_type, record.channel_topic, self.qos_profile)
        record.handshake = self._handshake and reliable_subscription(
            self._node, self._topic_name, info.gid)
        self._peers_added += 1
        return record

    def _on_peer(self, peer) -> None:
        # any subscription of our topic coming or changing, legacy ones too, may change routes
        if peer.kind is self._peer_kind:
            with self._lock:
                self._routes = None
        super()._on_peer(peer)

    def _on_peer_gone(self, gid: bytes) -> None:
        with self._lock:
            self._routes = None
            self._main_timestamps.pop(gid, None)
        super()._on_peer_gone(gid)

    def _update_peer(self, record: _SubscriptionPeer, compatible: Set[str]) -> None:
        record.compatible = compatible  # (_on_peer already dropped the routes)

    def _forget_peer(self, gid: bytes) -> None:
        if gid in self._peers:
            self._peers_removed += 1


#: The route fence's payload: the source timestamp of the last main-topic message (uint64 LE).
_FENCE = struct.Struct('<Q')


def create_publisher(node, msg_type, topic: str, qos_profile: Union[QoSProfile, int], *,
                     callback_group=None, event_callbacks=None,
                     qos_overriding_options=None) -> Publisher:
    """Create a buffer-aware publisher on ``node`` (arguments as ``Node.create_publisher``).

    The node owns it like any publisher: ``node.destroy_publisher(pub)`` and
    ``node.destroy_node()`` destroy it, and its ``event_callbacks`` fire as rclpy's do.
    """
    if _dds.is_supported():
        discovery.for_node(node)  # the tap goes first: peers re-announce when they see us
    return node.create_publisher(
        msg_type, topic, qos_of(qos_profile), callback_group=callback_group,
        event_callbacks=event_callbacks, qos_overriding_options=qos_overriding_options,
        publisher_class=functools.partial(Publisher, node=node))
