"""The buffer-aware subscription.

It is an rclpy subscription: the node owns it (``node.subscriptions`` lists it,
``destroy_subscription`` and ``destroy_node`` destroy it), executors wait on its main-topic
reader as on any subscription's, and its ``event_callbacks`` are rclpy's own event handlers. Its
main-topic DataReader is an ordinary rcl subscription (so plain rclpy and C++ publishers reach it)
that advertises ``BUFBE:`` with the backends it accepts; for every buffer-aware publisher it
discovers it opens the channel ``rt/<topic>/_buf/<pub gid>_<sub gid>`` below rcl, whose new data
triggers a guard condition in the same callback group.

One delivery path, :meth:`Subscription._next`, whichever of the two woke the executor. Per
publisher, messages are delivered once and in publish order by that publisher's
:class:`~rosidl_buffer_py.routes.Stream` (the route protocol's subscription side, in
:mod:`rosidl_buffer_py.routes`): this class takes samples, feeds them to the stream, and
delivers, queues or drops them as it decides.

- channels are taken first: a publisher writes a message's channel copy before its main-topic
  copy (kept for legacy subscribers), so the channel's route fence and copy are normally seen
  first, and the main-topic copy is dropped as their duplicate (uncopied: its key is read from
  the DDS sample info);
- control messages on a channel (:mod:`rosidl_buffer_py.control`: probes, route fences) are
  told apart from messages by two header bytes;
- a publisher that goes away leaves what its channel had delivered to our reader: it is taken
  before the channel is destroyed and delivered in order, as a stock reader keeps the samples
  of a writer that left.

Messages of legacy publishers arrive on the main topic only, as with stock.
"""
import collections
import time
from dataclasses import dataclass, field
from typing import Callable, Deque, Dict, List, NamedTuple, Optional, Set, Tuple, Union

import rclpy.subscription
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import InvalidTopicNameException
from rclpy.logging import LoggingSeverity
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.type_support import check_is_valid_msg_type

from rosidl_buffer_py import _dds, codec, control, discovery, routes
from rosidl_buffer_py import rclpy_seams_7_1 as seams
from rosidl_buffer_py._native import (
    discard_untaken, endpoint_gid, peek_untaken, take_message_with_gid, take_serialized_with_gid)
from rosidl_buffer_py.backend import EndpointInfo, EndpointKind
from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.channel import channel_topic
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.diagnostics import PublisherPeer, SubscriptionStatistics
from rosidl_buffer_py.endpoint import (
    ChannelPeer, EndpointCore, advertise, advertised_backends, buffer_aware, split_deadline)
from rosidl_buffer_py.message_support import enable_buffer_fields
from rosidl_buffer_py.on_demand import OnDemandTimer, destroy_node_entities
from rosidl_buffer_py.peers import PeerHandlers, PeerTable
from rosidl_buffer_py.plain import PlainSubscription
from rosidl_buffer_py.qos import history_metadata, incompatible_qos_once_per_peer
from rosidl_buffer_py.registry import get_installed_backends, parse_acceptable_buffer_backends
from rosidl_buffer_py.routes import Outcome
from rosidl_buffer_py.throttle import Throttle


#: Messages delivered per channel wake-up before yielding to the executor's other callbacks.
MAX_BATCH = 64
#: CPU messages up to this many CDR bytes are deserialized in C (rclpy's own conversion: no
#: Python-level work); longer ones are decoded by the codec, which splices the payload with one
#: copy where rosidl's generated conversion makes two (through an intermediate bytes object).
#: Types with a slot program (codec.program_of) are built in C at any length, their
#: payload copied once.
C_DESERIALIZE_MAX_BYTES = 64 * 1024
#: At most one "rejected a message" line per this many seconds (all are counted).
REJECTION_LOG_SECONDS = 5.0
#: A GID is the DDS GUID: a 12-byte participant prefix, then the 4-byte entity id.
_GUID_PREFIX = 12


