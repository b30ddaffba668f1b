"""The buffer-aware subscription.

Its main-topic DataReader is an ordinary rcl subscription (so plain rclpy and C++ publishers reach
it) that advertises ``BUFBE:`` with the backends it accepts; for every buffer-aware publisher it
discovers it opens the channel ``rt/<topic>/_buf/<pub gid>_<sub gid>`` below rcl. One guard
condition in the user's callback group is triggered by new data on any of them and by discovery;
its callback takes everything available and calls the user callback once per message.

Exactly-once: a buffer-aware publisher writes the channel copy and any main-topic copy of one
message with the same source timestamp; the subscription delivers each (publisher GID, source
timestamp) of a buffer-aware publisher once. Messages of legacy publishers are never filtered.
"""
import collections
import inspect
import threading
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Union

from rclpy.exceptions import InvalidHandle
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import get_logger
from rclpy.qos import QoSProfile

from rosidl_buffer_py import _dds, advertisement, codec, discovery
from rosidl_buffer_py.backend import EndpointInfo, EndpointKind
from rosidl_buffer_py.channel import channel_topic, dds_topic
from rosidl_buffer_py.cpu_backend import CPU_BACKEND
from rosidl_buffer_py.message_support import enable_buffer_fields
from rosidl_buffer_py.registry import get_installed_backends, parse_acceptable_buffer_backends
from rosidl_buffer_py.transport import (
    BufferEndpoint, hook_destruction, qos_of, warn_unsupported_rmw)

_logger = get_logger('rosidl_buffer_py.subscription')

#: Source timestamps remembered per buffer-aware publisher to drop a message's second copy.
DEDUP_WINDOW = 4096
#: The main topic is polled first at least once every this many takes (fairness).
MAIN_TOPIC_TURN = 16
#: How long a main-topic copy waits for its channel twin (see Subscription._should_hold).
HOLD_SECONDS = 0.05
#: Messages delivered per wake-up before yielding to the executor's other callbacks.
MAX_BATCH = 64
#: CPU messages up to this many CDR bytes are deserialized in C (rclpy's own conversion: no
#: Python-level work); longer ones are decoded by the codec, which splices the payload with one
#: copy where rosidl's generated conversion makes two (through an intermediate bytes object).
C_DESERIALIZE_MAX_BYTES = 64 * 1024


@dataclass
class _PublisherPeer:
    """A buffer-aware publisher of our topic and the channel it serves us on."""

    info: EndpointInfo
    backends: Dict[str, str]
    channel: Optional['_dds.ChannelSubscription'] = None
    channel_topic: str = ''
    created_at: float = 0.0
    received_descriptor: int = 0
    received_cpu: int = 0
    backend_in_use: Optional[str] = None
    #: The publisher advertises a backend we accept besides CPU: descriptors may come.
    descriptors_possible: bool = False


