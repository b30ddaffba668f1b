"""The buffer-aware publisher.

It is an rclpy publisher (created by ``Node.create_publisher`` with ``publisher_class``, so the
node owns it: ``destroy_publisher``, ``destroy_node`` and rclpy's event handlers work as for any
publisher) whose DataWriter also advertises ``BUFBE:cpu=;<backend>=<meta>;...`` in USER_DATA. For
every buffer-aware subscription it discovers, it opens a channel ``rt/<topic>/_buf/<pub gid>_<sub
gid>`` below rcl and, once that channel is up (see :mod:`rosidl_buffer_py.routes`), serves the
subscription there: a descriptor when the backend accepts the peer, CPU bytes otherwise. The main
topic is written while some matched subscription is not served by a channel, and always for a
TRANSIENT_LOCAL publisher (its DataWriter keeps the history late joiners get). A main-topic
sample is kept from the subscriptions a channel serves (writer side: Fast DDS sends them a GAP
instead of the payload, see :func:`rosidl_buffer_py._native.exclude_from_next_write`).

Each message has one designated route per subscription, which the route protocol decides
(:mod:`rosidl_buffer_py.routes`: one :class:`~rosidl_buffer_py.routes.Route` per buffer-aware
subscription, in a :class:`~rosidl_buffer_py.routes.RouteTable`). This class feeds it what DDS
says (matched channels, acknowledged samples, matched main-topic subscriptions) and carries out
its plan: probes and route fences (:mod:`rosidl_buffer_py.control`), channel writes, the
main-topic write and whom it is kept from. Every copy of a message carries the same explicit
source timestamp, increasing per publisher, so a subscription delivers every message once and in
publish order (see :mod:`rosidl_buffer_py.subscription`).
"""
import dataclasses
import functools
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, NamedTuple, Optional, Set, Tuple, Union

import rclpy.publisher
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.logging import LoggingSeverity
from rclpy.qos import (
    DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy)

from rosidl_buffer_py import _dds, codec, control, discovery, routes
from rosidl_buffer_py import rclpy_seams_7_1 as seams
from rosidl_buffer_py._native import (
    endpoint_gid, exclude_from_next_write, matched_subscription_gids, publish_serialized,
    remove_write_exclusions, write_message)
from rosidl_buffer_py.backend import EndpointGone, EndpointInfo, EndpointKind
from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.channel import channel_topic
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.diagnostics import PublisherStatistics, SubscriptionPeer
from rosidl_buffer_py.endpoint import (
    ChannelPeer, EndpointCore, advertise, advertised_backends, buffer_aware, split_deadline)
from rosidl_buffer_py.message_support import enable_buffer_fields
from rosidl_buffer_py.on_demand import OnDemandTimer
from rosidl_buffer_py.peers import PeerHandlers, PeerTable
from rosidl_buffer_py.plain import PlainPublisher, check_wait_arguments
from rosidl_buffer_py.qos import (
    incompatible_qos_once_per_peer, parse_history_metadata, reliable_subscription)
from rosidl_buffer_py.registry import get_installed_backends
from rosidl_buffer_py.throttle import Throttle


#: ``wait_for_all_acked`` that only checks.
_NO_WAIT = Duration(seconds=0)
#: publish() of a node that is not spun polls discovery at most this often (spinning nodes are
#: woken by discovery and skip the poll).
DISCOVERY_POLL_SECONDS = 0.02
#: After the discovery epoch or the peer table moves, the route signature is read from DDS on
#: every message for this long (Fast DDS pairs endpoints right after discovery callbacks).
EPOCH_GRACE_SECONDS = 1.0
#: At most one "failed to describe" line per this many seconds.
DESCRIBE_FAILURE_LOG_SECONDS = 5.0


@dataclass
class _SubscriptionPeer(ChannelPeer):
    """A buffer-aware subscription of our topic, its channel (a ChannelPublisher) and its
    route."""

    route: routes.Route = field(kw_only=True)
    compatible: Set[str] = field(default_factory=set)
    sent_descriptor: int = 0
    sent_cpu: int = 0


