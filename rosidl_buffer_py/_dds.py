"""Typed facade over the rmw_fastrtps layer of ``rosidl_buffer_py._native``.

Thin on purpose: it infers endpoint kinds, imports message type support, turns rclpy QoS
profiles into the rmw enum values and names the fields of discovery events. Every function
accepts rclpy objects (Node, Publisher, Subscription, GuardCondition), their ``.handle`` or a
raw pointer int; see ``src/native/README.md`` for lifetimes and threading.

Everything raises :class:`UnsupportedRmwError` when the entity is not rmw_fastrtps_cpp's
(callers then fall back to plain rclpy) and :class:`DdsError` when a middleware call fails.
"""
import os
import re
from pathlib import Path
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple

from rosidl_buffer_py import _native

DdsError = _native.DdsError
UnsupportedRmwError = _native.UnsupportedRmwError
#: ``ChannelPublisher(node, type_support, topic_name, reliability=1, history=1, depth=10)``:
#: ``.publish(data, source_timestamp: Optional[int] = None) -> None``,
#: ``.matched_count() -> int``, ``.matched_gids() -> List[bytes]``,
#: ``.wait_for_all_acked(timeout_sec: float) -> bool``, ``.destroy()``,
#: ``.gid``, ``.topic_name``, ``.valid``.
ChannelPublisher = _native.ChannelPublisher
#: ``ChannelSubscription(node, type_support, topic_name, ..., guard_condition=None)``:
#: ``.take() -> Optional[TakenMessage]``,
#: ``.take_message(msg_class, max_size=-1) -> Optional[TakenMessage]``
#: (the message deserialized in C when it can be, see :func:`take_message_with_gid`),
#: ``.matched_count() -> int``, ``.destroy()``, ``.gid``, ``.topic_name``, ``.valid``,
#: ``.on_udp`` (its DataReader listens on UDP only, not on the participant's shared memory:
#: see src/native/README.md, "Channel transport").
ChannelSubscription = _native.ChannelSubscription

#: The rmw implementation the native layer works with.
RMW_IMPLEMENTATION: str = _native.RMW_IMPLEMENTATION

#: (CDR bytes incl. encapsulation header, or a deserialized message; publisher GID; message info
#: dict)
TakenMessage = Tuple[Any, bytes, dict]


class EndpointEvent(NamedTuple):
    """One endpoint discovery event (or a ``known`` snapshot entry)."""

    kind: str             #: 'writer' or 'reader'
    status: str           #: 'discovered', 'changed', 'removed', 'ignored' or 'known'
    gid: bytes            #: 16 bytes, as rclpy's TopicEndpointInfo.endpoint_gid
    topic: str            #: DDS topic name, e.g. 'rt/camera/image'
    type_name: str        #: DDS type name, e.g. 'sensor_msgs::msg::dds_::Image_'
    user_data: bytes      #: USER_DATA QoS ('typehash=RIHS01_...;' + anything appended)
    participant_gid: bytes  #: 16-byte GID of the endpoint's DomainParticipant
    local: bool           #: True when the endpoint belongs to the queried node's participant


#: Package -> version this extension was compiled against (rmw_fastrtps_cpp and
#: rmw_fastrtps_shared_cpp from their package.xml, fastrtps = Fast DDS from its config.h).
BUILT_AGAINST: Dict[str, str] = dict(_native.BUILT_AGAINST)

#: Library file name (as mapped into the process) -> the package it belongs to.
_LIBRARIES = (
    ('rmw_fastrtps_cpp', re.compile(r'^librmw_fastrtps_cpp\.so(\.|$)')),
    ('rmw_fastrtps_shared_cpp', re.compile(r'^librmw_fastrtps_shared_cpp\.so(\.|$)')),
    ('fastrtps', re.compile(r'^libfastrtps\.so(\.|$)')),
)


class AbiStatus(NamedTuple):
    """Whether the running rmw_fastrtps libraries are those the extension was built against."""

    ok: bool
    reason: str                               #: '' when ok
    built: Dict[str, str]                     #: package -> version compiled against
    running: Dict[str, List[Tuple[str, str]]]  #: package -> [(library path, version)]