class _Ready(NamedTuple):
    """A message to deliver, with its message info (what :meth:`Subscription._next` gives)."""

    msg: object
    info: dict


class _Taken(NamedTuple):
    """One sample taken from the main topic or a channel."""

    raw: object        #: a deserialized message, or CDR bytes for the codec
    publisher_gid: bytes
    info: dict         #: rclpy's message info (source_timestamp, ...)
    #: a channel's descriptor message as the take decoded it in C: (the message without its
    #: payload, backend type, descriptor), or None (``raw`` says what it is)
    described: Optional[Tuple[object, str, bytes]] = None

    @property
    def timestamp(self) -> int:
        return self.info['source_timestamp']


@dataclass
class _PublisherPeer(ChannelPeer):
    """A buffer-aware publisher of our topic and the channel (a ChannelSubscription) it serves
    us on."""

    received_descriptor: int = 0
    received_cpu: int = 0
    #: The publisher advertises a backend we accept besides CPU: descriptors may come.
    descriptors_possible: bool = False
    #: The backends besides CPU it advertises, sorted (what a copy of its was offered as).
    offered: Tuple[str, ...] = ()
    #: Its messages were said (once) to arrive as CPU copies where zero-copy was on offer.
    copies_said: bool = False
    #: What its channel had delivered to our reader when the publisher went away.
    departed: Optional[Deque[_Taken]] = None
    #: Per backend of its descriptors: that backend's steady opener for it, or None
    #: (``BufferBackend.steady_opener``), asked at its first descriptor.
    openers: Dict[str, Optional[Callable[[bytes], Optional[Buffer]]]] = field(
        default_factory=dict)

    def take(self, reading: Optional[codec.DescriptorReading]) -> Optional[_Taken]:
        """The next sample of its channel (raw CDR bytes), or None. With ``reading``, for a
        publisher that may send descriptors, a descriptor message comes decoded too."""
        if self.departed is not None:
            return self.departed.popleft() if self.departed else None
        taken = (self.channel.take_described(*reading.args)
                 if reading is not None and self.descriptors_possible else self.channel.take())
        return None if taken is None else _Taken(*taken)

    @property
    def pending(self) -> bool:
        return bool(self.departed) if self.departed is not None else self.channel.pending


def _of_its_participant(peer: _PublisherPeer, writer_gid: bytes) -> bool:
    """A sample of the writer ``writer_gid`` was written by the publisher's participant, which
    creates its channel's writer (any process can create a writer on any topic)."""
    return writer_gid[:_GUID_PREFIX] == peer.info.gid[:_GUID_PREFIX]


