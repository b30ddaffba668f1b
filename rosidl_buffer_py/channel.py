"""Names of the per-endpoint descriptor channels.

For each pair of a buffer-aware publisher P and a buffer-aware subscription S of topic ``T``,
P serves S on the DDS topic ``rt/T/_buf/<P gid>_<S gid>``, each GID the full 16-byte rmw GID as
32 lowercase hex characters (as rclpy's ``get_publishers_info_by_topic()`` reports it). Upstream
once used an 8-byte prefix, which is the same for every endpoint of one participant.
"""
from rosidl_buffer_py.backend import GID_SIZE

#: Prefix of ROS topics in DDS.
ROS_TOPIC_PREFIX = 'rt'
CHANNEL_INFIX = '_buf'


def channel_topic(ros_topic: str, publisher_gid: bytes, subscription_gid: bytes) -> str:
    """DDS topic name of the channel from ``publisher_gid`` to ``subscription_gid``.

    :param ros_topic: Fully qualified ROS topic name, e.g. ``/camera/image``.
    """
    if not ros_topic.startswith('/'):
        raise ValueError(f'ros_topic must be fully qualified (start with "/"), got {ros_topic!r}')
    for label, gid in (('publisher_gid', publisher_gid), ('subscription_gid', subscription_gid)):
        if len(gid) != GID_SIZE:
            raise ValueError(f'{label} must be {GID_SIZE} bytes, got {len(gid)}: {gid!r}')
    return (f'{ROS_TOPIC_PREFIX}{ros_topic}/{CHANNEL_INFIX}/'
            f'{bytes(publisher_gid).hex()}_{bytes(subscription_gid).hex()}')


def dds_topic(ros_topic: str) -> str:
    """DDS name of a ROS topic (``/a/b`` -> ``rt/a/b``)."""
    return ROS_TOPIC_PREFIX + ros_topic


def is_channel_topic(dds_name: str) -> bool:
    """True when ``dds_name`` is a per-endpoint channel (hidden from buffer discovery)."""
    return f'/{CHANNEL_INFIX}/' in dds_name
