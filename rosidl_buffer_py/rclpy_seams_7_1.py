"""Every private part of rclpy this package uses, in one place: rclpy 7.1 (ROS 2 Jazzy).

rclpy has no hook for a subscription class of one's own, so a buffer-aware subscription is
created and registered as ``Node.create_subscription`` creates and registers its own (rclpy's
argument checks, its QoS-override parameters, the node's list of subscriptions), and its main
topic's C subscription is rclpy's C class with ``take_message`` delegated (the executor takes
through it as through any subscription, and the take runs the subscription's route protocol).
Each function names the private part it uses; nothing else in the package touches one.

:data:`MIRRORS` is the rclpy version these were read from. :func:`matches` compares the running
rclpy with it; ``test/test_rclpy_seams.py`` fails when they differ (read the parts again, then
update :data:`MIRRORS`), and creating an endpoint under another version logs one warning.
"""
import functools
import importlib.metadata
from typing import Callable, Iterable, Optional, Tuple

import rclpy.subscription
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import get_logger, LoggingSeverity
from rclpy.qos import QoSProfile

#: The rclpy release (major, minor) whose private parts this module mirrors.
MIRRORS: Tuple[int, int] = (7, 1)


@functools.lru_cache(maxsize=None)
def running_version() -> Optional[Tuple[int, int]]:
    """(major, minor) of the running rclpy, from its Python distribution's metadata (PyPI's
    wheels and ament's installs both carry it); None when it has none."""
    for dist in ('rclpy', 'ros-jazzy-rclpy'):
        try:
            return _major_minor(importlib.metadata.version(dist))
        except (importlib.metadata.PackageNotFoundError, ValueError):
            continue
    return None


def _major_minor(version: str) -> Tuple[int, int]:
    major, minor = version.split('.')[:2]
    return int(major), int(minor)


def matches() -> bool:
    """Whether the running rclpy is the release these seams mirror."""
    return running_version() == MIRRORS


@functools.lru_cache(maxsize=None)
def warn_if_other_version() -> None:
    """Log once per process when the running rclpy is not the one mirrored."""
    if not matches():
        get_logger('rosidl_buffer_py').warning(
            f'rclpy {running_version()} is running; rosidl_buffer_py mirrors private parts of '
            f'rclpy {MIRRORS[0]}.{MIRRORS[1]} (rosidl_buffer_py/rclpy_seams_7_1.py): '
            'buffer-aware subscriptions may not work as they should')


def log(logger, severity: LoggingSeverity, message: str, caller: Callable) -> bool:
    """Log ``message`` as ``logger.log(message, severity)`` does (console, ``/rosout``), but
    without its caller lookup: False when ``severity`` is not enabled.

    rclpy 7.1's ``RcutilsLogger.log`` finds its caller with ``inspect.getframeinfo`` on every
    call, which reads the caller's source and resolves paths: 17 ms for a first line on an idle
    machine, 0.5 ms after. A line logged on a subscription's delivery path held the executor
    that long, and a KEEP_LAST 5 reader of three publishers overwrote a sample meanwhile (the
    equivalence scenario ``publisher_restart`` under load). This calls what it calls last,
    ``_rclpy.rclpy_logging_rcutils_log``, with ``caller``'s name, file and first line (about
    10 µs). No filters (once, throttle): the caller decides.
    """
    if not logger.is_enabled_for(severity):
        return False
    code = caller.__code__
    _rclpy.rclpy_logging_rcutils_log(
        severity, logger.name, message, code.co_name, code.co_filename, code.co_firstlineno)
    return True


def validate_qos(node, qos_profile) -> QoSProfile:
    """``Node._validate_qos_or_depth_parameter``: a QoSProfile, or rclpy's error for a bad one."""
    return node._validate_qos_or_depth_parameter(qos_profile)


def validate_topic_name(node, topic: str) -> None:
    """``Node._validate_topic_or_service_name``: rclpy's error for a bad topic name."""
    node._validate_topic_or_service_name(topic)


def declare_qos_parameters(node, topic: str, qos: QoSProfile, options) -> None:
    """``rclpy.qos_overriding_options._declare_qos_parameters`` for a subscription: the
    QoS-override parameters ``Node.create_subscription`` declares (``options`` may be None)."""
    from rclpy.qos_overriding_options import _declare_qos_parameters, QoSOverridingOptions
    _declare_qos_parameters(rclpy.subscription.Subscription, node, topic, qos,
                            options or QoSOverridingOptions([]))


def register_subscription(node, sub, callback_group, handlers: Iterable) -> None:
    """What ``Node.create_subscription`` does with a new subscription: in its callback group,
    in ``Node._subscriptions`` (``node.subscriptions``, ``destroy_subscription``,
    ``destroy_node``), the executor woken (``Node._wake_executor``), its event handlers
    added as waitables."""
    callback_group.add_entity(sub)
    node._subscriptions.append(sub)
    node._wake_executor()
    for handler in handlers:
        node.add_waitable(handler)


def c_subscription(node, msg_type, topic: str, qos: QoSProfile):
    """rclpy's C subscription (``_rclpy.Subscription``), as ``Node.create_subscription``
    creates it."""
    with node.handle:
        return _rclpy.Subscription(node.handle, msg_type, topic, qos.get_c_qos_profile())


class DelegatingReader(_rclpy.Subscription):
    """rclpy's C subscription whose ``take_message`` (called by the executor, as for any
    subscription) returns what ``take()`` returns: ``(message, message_info)`` or None."""

    take: Callable[[], Optional[tuple]] = staticmethod(lambda: None)

    def take_message(self, msg_type, raw):
        return self.take()


def delegating_reader(node, msg_type, topic: str, qos: QoSProfile) -> DelegatingReader:
    """A :class:`DelegatingReader` of ``topic``; it takes nothing until its ``take`` is set."""
    with node.handle:
        return DelegatingReader(node.handle, msg_type, topic, qos.get_c_qos_profile())


def is_c_endpoint(endpoint, kind: str) -> bool:
    """Whether ``endpoint`` is rclpy's C publisher or subscription (``kind``)."""
    return isinstance(endpoint, _rclpy.Publisher if kind == 'publisher' else _rclpy.Subscription)


def before_guard_destroyed(guard, callback: Callable[[], None]) -> None:
    """Call ``callback()`` when ``guard`` (a guard condition of a node) is destroyed, first. In
    ``node.destroy_node()`` that is after the node's endpoints are destroyed and before its rcl
    node is (rmw destroys the context's participant with its last node).

    rclpy 7.1's ``Node.destroy_node`` destroys publishers, subscriptions, clients, services,
    timers, then guard conditions (each through its ``destroy()``), then the node's handle: the
    guard's ``destroy`` is wrapped, on the instance.
    """
    destroy = guard.destroy

    def destroy_after_callback() -> None:
        try:
            callback()
        finally:
            destroy()

    guard.destroy = destroy_after_callback


def subscription_counter(publisher) -> Callable[[], int]:
    """``publisher.get_subscription_count`` as one C call, for a caller that keeps the
    publisher from being destroyed while it calls (our publisher calls it under the lock its
    ``destroy()`` takes before rclpy's).

    rclpy 7.1's ``Publisher.get_subscription_count`` pins the handle around the C call (two
    Python frames and the pin per call); this is the C handle's ``get_subscription_count``
    itself, which the route view reads whenever discovery may have changed the count.
    """
    return publisher.handle.get_subscription_count
