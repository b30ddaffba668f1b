"""QoS of the endpoints on a topic, as the ROS graph reports them: which peers DDS would not
match with ours, which subscriptions are reliable, and rclpy's incompatible-QoS event reported
once per incompatible peer; and a subscription's history, which buffer-aware subscriptions
advertise (the graph does not report it)."""
import copy
from typing import Optional, Set

from rclpy.logging import get_logger
from rclpy.qos import (
    HistoryPolicy, QoSCompatibility, QoSProfile, ReliabilityPolicy, qos_check_compatible,
    qos_policy_name_from_kind)

from rosidl_buffer_py.backend import EndpointKind
from rosidl_buffer_py.events import once_per_peer


def _endpoint_qos(node, topic: str):
    """GID -> QoS profile (as DDS uses it) of the topic's publishers and subscriptions."""
    try:
        publishers = node.get_publishers_info_by_topic(topic)
        subscriptions = node.get_subscriptions_info_by_topic(topic)
    except Exception:  # the node is being destroyed
        return {}, {}
    return ({bytes(i.endpoint_gid): i.qos_profile for i in publishers},
            {bytes(i.endpoint_gid): i.qos_profile for i in subscriptions})


def _incompatible(pub: QoSProfile, sub: QoSProfile) -> bool:
    return qos_check_compatible(pub, sub)[0] == QoSCompatibility.ERROR


def incompatible_peers(node, topic: str, own_gid: bytes, peer_kind: EndpointKind) -> Set[bytes]:
    """GIDs of the endpoints of the opposite kind whose QoS is incompatible with ours.

    Both profiles come from the ROS graph (what DDS uses: rclpy's "default" durations are
    resolved there); an endpoint the graph does not list yet is not in the set.
    """
    publishers, subscriptions = _endpoint_qos(node, topic)
    if peer_kind is EndpointKind.SUBSCRIPTION:
        own = publishers.get(own_gid)
        return set() if own is None else {
            gid for gid, qos in subscriptions.items() if _incompatible(own, qos)}
    own = subscriptions.get(own_gid)
    return set() if own is None else {
        gid for gid, qos in publishers.items() if _incompatible(qos, own)}


def reliable_subscription(node, topic: str, gid: bytes) -> bool:
    """Whether the ROS graph lists subscription ``gid`` of ``topic`` as RELIABLE (False when it
    does not list it yet)."""
    qos = _endpoint_qos(node, topic)[1].get(gid)
    return qos is not None and qos.reliability == ReliabilityPolicy.RELIABLE


def incompatible_qos_once_per_peer(event_callbacks, node, endpoint_impl, kind: EndpointKind,
                                   gid: bytes, topic_as_passed: str):
    """A copy of rclpy ``event_callbacks`` whose incompatible-QoS callback (the user's, or one
    logging rclpy's default warning, which names the topic as it was passed, as rclpy's does)
    fires once per incompatible peer (see :func:`rosidl_buffer_py.events.once_per_peer`)."""
    callback = event_callbacks.incompatible_qos
    if callback is None and not event_callbacks.use_default_callbacks:
        return event_callbacks
    resolved = endpoint_impl.get_topic_name()
    topic = topic_as_passed
    if callback is None:
        logger = get_logger(endpoint_impl.get_logger_name())
        if kind is EndpointKind.PUBLISHER:
            text = (f"New subscription discovered on topic '{topic}', requesting incompatible "
                    'QoS. No messages will be sent to it. Last incompatible policy: {}')
        else:
            text = (f"New publisher discovered on topic '{topic}', offering incompatible QoS. "
                    'No messages will be received from it. Last incompatible policy: {}')

        def callback(info):
            logger.warn(text.format(qos_policy_name_from_kind(info.last_policy_kind)))
    peer_kind = (EndpointKind.SUBSCRIPTION if kind is EndpointKind.PUBLISHER
                 else EndpointKind.PUBLISHER)
    event_callbacks = copy.copy(event_callbacks)
    event_callbacks.incompatible_qos = once_per_peer(
        callback, lambda: incompatible_peers(node, resolved, gid, peer_kind))
    return event_callbacks


#: A subscription's history, as its ``cpu`` advertisement entry carries it: ``keep_last.<N>``
#: or ``keep_all``. DDS discovery does not carry a reader's history; a publisher needs it to
#: know which descriptors the subscription can still take (its buffers' memory is kept that
#: long, see ``EndpointInfo.history_depth``).
KEEP_LAST_PREFIX = 'keep_last.'
KEEP_ALL = 'keep_all'


def history_metadata(qos: QoSProfile) -> str:
    """``keep_last.<depth>`` or ``keep_all`` for a subscription's QoS."""
    if qos.history == HistoryPolicy.KEEP_ALL:
        return KEEP_ALL
    return f'{KEEP_LAST_PREFIX}{qos.depth}'


def parse_history_metadata(text: Optional[str]) -> Optional[int]:
    """The history a subscription advertised: its KEEP_LAST depth (> 0), 0 for KEEP_ALL, None
    when it said nothing usable (an older or foreign peer: the metadata comes from the
    network)."""
    if text == KEEP_ALL:
        return 0
    if isinstance(text, str) and text.startswith(KEEP_LAST_PREFIX):
        digits = text[len(KEEP_LAST_PREFIX):]
        if digits.isdigit() and len(digits) <= 9 and int(digits) > 0:
            return int(digits)
    return None