class _ReceiveView:
    """A subscription's DDS readers as :class:`routes.Receiver` asks about them
    (:class:`routes.ReceiveView`): its channels (:class:`_PublisherPeer`) and its main-topic
    reader. What it rejects on a channel it counts and logs through the subscription."""

    def __init__(self, sub: 'Subscription') -> None:
        self._sub = sub

    def channels(self) -> List[_PublisherPeer]:
        return self._sub._channels

    def channel_key(self, peer: _PublisherPeer) -> bytes:
        return peer.info.gid

    def take_channel(self, peer: _PublisherPeer) -> Optional[_Taken]:
        # Nothing announced since its last take: whatever lands there triggers the guard
        # condition, so it is taken on that wake-up, as if it had landed a moment later. A
        # quiet publisher's channel then costs no take per message of the others.
        return peer.take(self._sub._reading) if peer.pending else None

    def classify(self, peer: _PublisherPeer, taken: _Taken):
        if not _of_its_participant(peer, taken.publisher_gid):  # an impostor on its topic
            self._sub._reject(taken, f'the channel {peer.channel_topic} is not of publisher '
                                     f'{peer.info.gid_hex}\'s participant')
            return routes.Incoming.CONTROL, None
        if taken.described is not None or type(taken.raw) is self._sub.msg_type:
            return routes.Incoming.DATA, None
        try:
            message = control.parse(taken.raw)
        except control.ControlError as exc:
            self._sub._reject(taken, f'{exc} (on the channel {peer.channel_topic})')
            return routes.Incoming.CONTROL, None
        if message is None:
            return routes.Incoming.DATA, None
        if isinstance(message, routes.Fence):
            return routes.Incoming.FENCE, message
        return routes.Incoming.CONTROL, None  # a probe: the publisher learning we matched

    def timestamp(self, taken: _Taken) -> int:
        return taken.timestamp

    def channels_drained(self) -> None:
        self._sub._retire_departed()

    def peek_main(self) -> Optional[Tuple[bytes, int]]:
        return peek_untaken(self._sub.handle)

    def discard_main(self) -> None:
        discard_untaken(self._sub.handle)

    def take_main(self, publisher: Optional[bytes]) -> Optional[_Taken]:
        """Publishers write only CPU data on the main topic: it is deserialized in C, as rclpy
        does. A sample that does not deserialize makes Jazzy's C type support print a line to
        stderr; its publisher is then a *suspect*, whose later samples are taken as bytes for
        the codec (which rejects malformed data silently, counted and logged throttled), so a
        hostile writer gets one such line, not one per message."""
        sub = self._sub
        if publisher is None and sub._suspects:
            peeked = peek_untaken(sub.handle)
            if peeked is None:
                return None
            publisher = peeked[0]
        if publisher is not None and publisher in sub._suspects:
            taken = take_serialized_with_gid(sub.handle)
        else:
            taken = take_message_with_gid(sub.handle, sub.msg_type, C_DESERIALIZE_MAX_BYTES,
                                          sub._program)
            if taken is not None and type(taken[0]) is not sub.msg_type and \
                    len(taken[0]) <= C_DESERIALIZE_MAX_BYTES:
                sub._suspects.add(taken[1])  # C deserialization failed (and said so)
        return None if taken is None else _Taken(*taken)

    def main_key(self, taken: _Taken) -> bytes:
        return taken.publisher_gid