class _RouteView:
    """What DDS says of one publisher's routes (:class:`rosidl_buffer_py.routes.RouteView`),
    read from its main DataWriter and its peers' channels."""

    __slots__ = ('_writer', '_peers', '_main_count', '_epoch', '_seen', '_signature',
                 '_read_at', '_trust_from')

    def __init__(self, writer: 'Publisher', peers: PeerTable) -> None:
        self._writer = writer
        self._peers = peers
        #: the main DataWriter's matched count, one C call (the view is read under the
        #: publisher's lock, which its destroy() takes first)
        self._main_count = seams.subscription_counter(writer)
        self._epoch = _dds.discovery_epoch()
        #: (discovery epoch, peer table version) when the signature was last read from DDS
        self._seen = None
        self._signature = None
        self._read_at = self._trust_from = 0.0

    def signature(self, fresh: bool = False) -> tuple:
        """Matched counts of the main topic and of every channel.

        Read from DDS (one C call each, running DDS's code) only when they may have changed:
        a matched count changes only shortly after a discovery callback, which moves the
        process's discovery epoch (a read of memory), or when the peer table changes. After
        either moves they are read on every call for ``EPOCH_GRACE_SECONDS`` (Fast DDS pairs
        an endpoint right after the callback), and at least every ``routes.RECHECK_SECONDS``
        whatever happens; ``fresh``: now (the table re-plans)."""
        now = time.monotonic()
        if not fresh and self.settled(now) and now - self._read_at < routes.RECHECK_SECONDS:
            return self._signature
        seen = (self._epoch[0], self._peers.version)
        if seen != self._seen:
            self._seen = seen
            self._trust_from = now + EPOCH_GRACE_SECONDS
        self._read_at = now
        self._signature = (self._main_count(),
                           tuple(-1 if peer.channel is None else peer.channel.matched_count()
                                 for peer in self._peers))
        return self._signature

    def settled(self, now: float) -> bool:
        # nothing moved since the last reading and no grace (signature() re-reads on its own
        # every RECHECK_SECONDS too: the route table's re-plans read fresh at that pace)
        return (self._epoch[0], self._peers.version) == self._seen and self._trust_from <= now

    def matched_subscriptions(self) -> List[bytes]:
        return matched_subscription_gids(self._writer)

    def channel_matched(self, key: bytes) -> bool:
        channel = self._peers[key].channel
        return channel is not None and channel.matched_count() > 0

    def channel_acknowledged(self, key: bytes) -> bool:
        return self._peers[key].channel.wait_for_all_acked(0.0)

    def main_acknowledged(self) -> bool:
        # the main DataWriter alone (Publisher.wait_for_all_acked also waits for channels)
        return rclpy.publisher.Publisher.wait_for_all_acked(self._writer, _NO_WAIT)


class _SteadyLane(NamedTuple):
    """The writes of the route table's steady dispatch, prepared once (see
    :meth:`Publisher._publish_steady`): each served subscription with its backend's steady
    describer (:meth:`~rosidl_buffer_py.backend.BufferBackend.steady_describer`)."""

    #: The table's steady dispatch it was prepared for (``RouteTable.steady``, by identity).
    dispatch: routes.Dispatch
    #: The peer table's version then (a peer's backends or ledger change with it).
    version: int
    #: The backend whose Buffers every describer describes.
    backend: str
    targets: Tuple[Tuple['_SubscriptionPeer', Callable[[Buffer], Optional[bytes]]], ...]


