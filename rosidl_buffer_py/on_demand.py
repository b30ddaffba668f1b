"""The entities an endpoint creates on its node, and their end: timers that exist only while
something needs them, and the destruction of the timers and guard conditions it made.

rclpy 7.1's executor puts every timer of a node into each of its waits, cancelled ones too, and
pays a few hundred Python opcodes per timer and wake-up for it (the wake-up that delivers a
message included). A stock endpoint has no timer; an endpoint of ours needs one only while a
peer's channel is unmatched or a route is being brought up. So such a timer is destroyed when
it is not needed, never just cancelled, and created again when it is.
"""
from typing import Callable, List, Optional

from rclpy.timer import Timer


class OnDemandTimer:
    """A timer of ``node`` that calls ``callback`` every ``period`` seconds between
    :meth:`start` and :meth:`stop` (from any thread, its own callback's included)."""

    def __init__(self, node, period: float, callback: Callable[[], None], callback_group,
                 logger) -> None:
        self._node = node
        self._period = period
        self._callback = callback
        self._callback_group = callback_group
        self._logger = logger
        #: the node's timer while running, else None
        self.timer: Optional[Timer] = None

    @property
    def running(self) -> bool:
        return self.timer is not None

    def start(self) -> None:
        """Run from now on (the first call ``period`` seconds from now); nothing if running."""
        if self.timer is None:
            self.timer = self._node.create_timer(self._period, self._callback,
                                                 self._callback_group)

    def stop(self) -> None:
        """Destroy the timer (nothing if not running; a node destroyed first already did)."""
        timer, self.timer = self.timer, None
        destroy_node_entities(self._node, [timer], self._logger)


def destroy_node_entities(node, entities: List[object], logger) -> None:
    """Destroy the timers and guard conditions an endpoint created on its node (None entries
    are skipped; a node destroyed first already destroyed them)."""
    for entity in filter(None, entities):
        try:
            (node.destroy_timer if hasattr(entity, 'timer_period_ns')
             else node.destroy_guard_condition)(entity)
        except Exception as exc:  # the node was destroyed first
            logger.debug(f'destroying {entity!r}: {exc}')