class Subscription(rclpy.subscription.Subscription):
    """Receive messages whose ``uint8[]`` payload may arrive as a backend Buffer.

    Create it with :func:`rosidl_buffer_py.create_subscription`. The callback gets ``(msg)`` or
    ``(msg, message_info)`` like rclpy's; ``msg.<payload>`` is ``array.array('B')`` for CPU data and
    a Buffer of an accepted backend for descriptor data.

    What it shares with the publisher (identity, advertisement, its buffer-aware publishers
    as a :class:`~rosidl_buffer_py.peers.PeerTable`, deadline, teardown) is its
    :class:`~rosidl_buffer_py.endpoint.EndpointCore`; per publisher, a
    :class:`~rosidl_buffer_py.routes.Stream` decides what is delivered.
    """

    def __init__(self, node, msg_type, topic: str, callback: Callable, qos_profile: QoSProfile,
                 callback_group, event_callbacks: SubscriptionEventCallbacks,
                 acceptable_buffer_backends: Optional[str]) -> None:
        enable_buffer_fields(msg_type)
        self._accepted = parse_acceptable_buffer_backends(acceptable_buffer_backends)
        #: builds the CPU messages taken in C from their slots (codec.program_of)
        self._program = codec.program_of(msg_type)
        #: how a channel's take decodes a descriptor message in C (codec.descriptor_reading)
        self._reading = codec.descriptor_reading(msg_type)
        self._node = node
        #: one stream per publisher: the route protocol's subscription side
        self._streams: routes.StreamTable[_Taken] = routes.StreamTable(
            reliable=qos_profile.reliability != ReliabilityPolicy.BEST_EFFORT)
        self._counts = collections.Counter()
        self._rejections_logged = Throttle(REJECTION_LOG_SECONDS)
        self._receiver: routes.Receiver[_PublisherPeer, _Taken] = routes.Receiver(self._streams)
        self._view = _ReceiveView(self)
        #: the peers with a channel (and departed ones with samples left), polled in turn
        self._channels: List[_PublisherPeer] = []
        self._suspects: Set[bytes] = set()  # publishers whose data C could not deserialize
        # the discovery tap goes first: peers re-announce as soon as they see our endpoint
        discovery.for_node(node)
        event_callbacks, deadline = split_deadline(event_callbacks, qos_profile)
        _dds.type_support(msg_type)  # imports the type support, as rclpy's create_* do
        installed = get_installed_backends()
        backends = {name: installed[name] for name in self._accepted}
        # our history, which DDS discovery does not carry: publishers keep a descriptor's
        # memory while it can still be taken from it (see EndpointInfo.history_depth)
        advertised = advertised_backends(backends, history_metadata(qos_profile))
        # the main topic's reader: the executor takes through it as through any subscription's
        # handle, and its takes are this subscription's delivery path (set once it is ready);
        # created disabled, its advertisement set, then enabled: its first announcement
        # carries the advertisement (see _dds.created_disabled)
        with _dds.created_disabled(node, 'subscription'):
            reader = seams.delegating_reader(node, msg_type, topic, qos_profile)
            user_data = advertise(reader, EndpointKind.SUBSCRIPTION, advertised)
        event_callbacks = incompatible_qos_once_per_peer(
            event_callbacks, node, reader, EndpointKind.SUBSCRIPTION,
            endpoint_gid(reader, 'subscription'), topic)
        try:
            super().__init__(reader, msg_type, topic, callback, callback_group, qos_profile,
                             False, event_callbacks=event_callbacks)
        except Exception:
            reader.destroy_when_not_in_use()
            raise
        self._topic_name = reader.get_topic_name()
        core = self._core = EndpointCore(
            node, reader, EndpointKind.SUBSCRIPTION, topic_name=self._topic_name,
            backends=backends, advertised=advertised, user_data=user_data,
            qos_profile=qos_profile, callback_group=callback_group, deadline=deadline,
            handlers=PeerHandlers(self._peer_seen, self._channels_checked, self._add_peer,
                                  self._update_peer, self._forget_peer, self._peer_gone,
                                  self._release))
        self._lock = core.lock
        self._logger = core.logger
        self._peers: PeerTable[_PublisherPeer] = core.peers
        self._fence_timer = OnDemandTimer(node, routes.FENCE_TIMEOUT_SECONDS / 4,
                                          self._on_fence_timer, callback_group, core.logger)
        self._channel_guard = node.create_guard_condition(self._deliver_available,
                                                          callback_group)
        # discovery wakes the node's own guard: data wake-ups do not poll discovery
        core.open()
        reader.take = self._next  # None once closed: _next checks

    # rclpy.subscription.Subscription surface ------------------------------------------------

    @property
    def topic_name(self) -> str:
        """Fully qualified topic name."""
        return self._topic_name

    @property
    def acceptable_buffer_backends(self) -> frozenset:
        """The backends whose descriptors this subscription accepts (always with ``cpu``)."""
        return self._accepted

    def destroy(self) -> None:
        """Destroy the channels, then the subscription (``Node.destroy_subscription`` calls
        this)."""
        self._core.close()
        super().destroy()

    # diagnostics ----------------------------------------------------------------------------

    def buffer_peers(self) -> List[PublisherPeer]:
        """The buffer-aware publishers serving this subscription, and how."""
        return self._core.peer_rows(lambda peer, common: PublisherPeer(
            **common, received_as_descriptor=peer.received_descriptor,
            received_as_cpu=peer.received_cpu))

    def statistics(self) -> SubscriptionStatistics:
        """Counters: delivered, duplicates dropped, rejected descriptors, by route."""
        with self._lock:
            fence_timeouts, fenced_lost = self._streams.fence_counts()
            return SubscriptionStatistics(
                **self._core.identity(),
                **{key: self._counts[key] for key in (
                    'delivered', 'from_channels', 'from_main_topic', 'duplicates_dropped',
                    'rejected', 'fences')},
                fence_timeouts=fence_timeouts, fenced_lost=fenced_lost,
                waiting_for_fence=self._streams.waiting(), peers=self.buffer_peers(),
                delivered_steady=self._counts['delivered_steady'])

    # the delivery path ----------------------------------------------------------------------

    def _next(self) -> Optional[_Ready]:
        """The next message to deliver, with its message info, or None when none is left.

        The take order is the route protocol's (:class:`routes.Receiver`); this counts what
        each step did and decodes what it delivers."""
        with self._lock:
            while not self._peers.closed:
                now = time.monotonic()
                step = self._steady_step(now) or self._receiver.step(self._view, now)
                if step is None:
                    return None
                if step.__class__ is _Ready:
                    return step
                outcome, taken = step.outcome, step.sample
                if step.channel is None:  # the main topic: delivered, or a duplicate dropped
                    self._counts['from_main_topic'] += 1
                    if outcome is not Outcome.DELIVER:
                        self._counts['duplicates_dropped'] += 1
                        continue
                    peer = self._peers.get(taken.publisher_gid)
                    msg = self._decode(taken, peer)
                    if msg is None:
                        continue
                    self._say_copies(peer, on_channel=False)
                    if self._streams.any_holding:
                        self._wake()  # it may open a fence: the channel guard delivers the rest
                    return self._delivered(msg, taken.info)
                if outcome is Outcome.FENCE:
                    self._counts['fences'] += 1
                    self._logger.debug(
                        f'route fence from {step.channel.info.gid_hex}: main-topic messages up '
                        f'to {self._streams[step.channel.info.gid].fence} first')
                    self._arm_fence_timer()
                    continue
                if outcome is Outcome.CONTROL:
                    continue
                if not step.released:
                    self._counts['from_channels'] += 1
                if outcome is Outcome.DUPLICATE:
                    self._counts['duplicates_dropped'] += 1
                    continue
                if outcome is Outcome.QUEUED:
                    self._arm_fence_timer()
                    continue
                msg = self._decode(taken, step.channel)
                if msg is not None:
                    self._say_copies(step.channel, on_channel=True)
                    return self._delivered(msg, taken.info)
            return None

    def _steady_step(self, now: float) -> Union[None, _Ready, routes.Step]:
        """The next step when the take order is simply the one channel's next sample
        (:meth:`routes.Receiver.only_channel_next`) and a descriptor message is there: taken
        and decoded in C, known as data without the view's classification (what
        ``_ReceiveView.classify`` says of a descriptor message from its publisher's
        participant). Anything else taken goes to the classification; None, having taken
        nothing, where :meth:`routes.Receiver.step` is to run. Under the lock.

        The common case is delivered here, ready (:class:`_Ready`): a descriptor message that
        the stream delivers as it is (:meth:`routes.Stream.channel_steady`) and that its
        backend's steady opener opens. That is what the step and :meth:`_decode` would make of
        it, without their Python frames and the objects between them."""
        channels = self._channels
        if len(channels) != 1:
            return None
        peer = channels[0]
        if peer.departed is not None or not peer.descriptors_possible or \
                self._reading is None or not peer.channel.pending:
            return None
        stream = self._receiver.only_channel_next(peer.info.gid)
        if stream is None:
            return None
        taken = peer.channel.take_described(*self._reading.args)
        if taken is None:
            return None
        _, writer, info, described = taken  # (what _Taken names)
        if described is None or not _of_its_participant(peer, writer):
            return self._receiver.channel_step(self._view, peer, stream, _Taken(*taken), now)
        if not stream.channel_steady(info['source_timestamp']):
            return self._receiver.channel_step(self._view, peer, stream, _Taken(*taken), now,
                                               data=True)
        msg, backend, descriptor = described
        openers = peer.openers
        opener = openers[backend] if backend in openers else self._opener(peer, backend)
        try:
            buffer = None if opener is None else opener(descriptor)
        except Exception:  # noqa: BLE001 (bytes from the network: the general path says why)
            buffer = None
        if buffer is None:  # delivered by the general path, which opens it or says why not
            return routes.Step(Outcome.DELIVER, _Taken(*taken), peer)
        setattr(msg, self._reading.field, buffer)
        peer.received_descriptor += 1
        peer.backend_in_use = backend
        self._counts['from_channels'] += 1
        self._counts['delivered_steady'] += 1
        return self._delivered(msg, info)

    def _opener(self, peer: _PublisherPeer, backend: str
                ) -> Optional[Callable[[bytes], Optional[Buffer]]]:
        """The steady opener of ``backend`` (one we accept) for ``peer``, asked once."""
        known = self._core.backends.get(backend)
        opener = peer.openers[backend] = None if known is None else known.steady_opener(
            peer.info)
        return opener

    def _say_copies(self, peer: Optional[_PublisherPeer], on_channel: bool) -> None:
        """Say once per publisher, in the node's log, that its messages arrive as CPU copies
        although it offers a backend: because this subscription does not accept it, or because
        the publisher sent CPU data on a channel that could carry descriptors. Copies before a
        channel serves us are the documented start-up, not said."""
        if (peer is None or peer.copies_said or not peer.offered or
                peer.backend_in_use != CPU_BACKEND or
                (peer.descriptors_possible and not on_channel)):
            return  # said, a CPU-only publisher, zero-copy, or its channel not up yet
        offered = peer.offered
        if not peer.descriptors_possible:
            why = (f'it offers {", ".join(offered)} and this subscription accepts '
                   f'{", ".join(sorted(self._accepted))} (acceptable_buffer_backends='
                   f'{offered[0]!r} or \'any\' takes them zero-copy)')
        else:
            common = ", ".join(n for n in offered if n in self._core.backends)
            why = (f'its channel could carry {common} descriptors, but the publisher sent CPU '
                   f'data (a payload not in {common} memory, or one its backend could not '
                   "describe: see the publisher's log)")
        peer.copies_said = True
        # on the delivery path: rclpy's own logger call would hold the executor (see seams.log)
        seams.log(self._logger, LoggingSeverity.INFO,
                  f'messages on {self._topic_name} from publisher {peer.info.gid_hex} arrive as '
                  f'CPU copies, not zero-copy: {why}', Subscription._say_copies)

    def _delivered(self, msg, info: dict) -> _Ready:
        self._counts['delivered'] += 1
        self._core.activity()
        return _Ready(msg, info)

    def _deliver_available(self) -> None:
        """Channel data woke us: deliver what is deliverable (at most ``MAX_BATCH``).

        A callback that raises leaves through the executor's spin, as with rclpy; the guard is
        triggered first, so the next spin delivers the next message."""
        for _ in range(MAX_BATCH):
            item = self._next()
            if item is None:
                return
            try:
                self._call(*item)
            except BaseException:
                self._wake()
                raise
            if not self._streams.any_holding and not any(p.pending for p in self._channels):
                # drained (each take counts what its reader holds): no empty take to prove it.
                # A sample arriving from now on triggers the guard again; main-topic samples
                # wake the executor through the main reader itself.
                return
        self._wake()  # more may be waiting: let other callbacks run first

    def _on_fence_timer(self) -> None:
        with self._lock:
            if self._streams.next_deadline() is None:
                self._fence_timer.stop()
        self._deliver_available()

    def _arm_fence_timer(self) -> None:
        """Waiting streams give up on a lost fenced message after FENCE_TIMEOUT_SECONDS: a
        timer exists while some stream waits."""
        if self._streams.next_deadline() is not None:
            self._fence_timer.start()

    def _call(self, msg, info) -> None:
        if self._callback_type is rclpy.subscription.Subscription.CallbackType.MessageOnly:
            self.callback(msg)
        else:
            self.callback(msg, info)

    def _wake(self) -> None:
        with self._lock:
            if not self._peers.closed:
                self._channel_guard.trigger()

    def _reject(self, taken: _Taken, why: str) -> None:
        """Data from the network that is not to be delivered: counted and logged (throttled)."""
        self._counts['rejected'] += 1
        if not self._rejections_logged.due():
            return
        seams.log(self._logger, LoggingSeverity.WARN,
                  f'rejected a message on {self._topic_name} from '
                  f'{taken.publisher_gid.hex()}: {why} ({self._counts["rejected"]} '
                  'rejected so far)', Subscription._reject)

    def _decode(self, taken: _Taken, peer: Optional[_PublisherPeer]):
        """The message of a take: ``raw`` is already one (deserialized in C) or CDR bytes, and
        ``described`` a descriptor message the take decoded in C."""
        raw = taken.raw
        if type(raw) is self.msg_type:
            if peer is not None:
                peer.received_cpu += 1
                peer.backend_in_use = CPU_BACKEND
            return raw
        try:
            if (peer is not None and not peer.descriptors_possible and
                    len(raw) <= C_DESERIALIZE_MAX_BYTES):
                # a peer that cannot send us descriptors: deserialized in C, as rclpy's take
                msg = codec.deserialize(raw, self.msg_type)
                peer.received_cpu += 1
                peer.backend_in_use = CPU_BACKEND
                return msg
            described = taken.described
            if described is not None and peer is not None and \
                    described[1] in self._core.backends:
                # decoded by the take: what codec.decode gives, without its Python frames
                msg, backend, descriptor = described
                setattr(msg, self._reading.field, self._core.backends[backend]
                        .from_descriptor_with_endpoint(descriptor, peer.info))
            else:
                decoded = codec.decode(raw, self.msg_type, known_backends=self._core.backends)
                msg = decoded.msg
                if not decoded.descriptors:
                    if peer is not None:
                        peer.received_cpu += 1
                        peer.backend_in_use = CPU_BACKEND
                    return msg
                if peer is None:
                    raise codec.CodecError(
                        f'descriptors from publisher {taken.publisher_gid.hex()}, which is not '
                        'a discovered buffer-aware publisher')
                for path, (backend, descriptor) in decoded.descriptors.items():
                    codec.set_at(msg, path, self._core.backends[backend]
                                 .from_descriptor_with_endpoint(descriptor, peer.info))
            peer.received_descriptor += 1
            peer.backend_in_use = backend
            return msg
        except Exception as exc:  # bytes from the network: reject, count, log, go on
            self._reject(taken, f'{type(exc).__name__}: {exc}')
            return None

    # its PeerHandlers (rosidl_buffer_py.endpoint), under the lock --------------------------

    def _add_peer(self, info: EndpointInfo, backends: Dict[str, str]) -> _PublisherPeer:
        record = _PublisherPeer(info=info, backends=backends)
        record.channel_topic = channel_topic(self._topic_name, info.gid, self._core.gid)
        record.channel = _dds.create_channel_subscription(
            self._node, self.msg_type, record.channel_topic, self.qos_profile,
            self._channel_guard)
        return record

    def _update_peer(self, record: _PublisherPeer, compatible) -> None:
        # Small CPU messages of a peer that cannot send us descriptors are deserialized in C;
        # the others go to the codec. Either way a message of the other kind is still decoded
        # correctly: this only picks the cheaper conversion.
        record.offered = tuple(sorted(name for name in record.backends if name != CPU_BACKEND))
        record.descriptors_possible = any(name in self._core.backends for name in record.offered)
        self._poll_channels()

    def _poll_channels(self) -> None:
        """The channels ``_next`` takes from, in turn: the peers' and the departed peers' with
        samples left."""
        self._channels = [p for p in self._peers if p.channel is not None] + [
            p for p in self._channels if p.departed is not None]

    def _retire_departed(self) -> None:
        """Departed peers whose samples were all delivered are forgotten, with their stream."""
        done = [p for p in self._channels if p.departed is not None and not p.departed and
                not self._streams[p.info.gid].holding]
        if done:
            for peer in done:
                self._streams.pop(peer.info.gid)
            self._channels = [p for p in self._channels if all(p is not d for d in done)]

    def _peer_seen(self) -> None:
        """Nothing to do: a subscription's streams change with its peers' channels only."""

    def _channels_checked(self) -> None:
        """Nothing to do: a subscription's streams follow what its channels deliver."""

    def _peer_gone(self, gid: bytes) -> None:
        """A publisher went away: what its channel had delivered to our reader stays
        deliverable, in order (as a stock reader keeps the samples of a writer that left).
        Descriptors are resolved now, before the backend forgets the publisher."""
        self._suspects.discard(gid)
        peer = self._peers.get(gid)
        left = collections.deque()
        while peer is not None and peer.channel is not None:
            taken = peer.take(self._reading)
            if taken is None:
                break
            if type(taken.raw) is not self.msg_type and not control.is_control(taken.raw):
                msg = self._decode(taken, peer)
                if msg is None:
                    continue
                taken = taken._replace(raw=msg, described=None)
            left.append(taken)
        self._peers.drop(gid)
        if peer is not None and (left or self._streams[gid].holding):
            peer.departed = left
            self._channels.append(peer)
            self._wake()
        elif not self._streams[gid].holding:
            self._streams.pop(gid)

    def _forget_peer(self, record: _PublisherPeer) -> None:
        # its channel goes: its next messages (if any) come on the main topic again
        stream = self._streams.streams.get(record.info.gid)
        if stream is not None:
            stream.channel_lost()
        self._channels = [p for p in self._channels if p.info.gid != record.info.gid]

    def _release(self) -> None:
        self._fence_timer.stop()
        destroy_node_entities(self._node, [self._channel_guard], self._logger)


