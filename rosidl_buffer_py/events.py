"""QoS deadline events counted over every route of a buffer-aware endpoint.

A stock DataWriter reports an offered deadline missed when it wrote nothing for a deadline
period, and a DataReader a requested deadline missed when it received nothing: counted from the
first sample on, once per period of silence. A buffer-aware endpoint's traffic also travels on
its channels, which its main-topic DataWriter or DataReader does not see, so DDS would report
misses while messages flow. :class:`DeadlineMonitor` counts them instead, over every route, with
the same rule, from a timer of the node (it runs in the endpoint's callback group, like rclpy's
own event handlers). Incompatible-QoS events come from the main topic's DDS entities, once per
peer (:func:`once_per_peer`); every other event (liveliness, matched, message lost) comes from
them through rclpy's own event handlers as it is.
"""
import contextlib
from typing import Callable, NamedTuple, Set

from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.logging import get_logger


class DeadlineMissedInfo(NamedTuple):
    """What rclpy's deadline callbacks receive (the fields of rmw's deadline status)."""

    total_count: int
    total_count_change: int


def finite(duration: Duration) -> bool:
    """Whether a QoS duration is set (rclpy's default, 0, means infinite)."""
    return 0 < duration.nanoseconds < 0x7FFFFFFFFFFFFFFF


class DeadlineMonitor:
    """Call ``callback(DeadlineMissedInfo)`` once per ``period`` without :meth:`activity`.

    Armed by the first :meth:`activity` (a message published or delivered); each later one
    restarts the period, as DDS restarts its deadline timer on every sample.
    """

    def __init__(self, node, period: Duration, callback: Callable, callback_group) -> None:
        self._node = node
        self._callback = callback
        self._count = 0
        self.timer = node.create_timer(period.nanoseconds / 1e9, self._on_timer, callback_group,
                                       clock=Clock(clock_type=ClockType.STEADY_TIME),
                                       autostart=False)

    def activity(self) -> None:
        """A message went out (publisher) or was delivered (subscription): restart the period."""
        self.timer.reset()

    def _on_timer(self) -> None:
        self._count += 1
        self._callback(DeadlineMissedInfo(self._count, 1))


class IncompatibleQoSInfo(NamedTuple):
    """What rclpy's incompatible-QoS callbacks receive (the fields of rmw's status)."""

    total_count: int
    total_count_change: int
    last_policy_kind: object


def once_per_peer(callback: Callable, incompatible_peers: Callable[[], Set[bytes]]) -> Callable:
    """Wrap an incompatible-QoS event callback so it fires once per incompatible peer.

    DDS reports incompatible QoS again whenever a peer's discovery data changes, and a
    buffer-aware endpoint changes its USER_DATA right after creation (its advertisement): a
    stock endpoint would see one event per incompatible peer, a buffer-aware peer would cause
    two. ``incompatible_peers()`` gives the GIDs of the incompatible peers the ROS graph knows;
    an event that brings none new is a repeat and is dropped. Counts are per peer, as stock's.
    """
    reported: Set[bytes] = set()
    total = 0

    def on_event(info) -> None:
        nonlocal total
        new = incompatible_peers() - reported
        if not new:
            if reported:
                return  # a known peer's discovery data changed: stock would not report it
            new = {b''}  # the graph does not list the peer yet: report it, once
        reported.update(new)
        total += len(new)
        try:
            callback(IncompatibleQoSInfo(total, len(new), info.last_policy_kind))
        finally:  # the user's callback first, as with stock; this note never stops it
            _note_stock_peers_may_count_twice()

    return on_event


_noted = False


def _note_stock_peers_may_count_twice() -> None:
    """Say once per process what differs from stock about incompatible QoS (see
    docs/guarantees.md)."""
    global _noted
    if not _noted:
        _noted = True
        with contextlib.suppress(Exception):  # a failing log handler is not ours to raise
            get_logger('rosidl_buffer_py').warning(
                'incompatible QoS with a buffer-aware endpoint: a plain rclpy/rclcpp peer may '
                'report it more than once (a buffer-aware endpoint publishes its USER_DATA '
                'advertisement after creation and when it finds a new buffer-aware peer: '
                'discovery events); buffer-aware endpoints report it once per peer, as stock '
                'does')