def _loaded_libraries() -> Dict[str, List[str]]:
    """Paths of the rmw_fastrtps libraries mapped into this process (from /proc/self/maps)."""
    found: Dict[str, List[str]] = {package: [] for package, _ in _LIBRARIES}
    try:
        with open('/proc/self/maps') as maps:
            lines = maps.read().splitlines()
    except OSError:
        return found
    for line in lines:
        fields = line.split(maxsplit=5)  # address perms offset dev inode [path]
        path = fields[5].strip() if len(fields) == 6 else ''
        if not path.startswith('/'):
            continue
        name = os.path.basename(path)
        for package, pattern in _LIBRARIES:
            if pattern.match(name) and path not in found[package]:
                found[package].append(path)
    return found


def _version_of(package: str, library: str) -> str:
    """The version of the package a loaded library file belongs to, read from the files its
    install prefix holds next to it: ``share/<package>/package.xml`` for the rmw packages,
    ``share/fastrtps/cmake/fastrtps-config-version.cmake`` for Fast DDS ('unknown' when they
    cannot be read)."""
    prefix = Path(library).parent.parent
    try:
        if package == 'fastrtps':
            text = (prefix / 'share' / 'fastrtps' / 'cmake' /
                    'fastrtps-config-version.cmake').read_text()
            match = re.search(r'set\(PACKAGE_VERSION "([^"]+)"\)', text)
        else:
            text = (prefix / 'share' / package / 'package.xml').read_text()
            match = re.search(r'<version>\s*([^<\s]+)\s*</version>', text)
    except OSError:
        match = None
    return match.group(1) if match else 'unknown'


def check_abi() -> AbiStatus:
    """Compare the running rmw_fastrtps_cpp, rmw_fastrtps_shared_cpp and Fast DDS with
    :data:`BUILT_AGAINST`; allow the native layer's private-layout accesses only when equal.

    Run at import; :func:`abi_status` gives the result. Versions are read at run time from the
    install prefix of each library mapped into the process (the one the dynamic linker and rmw
    loaded). An unknown version counts as a mismatch: the layouts would be guessed.
    """
    global _abi
    running: Dict[str, List[Tuple[str, str]]] = {}
    problems = []
    for package, paths in _loaded_libraries().items():
        running[package] = [(path, _version_of(package, path)) for path in paths]
        built = BUILT_AGAINST.get(package, 'unknown')
        if not paths:
            problems.append(f'{package} is not loaded')
        for path, version in running[package]:
            if version != built or built == 'unknown':
                problems.append(f'{package} {version} at {path} (built against {built})')
    reason = '; '.join(problems)
    _abi = AbiStatus(not problems, reason, dict(BUILT_AGAINST), running)
    _native.set_private_layout_verified(_abi.ok)
    if not _abi.ok and reason not in _warned_abi:
        _warned_abi.add(reason)
        from rclpy.logging import get_logger
        get_logger('rosidl_buffer_py').warning(
            'the rmw_fastrtps libraries of this process differ from those the native extension '
            f'of rosidl_buffer_py was built against ({reason}); it reads their private memory '
            'layout, so it stays off: buffer-aware publishers and subscriptions are plain rclpy '
            'ones (CPU bytes only). Rebuild the package against the installed ROS (./dev setup, '
            'colcon build).')
    return _abi


def abi_status() -> AbiStatus:
    """The result of the import-time :func:`check_abi`."""
    return _abi


def unsupported_reason() -> Optional[str]:
    """Why :func:`is_supported` is False (None when it is True)."""
    import rclpy
    rmw = rclpy.get_rmw_implementation_identifier()
    if rmw != RMW_IMPLEMENTATION:
        return f'{rmw} is not {RMW_IMPLEMENTATION}'
    if not _abi.ok:
        return f'the rmw_fastrtps libraries differ from those it was built against: {_abi.reason}'
    return None


def is_supported() -> bool:
    """Whether the rmw implementation rclpy loaded is the one this layer supports, in the
    versions it was built against (else create_publisher/create_subscription are plain rclpy)."""
    import rclpy
    return _abi.ok and rclpy.get_rmw_implementation_identifier() == RMW_IMPLEMENTATION


_warned_abi: set = set()
_abi = check_abi()