def create_subscription(node, msg_type, topic: str, callback: Callable,
                        qos_profile: Union[QoSProfile, int], *, callback_group=None,
                        event_callbacks=None, qos_overriding_options=None, raw: bool = False,
                        acceptable_buffer_backends: Optional[str] = 'cpu'):
    """Create a buffer-aware subscription on ``node`` (arguments as ``Node.create_subscription``).

    The node owns it like any subscription: ``node.destroy_subscription(sub)`` and
    ``node.destroy_node()`` destroy it, and its ``event_callbacks`` fire as rclpy's do.

    :param acceptable_buffer_backends: Backends whose descriptors this subscription accepts:
        ``"cpu"`` (the default), ``""`` or ``None`` for CPU only, ``"any"`` for every installed
        backend, or a comma-separated list such as ``"demo"``. CPU data is always accepted.
    :param raw: Not supported: raw (serialized) messages are CPU bytes anyway, so use
        ``node.create_subscription(..., raw=True)``, which receives them from every publisher.
    """
    if raw:
        raise ValueError('raw=True is not supported by buffer-aware subscriptions: serialized '
                         'messages are always CPU bytes, which a plain '
                         'node.create_subscription(..., raw=True) receives from every publisher, '
                         'buffer-aware ones included')
    # what Node.create_subscription does, with rclpy's own checks (its errors, its exception
    # types: rclpy has no hook for a subscription class)
    seams.warn_if_other_version()
    qos = seams.validate_qos(node, qos_profile)
    callback_group = callback_group or node.default_callback_group
    try:
        final_topic = node.resolve_topic_name(topic)
    except RuntimeError:
        try:
            seams.validate_topic_name(node, topic)
        except InvalidTopicNameException as ex:
            raise ex from None
        raise
    seams.declare_qos_parameters(node, final_topic, qos, qos_overriding_options)
    check_is_valid_msg_type(msg_type)
    event_callbacks = event_callbacks or SubscriptionEventCallbacks()
    cls = Subscription if buffer_aware(msg_type) else PlainSubscription
    try:
        sub = cls(node, msg_type, topic, callback, qos, callback_group, event_callbacks,
                  acceptable_buffer_backends)
    except ValueError:
        seams.validate_topic_name(node, topic)  # rclpy's error for a bad name
        raise
    seams.register_subscription(node, sub, callback_group, sub.event_handlers)
    return sub

