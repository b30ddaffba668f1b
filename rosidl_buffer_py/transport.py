"""Small pieces shared by the buffer-aware publisher and subscription."""
import threading
from typing import Callable, Union

from rclpy.logging import get_logger
from rclpy.qos import QoSProfile

_logger = get_logger('rosidl_buffer_py')
_warned = set()
_warned_lock = threading.Lock()


def qos_of(qos_profile: Union[QoSProfile, int]) -> QoSProfile:
    """A QoSProfile from a profile or a history depth, as rclpy's create_* accept."""
    if isinstance(qos_profile, QoSProfile):
        return qos_profile
    if isinstance(qos_profile, int) and not isinstance(qos_profile, bool):
        if qos_profile < 0:
            raise ValueError(f'history depth must be >= 0, got {qos_profile}')
        return QoSProfile(depth=qos_profile)
    raise TypeError('qos_profile must be a QoSProfile or a history depth (int), got '
                    f'{type(qos_profile).__name__} {qos_profile!r}')


def warn_unsupported_rmw(what: str, topic: str) -> None:
    """Say once per process that this middleware gets plain rclpy pub/sub (CPU only)."""
    import rclpy
    from rosidl_buffer_py import _dds
    rmw = rclpy.get_rmw_implementation_identifier()
    with _warned_lock:
        if rmw in _warned:
            return
        _warned.add(rmw)
    _logger.warning(f'{rmw} is not supported by rosidl_buffer_py (needs '
                    f'{_dds.RMW_IMPLEMENTATION}): the {what} on {topic} and every other one '
                    'use plain rclpy pub/sub on the main topic, CPU bytes only')


def hook_destruction(guard_condition, teardown: Callable[[], None]) -> None:
    """Run ``teardown`` when ``guard_condition`` is destroyed.

    rclpy's ``Node.destroy_node()`` destroys every guard condition of the node, so a wrapper that
    owns a guard condition is torn down with its node (channels included), just like the
    publishers and subscriptions rclpy creates itself.
    """
    destroy = guard_condition.destroy

    def destroy_with_teardown():
        try:
            teardown()
        finally:
            destroy()

    guard_condition.destroy = destroy_with_teardown