def type_support(msg_type: Any) -> Any:
    """The ``_TYPE_SUPPORT`` capsule of a message class (imported on first use)."""
    if getattr(msg_type, '_TYPE_SUPPORT', None) is None:
        msg_type.__class__.__import_type_support__()
    capsule = getattr(msg_type, '_TYPE_SUPPORT', None)
    if capsule is None:
        raise TypeError(f'{msg_type!r} is not a ROS message class with type support')
    return capsule


def endpoint_kind(endpoint: Any) -> str:
    """'publisher' or 'subscription' for an rclpy Publisher/Subscription or their handle."""
    from rclpy import _rclpy_pybind11 as rclpy_c
    from rclpy.publisher import Publisher
    from rclpy.subscription import Subscription
    if isinstance(endpoint, (Publisher, rclpy_c.Publisher)):
        return 'publisher'
    if isinstance(endpoint, (Subscription, rclpy_c.Subscription)):
        return 'subscription'
    raise TypeError(
        f'cannot tell the kind of {type(endpoint).__name__}; pass kind= explicitly')


def endpoint_gid(endpoint: Any, kind: Optional[str] = None) -> bytes:
    """16-byte GID of an rclpy publisher/subscription, equal to the graph's endpoint_gid."""
    return _native.endpoint_gid(endpoint, kind or endpoint_kind(endpoint))


def get_user_data(endpoint: Any, kind: Optional[str] = None) -> bytes:
    """USER_DATA of the DataWriter/DataReader behind an rclpy publisher/subscription."""
    return _native.get_user_data(endpoint, kind or endpoint_kind(endpoint))


def set_user_data(endpoint: Any, data: bytes, kind: Optional[str] = None) -> None:
    """Replace that USER_DATA. Keep rmw's 'typehash=...;' prefix: append to get_user_data()."""
    _native.set_user_data(endpoint, kind or endpoint_kind(endpoint), bytes(data))


def take_serialized_with_gid(subscription: Any) -> Optional[TakenMessage]:
    """Take one serialized message from an rclpy subscription, with its publisher's GID."""
    return _native.take_serialized_with_gid(subscription)


def take_message_with_gid(subscription: Any, msg_type: Any,
                          max_size: int = -1) -> Optional[TakenMessage]:
    """Take one message from an rclpy subscription, deserialized in C as rclpy's take does.

    The first item is a ``msg_type`` instance, or the CDR ``bytes`` when they do not deserialize
    with the type's own type support (a descriptor payload or malformed data: hand them to
    :func:`rosidl_buffer_py.codec.decode`) or are longer than ``max_size`` (when >= 0). No
    Python-level CDR work for ordinary messages.
    """
    return _native.take_message_with_gid(subscription, msg_type, max_size)


def peek_untaken(subscription: Any) -> Optional[Tuple[bytes, int]]:
    """``(publisher_gid, source_timestamp)`` of the next unread sample of an rclpy subscription,
    from its DDS sample info: nothing is taken or copied. None when there is none."""
    return _native.peek_untaken(subscription)


def discard_untaken(subscription: Any) -> Optional[Tuple[bytes, int]]:
    """Take the next unread sample without copying its payload (a duplicate to drop); its key,
    or None when there was none."""
    return _native.discard_untaken(subscription)


def write_message(msg: Any, source_timestamp: int, targets: List[Any]) -> None:
    """Write a ROS message to channel publishers and/or rclpy publishers of its type.

    The message is converted to its C struct once, as rclpy's ``publish`` does, and rmw
    serializes it into each target's DDS payload with ``source_timestamp`` (ns since the epoch).
    ``targets``: :class:`ChannelPublisher` objects and rclpy publishers (or their handles).
    """
    _native.write_message(msg, source_timestamp, targets)


def publish_serialized(publisher: Any, data: Any, source_timestamp: int) -> None:
    """Write serialized CDR on the DataWriter behind an rclpy publisher, with its source timestamp.

    ``data`` is CDR with its 4-byte encapsulation header (what ``serialize_message`` gives), in
    any C-contiguous buffer (not copied in Python; do not mutate it during the call).
    ``source_timestamp`` is ns since the epoch (0 <= t < 2**31 s); subscribers' takes report
    exactly it in ``info['source_timestamp']``.
    """
    _native.publish_serialized(publisher, data, source_timestamp)