class _Encoder:
    """The wire forms of one message, each made at most once per ``publish()``.

    A message without Buffers is written as the message itself (rmw converts and serializes
    it, as rclpy does); serialized bytes and messages holding Buffers (in any ``uint8[]`` field,
    see :func:`rosidl_buffer_py.codec.buffers_of`) go through the codec: the CPU bytes once,
    and the descriptor form once per distinct set of descriptors.
    """

    __slots__ = ('msg', 'buffers', 'cpu_message', '_single', '_described_program', '_cpu',
                 '_described')

    def __init__(self, msg, serialized, buffers: List[codec.BufferAt],
                 single: Optional[str], program: Optional[tuple]) -> None:
        self.msg = msg
        #: the Buffers not in CPU memory: what descriptors can describe
        self.buffers = [at for at in buffers if not at.buffer.is_cpu]
        self.cpu_message = serialized is None and not buffers
        self._single = single if len(buffers) == 1 else None
        #: the type's codec.descriptor_program (the one payload's descriptor form from C)
        self._described_program = program
        self._cpu = serialized
        self._described = None

    @property
    def host_buffer(self) -> bool:
        """A message whose one payload (its top-level ``uint8[]``) is a Buffer in host memory:
        its CPU form is the message itself, converted through the buffer protocol. Only asked
        when some target gets CPU data (a descriptor-only publish skips it)."""
        if self._single is None:
            return False
        payload = getattr(self.msg, self._single)
        return isinstance(payload, Buffer) and payload.host_addressable

    def cpu_bytes(self):
        if self._cpu is None:
            self._cpu = codec.encode(self.msg)
        return self._cpu

    def write_described(self, described: Tuple[Tuple[codec.FieldPath, str, bytes], ...],
                        channel, timestamp: int) -> None:
        """Write the descriptor form with these ``(path, backend, descriptor)`` on ``channel``:
        the one payload's form written from the message's slots straight into the DataWriter
        (one native call: no encoded bytes object, no Python-level codec work), else
        :meth:`with_descriptors` published."""
        if self._single is not None and self._described_program is not None:
            (_, backend, descriptor), = described
            if write_message(self.msg, timestamp, (channel,), self._described_program,
                             (backend, descriptor)):
                return
        channel.publish(self.with_descriptors(described), timestamp)

    def with_descriptors(self, described: Tuple[Tuple[codec.FieldPath, str, bytes], ...]
                         ) -> bytearray:
        """The descriptor form with these ``(path, backend, descriptor)``, the other fields as
        CPU bytes."""
        cache = self._described
        if cache is None:
            cache = self._described = {}
        data = cache.get(described)
        if data is None:
            if self._single is not None:  # the one payload: its pair, no path to check
                (_, backend, descriptor), = described
                data = codec.encode(self.msg, (backend, descriptor))
            else:
                data = codec.encode(self.msg, {path: (backend, descriptor)
                                               for path, backend, descriptor in described})
            cache[described] = data
        return data


