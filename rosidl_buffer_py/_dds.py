"""Typed facade over the rmw_fastrtps layer of ``rosidl_buffer_py._native``.

What Python adds to the native layer, and only that: the ABI guard (:func:`check_abi`, run at
import) and whether the layer may be used (:func:`is_supported`), endpoint kinds inferred from
rclpy objects, message type support imported on first use, rclpy QoS profiles turned into the
rmw enum values of channels, and named fields for discovery events. Everything else is called
on ``_native`` directly: ``rosidl_buffer_py/_native.pyi`` types and documents every native
function and class, and ``src/native/README.md`` says how they behave (lifetimes, threading).

Native calls raise :class:`UnsupportedRmwError` when the entity is not rmw_fastrtps_cpp's
(callers then fall back to plain rclpy) and :class:`DdsError` when a middleware call fails.
"""
import contextlib
import os
import re
import threading
from pathlib import Path
from typing import Any, Dict, Iterator, List, NamedTuple, Optional, Tuple

from rosidl_buffer_py import _native

DdsError = _native.DdsError
UnsupportedRmwError = _native.UnsupportedRmwError

#: The rmw implementation the native layer works with.
RMW_IMPLEMENTATION: str = _native.RMW_IMPLEMENTATION


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


def warn_unsupported(what: str, topic: str) -> None:
    """Say once per process why buffer-aware endpoints are plain rclpy pub/sub (CPU only): another
    middleware, or rmw_fastrtps libraries other than those the extension was built against
    (:func:`check_abi` has already logged which)."""
    import rclpy
    rmw = rclpy.get_rmw_implementation_identifier()
    with _warned_lock:
        if rmw in _warned_rmw:
            return
        _warned_rmw.add(rmw)
    if rmw == RMW_IMPLEMENTATION:
        return  # the ABI check warned once, naming the versions
    from rclpy.logging import get_logger
    get_logger('rosidl_buffer_py').warning(
        f'{rmw} is not supported by rosidl_buffer_py (needs {RMW_IMPLEMENTATION}): the {what} '
        f'on {topic} and every other one use plain rclpy pub/sub on the main topic, CPU bytes '
        'only')


def is_supported() -> bool:
    """Whether the rmw implementation rclpy loaded is the one this layer supports, in the
    versions it was built against (else create_publisher/create_subscription are plain rclpy)."""
    import rclpy
    return _abi.ok and rclpy.get_rmw_implementation_identifier() == RMW_IMPLEMENTATION


_warned_abi: set = set()
_warned_rmw: set = set()
_warned_lock = threading.Lock()
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
    from rclpy.publisher import Publisher
    from rclpy.subscription import Subscription
    from rosidl_buffer_py.rclpy_seams_7_1 import is_c_endpoint
    if isinstance(endpoint, Publisher) or is_c_endpoint(endpoint, 'publisher'):
        return 'publisher'
    if isinstance(endpoint, Subscription) or is_c_endpoint(endpoint, 'subscription'):
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


@contextlib.contextmanager
def created_disabled(node: Any, kind: str) -> Iterator[None]:
    """Inside the block, the DataWriters (``kind`` 'publisher') or DataReaders ('subscription')
    that rmw creates with ``node``'s participant are created disabled: USER_DATA set on them
    (:func:`set_user_data`) goes out with their first announcement instead of as a change to
    it, which held a peer's match of the endpoint until its participant announced again (see
    docs/design.md, "Discovery"). :func:`enable_created` ends the hold early; the block's end
    ends it in any case, and enables every endpoint created meanwhile."""
    _native.hold_enabling(node, kind, True)
    try:
        yield
    finally:
        _native.hold_enabling(node, kind, False)


def enable_created(node: Any, kind: str) -> None:
    """End :func:`created_disabled`'s hold now: enable what was created in it (idempotent)."""
    _native.hold_enabling(node, kind, False)


def drain_discovery_events(node: Any) -> List[EndpointEvent]:
    """Queued endpoint events of the node's participant (single consumer per participant)."""
    return [EndpointEvent(*e) for e in _native.drain_discovery_events(node)]


def discovery_epoch() -> memoryview:
    """The process's count of discovery callbacks passed to rmw, as a one-item ``'Q'`` view
    (``view[0]``: no call into DDS): a matched count changes only shortly after it moves."""
    return _native.discovery_epoch().cast('Q')


def list_known_endpoints(node: Any) -> List[EndpointEvent]:
    """Alive endpoints seen since the tap was installed, with their latest USER_DATA."""
    return [EndpointEvent(*e) for e in _native.list_known_endpoints(node)]


def _qos_args(qos: Any) -> dict:
    return {
        'reliability': int(qos.reliability),
        'history': int(qos.history),
        'depth': int(qos.depth),
    }


def create_channel_publisher(node: Any, msg_type: Any, topic_name: str,
                             qos: Any) -> _native.ChannelPublisher:
    """A publisher below rcl on the full DDS topic name ``topic_name`` (volatile)."""
    return _native.ChannelPublisher(node, type_support(msg_type), topic_name, **_qos_args(qos))


def create_channel_subscription(node: Any, msg_type: Any, topic_name: str, qos: Any,
                                guard_condition: Any = None) -> _native.ChannelSubscription:
    """A subscription below rcl; new data triggers ``guard_condition``."""
    return _native.ChannelSubscription(node, type_support(msg_type), topic_name,
                               guard_condition=guard_condition, **_qos_args(qos))
