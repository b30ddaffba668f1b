"""What ``create_publisher`` and ``create_subscription`` give when an endpoint cannot be
buffer-aware (:func:`rosidl_buffer_py.endpoint.buffer_aware` is False: a type without a
``uint8[]`` field, or another rmw than the one the native layer supports): plain rclpy
endpoints, CPU bytes as stock sends them, with the diagnostics surface of the buffer-aware ones
(no peers, ``buffer_aware`` False).
"""
from typing import Callable, List, Optional

import rclpy.publisher
import rclpy.subscription
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.qos import QoSProfile

from rosidl_buffer_py import _dds, codec
from rosidl_buffer_py import rclpy_seams_7_1 as seams
from rosidl_buffer_py.diagnostics import (
    PublisherPeer, PublisherStatistics, SubscriptionPeer, SubscriptionStatistics)
from rosidl_buffer_py.message_support import enable_buffer_fields
from rosidl_buffer_py.registry import parse_acceptable_buffer_backends


def check_wait_arguments(count: int, timeout_sec: Optional[float]) -> None:
    """``wait_for_buffer_peers``'s argument checks (both publishers)."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f'count must be an int of at least 1, got {count!r}')
    if timeout_sec is not None and not timeout_sec >= 0:
        raise ValueError(f'timeout_sec must be None or >= 0, got {timeout_sec!r}')


class PlainPublisher(rclpy.publisher.Publisher):
    """A plain rclpy publisher. A message whose ``uint8[]`` fields hold Buffers (another rmw)
    is sent as its CPU bytes, which stock rclpy cannot convert itself."""

    def __init__(self, publisher_impl, msg_type, topic: str, qos_profile: QoSProfile, *,
                 event_callbacks: PublisherEventCallbacks, callback_group, node) -> None:
        enable_buffer_fields(msg_type)
        self._has_buffer_fields = bool(codec.buffer_paths(msg_type))
        super().__init__(publisher_impl, msg_type, topic, qos_profile,
                         event_callbacks=event_callbacks, callback_group=callback_group)
        self._sent = 0
        if self._has_buffer_fields:
            _dds.warn_unsupported('publisher', self.topic_name)

    def publish(self, msg) -> None:
        """Publish ``msg`` (or serialized CDR bytes) as rclpy does."""
        if isinstance(msg, (bytes, bytearray, memoryview)):
            msg = bytes(msg)
        elif not isinstance(msg, self.msg_type):
            raise TypeError(f'Expected {self.msg_type.__name__} or serialized bytes, '
                            f'got {type(msg).__name__}')
        elif self._has_buffer_fields and codec.buffers_of(msg):
            msg = bytes(codec.encode(msg))
        super().publish(msg)
        self._sent += 1

    def wait_for_buffer_peers(self, count: int = 1, timeout_sec: Optional[float] = None
                              ) -> bool:
        """False at once: a plain publisher has no buffer-aware peers (arguments checked as
        the buffer-aware publisher checks them)."""
        check_wait_arguments(count, timeout_sec)
        return False

    def buffer_peers(self) -> List[SubscriptionPeer]:
        return []

    def statistics(self) -> PublisherStatistics:
        return PublisherStatistics(
            gid=None, buffer_aware=False, advertised_backends={}, sent_on_main_topic=self._sent,
            main_topic_withheld=0, main_topic_doubled=0, cpu_copies_to_buffer_capable_peers=0,
            peers_added=0, peers_removed=0, peers=[])


class PlainSubscription(rclpy.subscription.Subscription):
    """A plain rclpy subscription (CPU bytes only)."""

    def __init__(self, node, msg_type, topic: str, callback: Callable, qos_profile: QoSProfile,
                 callback_group, event_callbacks: SubscriptionEventCallbacks,
                 acceptable_buffer_backends: Optional[str]) -> None:
        self.acceptable_buffer_backends = parse_acceptable_buffer_backends(
            acceptable_buffer_backends)
        _dds.type_support(msg_type)  # imports the type support, as rclpy's create_* do
        handle = seams.c_subscription(node, msg_type, topic, qos_profile)
        super().__init__(handle, msg_type, topic, callback, callback_group, qos_profile, False,
                         event_callbacks=event_callbacks)
        if codec.buffer_paths(msg_type):
            _dds.warn_unsupported('subscription', self.topic_name)

    @property
    def topic_name(self) -> str:
        with self.handle:
            return self.handle.get_topic_name()

    def buffer_peers(self) -> List[PublisherPeer]:
        return []

    def statistics(self) -> SubscriptionStatistics:
        return SubscriptionStatistics(gid=None, buffer_aware=False, advertised_backends={})