class Publisher(rclpy.publisher.Publisher):
    """Publish messages of any type whose ``uint8[]`` fields may hold :class:`Buffer` objects.

    Create it with :func:`rosidl_buffer_py.create_publisher`. ``publish(msg)`` takes a message
    whose ``uint8[]`` fields (at any depth) hold CPU data (``array.array``, ``bytes``, ...) or
    Buffers (for example ``DemoBuffer``), or already serialized CDR ``bytes``. A type without
    ``uint8[]`` fields gets a :class:`~rosidl_buffer_py.plain.PlainPublisher` instead.

    What it shares with the subscription (identity, advertisement, its buffer-aware
    subscriptions as a :class:`~rosidl_buffer_py.peers.PeerTable`, deadline, teardown) is its
    :class:`~rosidl_buffer_py.endpoint.EndpointCore`; their routes are a
    :class:`~rosidl_buffer_py.routes.RouteTable`.
    """

    def __init__(self, publisher_impl, msg_type, topic: str, qos_profile: QoSProfile, *,
                 event_callbacks: PublisherEventCallbacks, callback_group, node) -> None:
        #: every uint8[] field, at any depth
        self._paths = codec.buffer_paths(msg_type)
        enable_buffer_fields(msg_type)
        #: the one top-level uint8[] field when that is all the type has (Image: 'data'),
        #: read directly on the hot path
        self._single = (self._paths[0][0] if len(self._paths) == 1 and len(self._paths[0]) == 1
                        else None)
        #: writes CPU messages' CDR from their slots in C (codec.program_of), or None
        self._program = codec.program_of(msg_type)
        self._described_program = codec.descriptor_program(msg_type)
        # the DataWriter was created disabled (create_publisher): its first announcement
        # carries the advertisement, and it is enabled as soon as that is set (what runs
        # meanwhile in other threads, a channel's creation say, waits for nothing of ours)
        backends = get_installed_backends()
        advertised = advertised_backends(backends, '')
        user_data = advertise(publisher_impl, EndpointKind.PUBLISHER, advertised)
        _dds.enable_created(node, 'publisher')
        event_callbacks, deadline = split_deadline(event_callbacks, qos_profile)
        event_callbacks = incompatible_qos_once_per_peer(
            event_callbacks, node, publisher_impl, EndpointKind.PUBLISHER,
            endpoint_gid(publisher_impl, 'publisher'), topic)
        super().__init__(publisher_impl, msg_type, topic, qos_profile,
                         event_callbacks=event_callbacks, callback_group=callback_group)
        self._node = node
        self._topic_name = super().topic_name  # usable after rclpy destroyed the handle
        self._last_timestamp = 0
        self._sent_main = 0
        #: main-topic samples kept from subscriptions served on channels (per subscription)
        self._withheld = 0
        #: main-topic samples sent to subscriptions their channels carried too (per subscription)
        self._doubled = 0
        self._describe_failures_logged = Throttle(DESCRIBE_FAILURE_LOG_SECONDS)
        #: CPU copies written on channels to peers that share a backend with the message's
        #: Buffers (the backend declined: pool exhausted, or the peer cannot be reached)
        self._cpu_to_capable = 0
        #: None: writer-side exclusion not tried yet; False: this DataWriter cannot do it
        self._exclusions: Optional[bool] = None
        #: the last exclusion registered was not empty (the next main write must re-register)
        self._excluding = False
        self._peers_added = 0
        self._peers_removed = 0
        self._polled_at = 0.0
        #: The steady dispatch's writes, prepared (None: none prepared, or not preparable)
        self._lane: Optional[_SteadyLane] = None
        self._on_lane = 0  #: messages published through it
        #: The steady dispatch a lane was last prepared for, or found not preparable for
        self._lane_tried: Optional[routes.Dispatch] = None
        #: TRANSIENT_LOCAL: every message goes to the main DataWriter, whose history late
        #: joiners receive (as CPU bytes; their channels serve them from then on).
        self._table: routes.RouteTable[bytes] = routes.RouteTable(
            main_always=qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL)
        self._manual_liveliness = qos_profile.liveliness == LivelinessPolicy.MANUAL_BY_TOPIC
        #: RELIABLE KEEP_LAST channels can acknowledge probes (see routes.Route)
        self._handshake = (qos_profile.reliability != ReliabilityPolicy.BEST_EFFORT and
                           qos_profile.history != HistoryPolicy.KEEP_ALL)
        core = self._core = EndpointCore(
            node, self, EndpointKind.PUBLISHER, topic_name=self._topic_name, backends=backends,
            advertised=advertised, user_data=user_data, qos_profile=qos_profile,
            callback_group=callback_group, deadline=deadline,
            handlers=PeerHandlers(self._peer_seen, self._channels_checked, self._add_peer,
                                  self._update_peer, self._forget_peer, self._peer_gone,
                                  self._release))
        self._lock = core.lock
        self._logger = core.logger
        self._route_timer = OnDemandTimer(node, routes.PROBE_INTERVAL_SECONDS,
                                          self._on_route_timer, callback_group, core.logger)
        self._peers: PeerTable[_SubscriptionPeer] = core.peers
        self._view = _RouteView(self, core.peers)
        core.open()

    # rclpy.publisher.Publisher surface ------------------------------------------------------

    @property
    def topic_name(self) -> str:
        """Fully qualified topic name."""
        return self._topic_name

    def wait_for_buffer_peers(self, count: int = 1, timeout_sec: Optional[float] = None
                              ) -> bool:
        """Wait until ``count`` buffer-aware subscriptions are served on their channels (their
        next messages go zero-copy where they share a backend); True when they are in time.

        Frames published before a new buffer-aware subscription's channel is up reach it as CPU
        bytes: a camera that wants its first frames zero-copy waits here first. Plain
        subscriptions (rviz, recorders) need no wait and are not counted. Works whether an
        executor spins the node or not (discovery and the routes are moved on here too, as
        ``publish`` does); ``timeout_sec`` None waits forever, 0 only checks.
        """
        check_wait_arguments(count, timeout_sec)
        deadline = None if timeout_sec is None else time.monotonic() + timeout_sec
        while True:
            now = time.monotonic()
            if not self._peers.reannouncer.spinning(now):
                self._peers.poll()  # nobody else processes discovery for this node
            with self._lock:
                if self._peers.closed:
                    raise RuntimeError(f'publisher of {self._topic_name} was destroyed')
                self._advance()
                served = sum(peer.route.on_channel for peer in self._peers)
            if served >= count:
                return True
            if deadline is not None and now >= deadline:
                return False
            time.sleep(routes.PROBE_INTERVAL_SECONDS if deadline is None else
                       max(0.0, min(routes.PROBE_INTERVAL_SECONDS, deadline - now)))

    def wait_for_all_acked(self, timeout: Duration = Duration(seconds=-1)) -> bool:
        """Wait until every subscription acknowledged every message, on every route.

        As rclpy's: a negative timeout waits forever, 0 only checks; True when all is
        acknowledged in time. Channels count: the main topic alone may carry nothing.
        """
        deadline = None if timeout.nanoseconds < 0 else time.monotonic() + timeout.nanoseconds / 1e9
        if not super().wait_for_all_acked(timeout):
            return False
        with self._lock:
            channels = [p.channel for p in self._peers if p.channel is not None]
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
        self._core.close()
        super().destroy()

    def publish(self, msg) -> None:
        """Publish ``msg`` to every subscription, each by the cheapest route it can take.

        The route table decides where it goes, with the probes and route fences due
        (:meth:`~rosidl_buffer_py.routes.RouteTable.dispatch`); this method writes exactly
        that, every copy with the same source timestamp.
        """
        lane = self._lane
        if lane is not None and type(msg) is self.msg_type and self._publish_steady(lane, msg):
            return
        if isinstance(msg, (bytes, bytearray, memoryview)):
            serialized = msg
        elif isinstance(msg, self.msg_type):
            serialized = None
        else:
            raise TypeError(f'Expected {self.msg_type.__name__} or serialized bytes, '
                            f'got {type(msg).__name__}')
        now = time.monotonic()
        if (now - self._polled_at >= DISCOVERY_POLL_SECONDS and
                not self._peers.reannouncer.spinning(now)):
            self._polled_at = now
            self._peers.poll()
        encoder = _Encoder(msg, serialized, [] if serialized is not None else
                           self._buffers_of(msg), self._single, self._described_program)
        with self._lock:
            if self._peers.closed:
                raise RuntimeError(f'publisher of {self._topic_name} was destroyed')
            previous = self._last_timestamp
            timestamp = self._next_timestamp()
            self._write_dispatched(encoder, previous, timestamp,
                                   self._table.dispatch(time.monotonic(), timestamp, self._view))
        self._core.activity()

    def _write_dispatched(self, encoder: '_Encoder', previous: int, timestamp: int,
                          dispatch: routes.Dispatch) -> None:
        """Write message ``timestamp`` (``previous``: the one before it, 0 for none) as the
        route table's ``dispatch`` says, its probes and route timer included, and prepare the
        steady lane when that is the table's steady answer. Under the lock."""
        if dispatch.probes:
            self._write_probes(dispatch.probes, previous or timestamp - 1)
        if dispatch.timer is not None:
            self._arm_route_timer(dispatch.timer)
        self._write(encoder, timestamp, dispatch)
        if dispatch is self._table.steady and dispatch is not self._lane_tried and \
                len(encoder.buffers) == 1 and self._peers.reannouncer.retired:
            # (tried once per steady answer, which a re-plan that keeps it keeps: not before
            # the node is known to spin, which comes later than the answer in a new graph)
            self._lane_tried = dispatch
            self._lane = self._prepare_lane(dispatch, encoder)
        if dispatch.main:
            self._sent_main += 1
        elif self._manual_liveliness:
            self.assert_liveliness()  # what a write on the main DataWriter would do

    def _publish_steady(self, lane: _SteadyLane, msg) -> bool:
        """publish() while the routes are steady: the message goes where ``lane`` was prepared
        for, each descriptor from its peer's steady describer; a peer whose describer declines
        gets what :meth:`_write` gives it. When the route table answers otherwise
        (:meth:`~rosidl_buffer_py.routes.RouteTable.dispatch_prepared`: a transition, or a
        re-plan to another answer), the message is written as that answer says, as publish()
        writes it. False, having written nothing, when the peer table moved or the payload is
        not a Buffer. (publish() skips its discovery poll: a lane exists only while the node
        is known to spin, see :meth:`_prepare_lane`.)"""
        payload = getattr(msg, self._single)
        if not isinstance(payload, Buffer):
            return False
        now = time.monotonic()
        with self._lock:
            if self._peers.closed or lane.version != self._peers.version:
                return False
            previous = self._last_timestamp
            timestamp = self._next_timestamp()
            dispatch = self._table.dispatch_prepared(lane.dispatch, now, timestamp, self._view)
            if dispatch is not lane.dispatch:
                self._write_dispatched(
                    _Encoder(msg, None, self._buffers_of(msg), self._single,
                             self._described_program), previous, timestamp, dispatch)
                self._core.activity()
                return True
            # the lane's writes, inline (a method call more costs every message a cold frame)
            self._on_lane += 1
            declined = []
            backend, program = lane.backend, self._described_program
            for peer, describe in lane.targets:
                try:
                    descriptor = describe(payload)
                except Exception:  # the full describe runs next, and logs what fails there
                    descriptor = None
                if descriptor is None:
                    declined.append((peer.info.gid, None))
                    continue
                if not write_message(msg, timestamp, (peer.channel,), program,
                                     (backend, descriptor)):
                    peer.channel.publish(codec.encode(msg, (backend, descriptor)), timestamp)
                peer.sent_descriptor += 1
                peer.backend_in_use = backend
            if declined:
                self._write(_Encoder(msg, None, self._buffers_of(msg), self._single, program),
                            timestamp, routes.Dispatch((), tuple(declined), False, (), None))
            if self._manual_liveliness:
                self.assert_liveliness()  # what a write on the main DataWriter would do
            if self._table.replan_due:  # the periodic re-plan, after this message's writes
                self._advance()
        self._core.activity()
        return True

    def _prepare_lane(self, dispatch: routes.Dispatch, encoder: '_Encoder'
                      ) -> Optional[_SteadyLane]:
        """The steady lane for ``dispatch`` (the table's steady one), for messages like
        ``encoder``'s: its one payload a Buffer of a backend that every served peer accepts and
        that has a steady describer for each; None otherwise. Asked only once the node is known
        to spin (until then publish() polls discovery; the re-announcer's retirement lasts
        until a new peer comes, which moves the peer table's version). Under the lock."""
        if self._single is None or self._described_program is None or not dispatch.channel:
            return None
        backend = encoder.buffers[0].buffer.backend_type
        vendor = self._core.backends.get(backend)
        if vendor is None:
            return None
        targets = []
        for key, _ in dispatch.channel:
            peer = self._peers.get(key)
            describer = (vendor.steady_describer(peer.info)
                         if peer is not None and backend in peer.compatible else None)
            if describer is None:
                return None
            targets.append((peer, describer))
        return _SteadyLane(dispatch, self._peers.version, backend, tuple(targets))

    def _write(self, encoder: '_Encoder', timestamp: int, dispatch: routes.Dispatch) -> None:
        """Write one message as ``dispatch`` says: on its routes' channels (after the route
        fence where one is given) and, when it says so, on the main topic, whose sample the
        withheld subscriptions (their channels carry this message) do not get."""
        peers = []
        for key, fence in dispatch.channel:
            peer = self._peers[key]
            if fence is not None:
                self._logger.debug(f'route fence to {peer.info.gid_hex} (last main-topic message '
                                   f'{fence.last_main})')
                peer.channel.publish(control.encode(fence), timestamp)
            peers.append(peer)
        main, withheld = dispatch.main, dispatch.withheld
        if main and peers:  # the serving routes not confirmed yet get the main-topic copy too
            self._doubled += sum(1 for key, _ in dispatch.channel if key not in withheld)
        if encoder.cpu_message:
            # CPU payload: one conversion for every target, no Python-level CDR work: its CDR
            # written from the slots where the type has a slot program, else the C struct
            # rmw serializes into each target, as rclpy's publish does
            targets = [peer.channel for peer in peers] + ([self] if main else [])
            if main:
                self._exclude_from_main(withheld)
            if targets:
                write_message(encoder.msg, timestamp, targets, self._program)
            for peer in peers:
                peer.sent_cpu += 1
                peer.backend_in_use = CPU_BACKEND
            return
        cpu_targets = []
        for peer in peers:
            if encoder.buffers and peer.compatible:
                try:
                    described = self._describe(encoder, peer)
                except EndpointGone:
                    # its process is gone (the backend knows before DDS does): nothing more
                    # is written to it, neither this message nor a CPU copy
                    self._logger.debug(f'{peer.info.gid_hex} is gone: its route ends')
                    self._table.gone(peer.info.gid)
                    continue
                if described:
                    encoder.write_described(described, peer.channel, timestamp)
                    peer.sent_descriptor += 1
                    peer.backend_in_use = described[0][1]
                    continue
            if encoder.buffers and peer.compatible:
                self._cpu_to_capable += 1  # it shares a backend, yet gets CPU bytes
            cpu_targets.append(peer.channel)
            peer.sent_cpu += 1
            peer.backend_in_use = CPU_BACKEND
        if main:
            cpu_targets.append(self)
            self._exclude_from_main(withheld)
        if not cpu_targets:
            return
        if encoder.host_buffer:
            # a Buffer in host memory: read through its buffer protocol by the one conversion
            # write_message makes, as rclpy's publish reads an array (no Python-level CDR)
            write_message(encoder.msg, timestamp, cpu_targets, self._program)
            return
        data = encoder.cpu_bytes()
        for target in cpu_targets:
            if target is self:
                publish_serialized(self, data, timestamp)
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
        self._exclusions = exclude_from_next_write(self, withheld)
        self._excluding = bool(withheld) and self._exclusions
        if self._excluding:
            self._withheld += len(withheld)
        elif self._exclusions is False:
            self._logger.warning(
                f'publisher of {self._topic_name}: this Fast DDS DataWriter cannot keep '
                'main-topic samples from subscriptions served on channels; they receive and '
                'drop them (costs CPU, loses nothing)', once=True)

    def _write_probes(self, probes: Tuple[Tuple[bytes, int], ...], timestamp: int) -> None:
        """Write the probes the route table asked for, stamped ``timestamp`` (the last message's
        or older: nothing takes them for a newer message). Under the lock."""
        for key, count in probes:
            peer = self._peers[key]
            self._logger.debug(f'{count} probes to {peer.info.gid_hex}')
            for _ in range(count):
                peer.channel.publish(control.PROBE_BYTES, timestamp)

    def _advance(self) -> None:
        """Bring the routes up to date between messages (the route timer). Under the lock."""
        probes, timer = self._table.advance(time.monotonic(), self._view)
        if probes:
            self._write_probes(probes, self._last_timestamp or time.time_ns())
        self._arm_route_timer(timer)

    def _arm_route_timer(self, needed: bool) -> None:
        """Routes in bring-up (probes, settle time, confirmation) advance on the executor too,
        not only when a message is published: a timer exists while some route needs it."""
        if needed:
            self._route_timer.start()
        else:
            self._route_timer.stop()

    def _on_route_timer(self) -> None:
        with self._lock:
            if not self._peers.closed:
                self._advance()

    # diagnostics ----------------------------------------------------------------------------

    def buffer_peers(self) -> List[SubscriptionPeer]:
        """The buffer-aware subscriptions this publisher serves, and how."""
        return self._core.peer_rows(lambda peer, common: SubscriptionPeer(
            **common, compatible_backends=sorted(peer.compatible),
            channel_matched=bool(peer.channel and peer.channel.matched_count()),
            channel_serving=peer.route.on_channel, route_state=peer.route.state.value,
            sent_as_descriptor=peer.sent_descriptor, sent_as_cpu=peer.sent_cpu))

    def statistics(self) -> PublisherStatistics:
        """Counters: messages written on the main topic, and per-peer counts."""
        with self._lock:
            return PublisherStatistics(
                **self._core.identity(), sent_on_main_topic=self._sent_main,
                main_topic_withheld=self._withheld, main_topic_doubled=self._doubled,
                cpu_copies_to_buffer_capable_peers=self._cpu_to_capable,
                peers_added=self._peers_added, peers_removed=self._peers_removed,
                peers=self.buffer_peers(), published_on_lane=self._on_lane)

    # internals ------------------------------------------------------------------------------

    def _next_timestamp(self) -> int:
        now = time.time_ns()
        self._last_timestamp = now if now > self._last_timestamp else self._last_timestamp + 1
        return self._last_timestamp

    def _buffers_of(self, msg) -> List[codec.BufferAt]:
        """The fields of ``msg`` that hold a Buffer (the one top-level field read directly)."""
        if self._single is not None:
            payload = getattr(msg, self._single)
            return [codec.BufferAt(self._paths[0], payload)] if isinstance(payload, Buffer) \
                else []
        return codec.buffers_of(msg)

    def _describe(self, encoder: _Encoder, peer: _SubscriptionPeer
                  ) -> Tuple[Tuple[codec.FieldPath, str, bytes], ...]:
        """``(path, backend, descriptor)`` of each Buffer of the message that a backend the
        peer accepts describes for it (the others travel as CPU bytes in the same message)."""
        described = []
        for path, buffer in encoder.buffers:
            vendor = buffer.backend_type
            if vendor not in peer.compatible:
                continue
            try:
                descriptor = self._core.backends[vendor].create_descriptor_with_endpoint(
                    buffer, peer.info)
            except EndpointGone:
                raise
            except Exception as exc:  # a failing backend degrades to CPU bytes for this field
                if self._describe_failures_logged.due():
                    seams.log(self._logger, LoggingSeverity.ERROR,
                              f'backend {vendor!r} failed to describe a buffer for '
                              f'{peer.info.gid_hex}: {type(exc).__name__}: {exc}; sending CPU '
                              'bytes', Publisher._describe)
                continue
            if descriptor is not None:
                described.append((path, vendor, descriptor))
        return tuple(described)

    # its PeerHandlers (rosidl_buffer_py.endpoint), under the lock --------------------------

    def _release(self) -> None:
        if self._exclusions:
            try:  # before rclpy destroys the DataWriter the filter sits on
                remove_write_exclusions(self)
            except Exception as exc:  # rclpy already destroyed it (exit): nothing left to do
                self._logger.debug(f'removing the main-topic exclusions: {exc}')
        self._route_timer.stop()

    def _add_peer(self, info: EndpointInfo, backends: Dict[str, str]) -> _SubscriptionPeer:
        # backends account per channel: which local publisher serves this peer, and what its
        # reader's history holds (it advertises it with its cpu entry)
        depth = parse_history_metadata(backends.get(CPU_BACKEND))
        topic = channel_topic(self._topic_name, self._core.gid, info.gid)
        channel = _dds.create_channel_publisher(self._node, self.msg_type, topic,
                                                self.qos_profile)
        info = dataclasses.replace(info, local_gid=self._core.gid, history_depth=depth,
                                   delivered=self._delivery_check(channel, depth))
        # the route last: the route table never has a route without its channel
        route = self._table.add(info.gid, handshake=self._handshake and reliable_subscription(
            self._node, self._topic_name, info.gid), depth=self.qos_profile.depth)
        self._peers_added += 1
        return _SubscriptionPeer(info=info, backends=backends, route=route, channel=channel,
                                 channel_topic=topic)

    def _delivery_check(self, channel, reader_depth: Optional[int]):
        """``EndpointInfo.delivered`` of a peer: did everything sent on its channel reach its
        reader? The channel's acknowledgments tell when the channel holds at least the
        reader's KEEP_LAST depth (a stopped reader that resumes then receives at least that
        many newer messages, which push out what it held); a shallower channel cannot."""
        qos = self.qos_profile
        if qos.history == HistoryPolicy.KEEP_LAST and reader_depth and qos.depth < reader_depth:
            return _never
        return functools.partial(_all_acknowledged, channel)

    def _peer_seen(self) -> None:
        # any subscription of our topic coming or changing, legacy ones too, may change routes
        self._table.invalidate()

    def _channels_checked(self) -> None:
        # a channel that matched since the last plan moves its route on (probes, settling):
        # a publisher that is not publishing (waiting for its subscribers) plans on the timer
        self._arm_route_timer(True)

    def _peer_gone(self, gid: bytes) -> None:
        # any subscription of our topic going, legacy ones too, may change routes (the table
        # also remembers legacy subscriptions' last main-topic message)
        self._table.remove(gid)
        self._peers.drop(gid)

    def _update_peer(self, record: _SubscriptionPeer, compatible: Set[str]) -> None:
        record.compatible = compatible
        self._table.invalidate()
        self._arm_route_timer(True)  # its route advances on the executor, publishing or not

    def _forget_peer(self, record: _SubscriptionPeer) -> None:
        self._peers_removed += 1
        self._table.remove(record.info.gid)