class Subscription(BufferEndpoint):
    """Receive messages whose ``uint8[]`` payload may arrive as a backend Buffer.

    Create it with :func:`rosidl_buffer_py.create_subscription`. The callback gets ``(msg)`` or
    ``(msg, message_info)`` like rclpy's; ``msg.<payload>`` is ``array.array('B')`` for CPU data and
    a Buffer of an accepted backend for descriptor data.
    """

    def __init__(self, node, msg_type, topic: str, callback: Callable,
                 qos_profile: Union[QoSProfile, int], *, callback_group=None,
                 event_callbacks=None,
                 acceptable_buffer_backends: Optional[str] = 'cpu') -> None:
        self._field = codec.payload_field(msg_type)
        enable_buffer_fields(msg_type)
        self._peer_kind = EndpointKind.PUBLISHER
        self._accepted = parse_acceptable_buffer_backends(acceptable_buffer_backends)
        self._node = node
        self.msg_type = msg_type
        self.callback = callback
        self.qos_profile = qos_of(qos_profile)
        self._lock = threading.RLock()
        self._peers: Dict[bytes, _PublisherPeer] = {}
        self._seen: Dict[bytes, 'collections.OrderedDict[int, None]'] = {}
        self._counts = collections.Counter()
        self._next_channel = 0
        self._channels: List[_PublisherPeer] = []  # the peers with a channel, polled in turn
        self._takes = 0
        self._held = collections.deque()
        self._hold_timer = None
        self._destroyed = False
        self._plain = None
        self._transport = _dds.is_supported()
        if not self._transport:
            self._plain = node.create_subscription(
                msg_type, topic, callback, self.qos_profile, callback_group=callback_group,
                event_callbacks=event_callbacks)
            warn_unsupported_rmw('subscription', self._plain.topic_name)
            return
        self._with_info = _takes_message_info(callback)
        _dds.type_support(msg_type)  # imports the type support, as rclpy's create_* do
        # the discovery tap goes first: peers re-announce as soon as they see our endpoint
        self._discovery = discovery.for_node(node)
        with node.handle:
            self._sub = _rclpy.Subscription(node.handle, msg_type, topic,
                                            self.qos_profile.get_c_qos_profile())
        self._topic_name = self._sub.get_topic_name()
        self._gid = _dds.endpoint_gid(self._sub, 'subscription')
        self._info = EndpointInfo(self._gid, self._topic_name, EndpointKind.SUBSCRIPTION,
                                  node.get_name(), node.get_namespace())
        backends = get_installed_backends()
        self._backends = {name: backends[name] for name in self._accepted}
        self._advertised = {name: backend.get_backend_metadata()
                            for name, backend in sorted(self._backends.items())}
        self._user_data = advertisement.append(
            _dds.get_user_data(self._sub, 'subscription'), self._advertised)
        self._announce()
        for backend in self._backends.values():
            backend.on_creating_endpoint(self._info)
        self._guard = node.create_guard_condition(self._on_wake, callback_group)
        hook_destruction(self._guard, self._teardown)
        _dds.set_new_message_wakeup(self._sub, self._guard)
        # discovery wakes its own guard: data wake-ups do not poll discovery
        self._discovery_guard = node.create_guard_condition(self._discovery.process,
                                                            callback_group)
        self._discovery.add_wakeup(node, self._discovery_guard)
        self._start_reannounce_timer(node, callback_group)
        with self._lock:
            for peer in self._discovery.watch(dds_topic(self._topic_name), self):
                self._on_peer(peer)
        self._guard.trigger()  # take what arrived before the wake-up was armed

    # rclpy.subscription.Subscription compatible surface --------------------------------------

    @property
    def topic_name(self) -> str:
        """Fully qualified topic name."""
        return self._plain.topic_name if self._plain is not None else self._topic_name

    def get_publisher_count(self) -> int:
        """Publishers matched on the main topic (every publisher, buffer-aware or not)."""
        if self._plain is not None:
            return self._plain.get_publisher_count()
        return self._sub.get_publisher_count()

    @property
    def acceptable_buffer_backends(self) -> frozenset:
        """The backends whose descriptors this subscription accepts (always with ``cpu``)."""
        return self._accepted

    def destroy(self) -> None:
        """Destroy the subscription and its channels."""
        if self._plain is not None:
            self._node.destroy_subscription(self._plain)
            return
        self._node.destroy_guard_condition(self._guard)  # runs _teardown through the hook

    # diagnostics ----------------------------------------------------------------------------

    def buffer_peers(self) -> List[dict]:
        """The buffer-aware publishers serving this subscription, and how."""
        names = self._peer_node_names()
        with self._lock:
            return [{
                'gid': peer.info.gid_hex,
                'node': names.get(peer.info.gid, ''),
                'advertised_backends': dict(peer.backends),
                'channel_topic': peer.channel_topic,
                'backend_in_use': peer.backend_in_use,
                'received_as_descriptor': peer.received_descriptor,
                'received_as_cpu': peer.received_cpu,
            } for peer in self._peers.values()]

    def statistics(self) -> dict:
        """Counters: delivered, duplicates dropped, rejected descriptors, by route."""
        with self._lock:
            return {'gid': self._gid.hex() if self._transport else None,
                    'buffer_aware': self._transport,
                    'advertised_backends': dict(getattr(self, '_advertised', {})),
                    **{key: self._counts[key] for key in (
                        'delivered', 'from_channels', 'from_main_topic', 'duplicates_dropped',
                        'rejected')},
                    'peers': self.buffer_peers()}

    # internals ------------------------------------------------------------------------------

    def _announce(self) -> None:
        """(Re-)set USER_DATA: peers discover, or re-discover, our advertisement."""
        _dds.set_user_data(self._sub, self._user_data, 'subscription')

    def _on_wake(self) -> None:
        for _ in range(MAX_BATCH):
            with self._lock:
                if self._destroyed:
                    return
                item = self._take_one()
            if item is None:
                return
            msg, info = item
            if self._with_info:
                self.callback(msg, info)
            else:
                self.callback(msg)
        self._wake()  # more may be waiting: let other callbacks run first

    def _wake(self) -> None:
        """Trigger our guard condition, unless the subscription is being destroyed."""
        with self._lock:
            if self._destroyed:
                return
            try:
                self._guard.trigger()
            except InvalidHandle:  # the node is being destroyed
                pass

    def _take_one(self):
        """Take and decode the next deliverable message, or return None when none is left.

        Channels are polled before the main topic: a buffer-aware publisher writes a message's
        channel copy before its main-topic copy (kept for legacy subscribers), so the descriptor
        copy is normally found first and the CPU copy dropped as its duplicate. Channels are
        polled in rotating order, and the main topic gets a turn at least every
        ``MAIN_TOPIC_TURN`` takes, so that no source starves.
        """
        while True:
            taken = self._release_held() if self._held else None
            if taken is not None:
                raw, publisher_gid, info, peer = taken
                if self._is_duplicate(peer.info.gid, info['source_timestamp']):
                    self._counts['duplicates_dropped'] += 1
                    continue
                msg = self._decode(raw, peer, publisher_gid)
                if msg is not None:
                    self._counts['delivered'] += 1
                    return msg, info
                continue
            taken, peer, from_main = None, None, False
            self._takes += 1
            main_first = self._takes % MAIN_TOPIC_TURN == 0
            if main_first:
                taken, peer = self._take_main()
                from_main = taken is not None
            if taken is None:
                taken, peer = self._take_channels()
            if taken is None and not main_first:
                taken, peer = self._take_main()
                from_main = taken is not None
            if taken is None:
                return None
            raw, publisher_gid, info = taken
            if from_main and self._should_hold(peer, taken):
                continue
            # a channel's own writer has its own GID: both copies are keyed by the publisher's
            if peer is not None and self._is_duplicate(peer.info.gid, info['source_timestamp']):
                self._counts['duplicates_dropped'] += 1
                continue
            msg = self._decode(raw, peer, publisher_gid)
            if msg is not None:
                self._counts['delivered'] += 1
                return msg, info

    def _take_channels(self):
        """The next message of any channel (polled in rotating order), and its peer."""
        channels = self._channels
        count = len(channels)
        for i in range(count):
            peer = channels[(self._next_channel + i) % count]
            # peers that cannot send us descriptors: deserialized in C, as rclpy's take does
            taken = peer.channel.take() if peer.descriptors_possible else \
                peer.channel.take_message(self.msg_type, C_DESERIALIZE_MAX_BYTES)
            if taken is not None:
                self._counts['from_channels'] += 1
                self._next_channel = (self._next_channel + i + 1) % count
                return taken, peer
        return None, None

    def _should_hold(self, peer: Optional[_PublisherPeer], taken: tuple) -> bool:
        """Hold a main-topic copy whose channel copy is probably on its way.

        When the publisher serves us on a matched channel, the main-topic copy (written for
        legacy subscribers) is a duplicate whose descriptor twin may simply not have been taken
        yet: keep it up to ``HOLD_SECONDS`` so the channel copy wins. If none comes (the
        publisher had not matched the channel yet), it is delivered then.
        """
        if peer is None or peer.channel is None or peer.channel.matched_count() == 0:
            return False
        if taken[2]['source_timestamp'] in self._seen.get(peer.info.gid, ()):
            return False  # its twin was already delivered: let the duplicate check drop it
        self._held.append((time.monotonic() + HOLD_SECONDS, taken, peer))
        if self._hold_timer is None or not self._hold_timer.is_alive():
            self._hold_timer = threading.Timer(HOLD_SECONDS, self._wake)
            self._hold_timer.daemon = True
            self._hold_timer.start()
        return True

    def _release_held(self):
        """The oldest held main-topic copy whose hold expired, or None."""
        if self._held and self._held[0][0] <= time.monotonic():
            _, (raw, publisher_gid, info), peer = self._held.popleft()
            return raw, publisher_gid, info, peer
        if self._held and (self._hold_timer is None or not self._hold_timer.is_alive()):
            self._hold_timer = threading.Timer(
                max(0.0, self._held[0][0] - time.monotonic()), self._wake)
            self._hold_timer.daemon = True
            self._hold_timer.start()
        return None

    def _take_main(self):
        # publishers write only CPU data on the main topic: deserialize it in C, as rclpy does
        taken = _dds.take_message_with_gid(self._sub, self.msg_type, C_DESERIALIZE_MAX_BYTES)
        if taken is None:
            return None, None
        self._counts['from_main_topic'] += 1
        return taken, self._peers.get(taken[1])

    def _is_duplicate(self, publisher_gid: bytes, source_timestamp: int) -> bool:
        seen = self._seen.setdefault(publisher_gid, collections.OrderedDict())
        if source_timestamp in seen:
            del seen[source_timestamp]  # at most two copies exist: forget it now
            return True
        seen[source_timestamp] = None
        if len(seen) > DEDUP_WINDOW:
            seen.popitem(last=False)
        return False

    def _decode(self, raw, peer: Optional[_PublisherPeer], publisher_gid: bytes):
        """The message of a take: ``raw`` is already one (deserialized in C) or CDR bytes."""
        if type(raw) is self.msg_type:
            if peer is not None:
                peer.received_cpu += 1
                peer.backend_in_use = 'cpu'
            return raw
        try:
            decoded = codec.decode(raw, self.msg_type, known_backends=self._backends)
            if decoded.backend_type is None:
                if peer is not None:
                    peer.received_cpu += 1
                    peer.backend_in_use = 'cpu'
                return decoded.msg
            if peer is None:
                raise codec.CodecError(
                    f'descriptor of backend {decoded.backend_type!r} from publisher '
                    f'{publisher_gid.hex()}, which is not a discovered buffer-aware publisher')
            buffer = self._backends[decoded.backend_type].from_descriptor_with_endpoint(
                decoded.descriptor, peer.info)
            setattr(decoded.msg, self._field, buffer)
            peer.received_descriptor += 1
            peer.backend_in_use = decoded.backend_type
            return decoded.msg
        except Exception as exc:  # bytes from the network: reject, count, log, go on
            self._counts['rejected'] += 1
            _logger.warning(
                f'rejected a message on {self._topic_name} from {publisher_gid.hex()}: '
                f'{type(exc).__name__}: {exc} ({self._counts["rejected"]} rejected so far)',
                throttle_duration_sec=5.0)
            return None

    def _add_peer(self, info: EndpointInfo, backends: Dict[str, str]) -> _PublisherPeer:
        record = _PublisherPeer(info=info, backends=backends)
        record.channel_topic = channel_topic(self._topic_name, info.gid, self._gid)
        record.channel = _dds.create_channel_subscription(
            self._node, self.msg_type, record.channel_topic, self.qos_profile, self._guard)
        return record

    def _update_peer(self, record: _PublisherPeer, compatible) -> None:
        # Channels of a peer that cannot send us descriptors are taken as messages (C
        # deserialization); the others as bytes for the codec. Either way a message of the other
        # kind is still decoded correctly: this only picks the cheaper take.
        record.descriptors_possible = any(
            name != CPU_BACKEND and name in self._backends for name in record.backends)
        self._channels = [p for p in self._peers.values() if p.channel is not None]

    def _forget_peer(self, gid: bytes) -> None:
        self._seen.pop(gid, None)
        self._channels = [p for p in self._channels if p.info.gid != gid]

    def _release(self) -> None:
        self._node.destroy_guard_condition(self._discovery_guard)
        if self._hold_timer is not None:
            self._hold_timer.cancel()
        self._held.clear()
        _dds.clear_new_message_wakeup(self._sub)
        self._sub.destroy_when_not_in_use()

def _takes_message_info(callback: Callable) -> bool:
    """True when ``callback`` accepts ``(msg, message_info)`` (the rule rclpy applies)."""
    try:
        inspect.signature(callback).bind(object())
        return False
    except TypeError:
        inspect.signature(callback).bind(object(), object())
        return True


def create_subscription(node, msg_type, topic: str, callback: Callable,
                        qos_profile: Union[QoSProfile, int], *, callback_group=None,
                        event_callbacks=None,
                        acceptable_buffer_backends: Optional[str] = 'cpu') -> Subscription:
    """Create a buffer-aware subscription on ``node`` (arguments as ``Node.create_subscription``).

    :param acceptable_buffer_backends: Backends whose descriptors this subscription accepts:
        ``"cpu"`` (the default), ``""`` or ``None`` for CPU only, ``"any"`` for every installed
        backend, or a comma-separated list such as ``"demo"``. CPU data is always accepted.
    """
    return Subscription(node, msg_type, topic, callback, qos_profile,
                        callback_group=callback_group, event_callbacks=event_callbacks,
                        acceptable_buffer_backends=acceptable_buffer_backends)