def exclude_from_next_write(publisher: Any, reader_gids: Sequence[bytes]) -> bool:
    """Keep the next sample written on an rclpy publisher's DataWriter from ``reader_gids``.

    Writer side: Fast DDS sends those matched readers a GAP instead of the sample, so they
    neither receive nor copy its payload (a reliable reader counts nothing as lost). Call right
    before the write; calling again before it replaces the set. The filter chains to Fast DDS's
    own (content-filtered readers keep working). False when this DataWriter cannot filter (its
    private layout did not check out): nothing is excluded then.
    """
    return _native.exclude_from_next_write(publisher, reader_gids)


def remove_write_exclusions(publisher: Any) -> None:
    """Take :func:`exclude_from_next_write`'s filter off the publisher's DataWriter again."""
    _native.remove_write_exclusions(publisher)


def matched_subscription_gids(publisher: Any) -> List[bytes]:
    """16-byte GIDs of the subscriptions currently matched with an rclpy publisher.

    Same format as :func:`endpoint_gid` and ``get_subscriptions_info_by_topic()``'s
    ``endpoint_gid``; the set ``publisher.get_subscription_count()`` counts.
    """
    return _native.matched_subscription_gids(publisher)


def set_new_message_wakeup(subscription: Any, guard_condition: Any) -> None:
    """Trigger an rclpy GuardCondition whenever a new message reaches ``subscription``.

    ``subscription`` is an rclpy Subscription, a raw ``rclpy._rclpy_pybind11.Subscription``
    (e.g. not added to any node), or a pointer int. rmw triggers it right away when messages
    are already unread, and only on status changes after that: the woken code must take until
    nothing is left. Replaces an earlier wakeup of the same subscription. Pins both the
    subscription and the guard condition (rclpy defers destroying them) until
    :func:`clear_new_message_wakeup`, which must be called before letting them go.
    """
    _native.set_new_message_wakeup(subscription, guard_condition)


def clear_new_message_wakeup(subscription: Any) -> None:
    """Stop the wakeup and unpin; when it returns the guard condition is never triggered by it.

    A no-op when none is set. Works after rclpy was asked to destroy the subscription (the
    deferred destruction then happens here).
    """
    _native.clear_new_message_wakeup(subscription)


def install_discovery(node: Any) -> bool:
    """Install the discovery tap on the node's participant; call right after node creation."""
    return _native.install_discovery(node)


def uninstall_discovery(node: Any) -> bool:
    """Give rmw its own participant listener back."""
    return _native.uninstall_discovery(node)


def drain_discovery_events(node: Any) -> List[EndpointEvent]:
    """Queued endpoint events of the node's participant (single consumer per participant)."""
    return [EndpointEvent(*e) for e in _native.drain_discovery_events(node)]


def list_known_endpoints(node: Any) -> List[EndpointEvent]:
    """Alive endpoints seen since the tap was installed, with their latest USER_DATA."""
    return [EndpointEvent(*e) for e in _native.list_known_endpoints(node)]


def add_discovery_wakeup(node: Any, guard_condition: Any) -> bool:
    """Trigger an rclpy GuardCondition on every discovery event (pinned until removed)."""
    return _native.add_discovery_wakeup(node, guard_condition)


def remove_discovery_wakeup(guard_condition: Any) -> bool:
    """Stop triggering the guard condition and unpin it."""
    return _native.remove_discovery_wakeup(guard_condition)


def discovery_stats(node: Any) -> dict:
    """installed, queued, known, wakeups, dropped, recorded."""
    return _native.discovery_stats(node)


def _qos_args(qos: Any) -> dict:
    return {
        'reliability': int(qos.reliability),
        'history': int(qos.history),
        'depth': int(qos.depth),
    }


def create_channel_publisher(node: Any, msg_type: Any, topic_name: str,
                             qos: Any) -> ChannelPublisher:
    """A publisher below rcl on the full DDS topic name ``topic_name`` (volatile)."""
    return ChannelPublisher(node, type_support(msg_type), topic_name, **_qos_args(qos))


def create_channel_subscription(node: Any, msg_type: Any, topic_name: str, qos: Any,
                                guard_condition: Any = None) -> ChannelSubscription:
    """A subscription below rcl; new data triggers ``guard_condition``."""
    return ChannelSubscription(node, type_support(msg_type), topic_name,
                               guard_condition=guard_condition, **_qos_args(qos))