def _all_acknowledged(channel) -> bool:
    try:
        return channel.wait_for_all_acked(0.0)
    except _dds.DdsError:  # destroyed: its peer left, and receives nothing more
        return True


def _never() -> bool:
    return False


def create_publisher(node, msg_type, topic: str, qos_profile: Union[QoSProfile, int], *,
                     callback_group=None, event_callbacks=None,
                     qos_overriding_options=None) -> Union[Publisher, PlainPublisher]:
    """Create a buffer-aware publisher on ``node`` (arguments as ``Node.create_publisher``).

    The node owns it like any publisher: ``node.destroy_publisher(pub)`` and
    ``node.destroy_node()`` destroy it, and its ``event_callbacks`` fire as rclpy's do. A type
    that cannot be buffer-aware (:func:`rosidl_buffer_py.endpoint.buffer_aware`) gets a
    :class:`~rosidl_buffer_py.plain.PlainPublisher`.
    """
    aware = buffer_aware(msg_type)
    create = functools.partial(
        node.create_publisher, msg_type, topic, qos_profile, callback_group=callback_group,
        event_callbacks=event_callbacks, qos_overriding_options=qos_overriding_options,
        publisher_class=functools.partial(Publisher if aware else PlainPublisher, node=node))
    if not aware:
        return create()
    discovery.for_node(node)  # the tap goes first: peers re-announce when they see us
    # created disabled: Publisher.__init__ sets the advertisement first, then enables the
    # DataWriter (the block's end only makes sure, should rclpy fail before that)
    with _dds.created_disabled(node, 'publisher'):
        return create()
