"""buffer_topic_info: ``ros2 topic info -v`` for buffer-aware topics.

``ros2 run rosidl_buffer_py buffer_topic_info <topic> [--wait S] [--probe] [--json]`` (or
``python -m rosidl_buffer_py.tools.info``) lists every publisher and subscription of a topic: node,
GID (32 hex), QoS, whether it is buffer-aware or legacy, the backends and metadata it advertises
in USER_DATA (``BUFBE:``), and the per-endpoint descriptor channels
``rt/<topic>/_buf/<publisher gid>_<subscription gid>``.

How it learns the advertisements: a normal rclpy node installs the discovery tap
(``_native.install_discovery``) right after it is created, then listens for ``--wait`` seconds
(default 3: a new Fast DDS participant can need up to one announcement period, about 3 s, to
discover a running one). When what it heard by then is visibly incomplete (nothing yet, a
channel names an endpoint not seen yet, an endpoint is known to DDS but not yet to the ROS graph
or has no node name yet, a channel has only one side) or still changing, it keeps listening, up
to ``COMPLETION_GRACE_SECONDS`` more, and says in a note what was still missing if that did not
suffice. A ``--wait`` shorter than the default is answered with a note that endpoints may be
missing. Fast DDS cannot replay USER_DATA of endpoints
discovered before the tap existed, and a node's participant starts discovering at
``rclpy.init``, so an endpoint found in that short gap is reported with
``"advertisement": "unknown"``. ``--probe`` closes the gap: it creates a
temporary plain subscription and a plain publisher on the topic (for ``--wait`` seconds more);
buffer-aware endpoints re-announce when they see a new endpoint of the opposite kind. The price
is a short disturbance of the topic: while the probe subscription exists, buffer-aware publishers
also write CPU bytes on the main topic (a legacy subscriber is matched), and publishers or
subscribers that wait for a number of peers count the probes. The probes never publish and are
never listed. Without ``--probe`` the inspector creates no endpoint on the topic.

Exit status: 0 when the topic has endpoints, 1 (with a message on stderr) when it has none, 2
for a usage error, 130 when interrupted.
"""
import argparse
import importlib
import json
import os
import signal
import sys
import time
from typing import Dict, List, Optional

import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.subscription import Subscription
from rclpy.utilities import remove_ros_args

from rosidl_buffer_py import advertisement
from rosidl_buffer_py.channel import CHANNEL_INFIX, dds_topic
from rosidl_buffer_py.tools.native_output import native_stdout_to_stderr

_KIND = {'writer': 'publisher', 'reader': 'subscription'}

#: Default ``--wait``: a new participant can need up to one Fast DDS announcement period (about
#: 3 s) to discover a running one.
DEFAULT_WAIT_SECONDS = 3.0
#: After ``--wait``, how much longer to listen while the view is visibly incomplete.
COMPLETION_GRACE_SECONDS = 3.0
#: The view counts as complete once nothing visibly misses and it has not changed this long.
QUIET_SECONDS = 0.3
#: The node name the ROS graph gives an endpoint whose node is not known yet.
_UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'

#: How often the view is re-checked during that grace.
_RECHECK_SECONDS = 0.1


def _gid_hex(gid) -> str:
    return bytes(gid).hex()


def _qos(profile) -> dict:
    def name(policy):
        return getattr(policy, 'name', str(policy))
    return {'reliability': name(profile.reliability), 'durability': name(profile.durability),
            'history': name(profile.history), 'depth': profile.depth}


def _message_class(type_name: str):
    """``pkg/msg/Name`` -> the message class (None when it cannot be imported)."""
    try:
        package, interface, name = type_name.split('/')
        return getattr(importlib.import_module(f'{package}.{interface}'), name)
    except (ValueError, ImportError, AttributeError):
        return None


def _channels(topic: str, node, known) -> List[dict]:
    """Channels of ``topic`` from the tap's known endpoints and the graph's DDS topic names."""
    prefix = f'{dds_topic(topic)}/{CHANNEL_INFIX}/'
    found: Dict[str, dict] = {}

    def entry(name: str) -> Optional[dict]:
        pub, sep, sub = name[len(prefix):].partition('_')
        if not sep or len(pub) != 32 or len(sub) != 32:
            return None
        return found.setdefault(name, {
            'dds_topic': name, 'publisher_gid': pub, 'subscription_gid': sub,
            'writer_gids': set(), 'reader_gids': set()})

    for event in known:
        if event.topic.startswith(prefix):
            item = entry(event.topic)
            if item is not None:
                item['writer_gids' if event.kind == 'writer' else 'reader_gids'].add(
                    _gid_hex(event.gid))
    for name, _types in node.get_topic_names_and_types(no_demangle=True):
        if name.startswith(prefix):
            item = entry(name)
            if item is None:
                continue
            for info in node.get_publishers_info_by_topic(name, no_mangle=True):
                item['writer_gids'].add(_gid_hex(info.endpoint_gid))
            for info in node.get_subscriptions_info_by_topic(name, no_mangle=True):
                item['reader_gids'].add(_gid_hex(info.endpoint_gid))
    result = []
    for item in sorted(found.values(), key=lambda c: c['dds_topic']):
        result.append({'dds_topic': item['dds_topic'],
                       'publisher_gid': item['publisher_gid'],
                       'subscription_gid': item['subscription_gid'],
                       'writer': bool(item['writer_gids']), 'reader': bool(item['reader_gids'])})
    return result


def _missing(node, topic: str, tapped: bool, own: set) -> List[str]:
    """What discovery visibly has not delivered yet about ``topic`` (empty: consistent view).

    Each buffer-aware pair names both endpoints in its channel, every endpoint DDS reports
    should also reach the ROS graph, and every endpoint of the graph should have its node's
    name: rmw learns it from the ``ros_discovery_info`` topic, which can arrive after the
    endpoint itself (the graph says ``_NODE_NAME_UNKNOWN_`` meanwhile). A gap in any of these
    means discovery is still under way; so does a topic with no endpoint at all yet.
    """
    from rosidl_buffer_py import _dds
    infos = [i for i in node.get_publishers_info_by_topic(topic) +
             node.get_subscriptions_info_by_topic(topic) if _gid_hex(i.endpoint_gid) not in own]
    graph = {_gid_hex(i.endpoint_gid) for i in infos}
    known = _dds.list_known_endpoints(node) if tapped else []
    main = dds_topic(topic)
    dds = {_gid_hex(e.gid) for e in known
           if e.topic == main and e.kind in _KIND and not e.local} - own
    if not graph and not dds:
        return [f'no endpoint of {topic} discovered yet']
    missing = [f'{gid} known to DDS, not to the ROS graph' for gid in sorted(dds - graph)]
    missing += [f'the node of {_gid_hex(i.endpoint_gid)} (not in ros_discovery_info yet)'
                for i in infos if i.node_name.startswith(_UNKNOWN_NODE)]
    for channel in _channels(topic, node, known):
        for side in ('publisher_gid', 'subscription_gid'):
            if channel[side] not in graph:
                missing.append(f"{channel[side]} named by channel {channel['dds_topic']}")
        if not (channel['writer'] and channel['reader']):
            missing.append(f"channel {channel['dds_topic']} has one side only")
    return missing


def _snapshot(node, topic: str) -> tuple:
    """The graph's endpoints of ``topic`` with their node names (to notice changes)."""
    return tuple(sorted((_gid_hex(i.endpoint_gid), i.node_name) for i in
                        node.get_publishers_info_by_topic(topic) +
                        node.get_subscriptions_info_by_topic(topic)))


def _listen_until_complete(node, topic: str, tapped: bool, own: set) -> List[str]:
    """After the wait: listen while the view is visibly incomplete or still changing (each
    participant's endpoints arrive together, but participants and their node names arrive one
    by one), at most ``COMPLETION_GRACE_SECONDS``. Returns what is still missing."""
    deadline = time.monotonic() + COMPLETION_GRACE_SECONDS
    last = _snapshot(node, topic)
    quiet_since = time.monotonic()
    while True:
        missing = _missing(node, topic, tapped, own)
        now = time.monotonic()
        if now >= deadline or (not missing and now - quiet_since >= QUIET_SECONDS):
            return missing
        time.sleep(_RECHECK_SECONDS)
        current = _snapshot(node, topic)
        if current != last:
            last, quiet_since = current, time.monotonic()


def _second_look(topic: str, gids: set) -> list:
    """Discovery events of the endpoints ``gids`` of ``topic``, seen by a second participant.

    The first participant starts discovering when it is created, a moment before its tap is
    installed: an endpoint found in that gap has no advertisement. A fresh participant (its own
    context), tapped at once, discovers the graph again; it is rarely unlucky twice. Listens at
    most ``DEFAULT_WAIT_SECONDS`` (a discovery announcement period).
    """
    from rosidl_buffer_py import _dds, _native
    context = rclpy.Context()
    rclpy.init(context=context, args=[])
    try:
        node = rclpy.create_node(
            f'_buffer_topic_info_{os.getpid()}_2', context=context, enable_rosout=False,
            start_parameter_services=False,
            parameter_overrides=[Parameter('start_type_description_service', value=False)])
        try:
            _native.install_discovery(node)
            main = dds_topic(topic)
            deadline = time.monotonic() + DEFAULT_WAIT_SECONDS
            while True:
                found = [e for e in _dds.list_known_endpoints(node)
                         if e.topic == main and _gid_hex(e.gid) in gids and not e.local]
                if len(found) == len(gids) or time.monotonic() >= deadline:
                    return found
                time.sleep(_RECHECK_SECONDS)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def inspect_topic(node, topic: str, wait: float, probe: bool, tapped: bool) -> dict:
    """Collect what the graph and the discovery tap know about ``topic`` (fully qualified)."""
    from rosidl_buffer_py import _dds
    time.sleep(wait)
    probes = []
    notes = []
    if probe:
        types = {t for name, ts in node.get_topic_names_and_types() if name == topic for t in ts}
        for type_name in sorted(types):
            msg_type = _message_class(type_name)
            if msg_type is None:
                notes.append(f'--probe: cannot import {type_name}; not probed')
                continue
            qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
            probes.append(node.create_subscription(msg_type, topic, lambda _m: None, qos,
                                                   raw=True))
            probes.append(node.create_publisher(msg_type, topic, 1))
        if probes:
            time.sleep(wait)
    own = set()
    if tapped:
        for entity in probes:
            own.add(_gid_hex(_dds.endpoint_gid(entity)))
    missing = _listen_until_complete(node, topic, tapped, own)
    if wait < DEFAULT_WAIT_SECONDS:
        notes.append(f'listened {wait:g} s, less than a Fast DDS announcement period '
                     f'({DEFAULT_WAIT_SECONDS:g} s): endpoints of processes not discovered yet '
                     'may be missing, as may their node names and advertisements')
    if missing:
        notes.append(f'discovery still incomplete after {COMPLETION_GRACE_SECONDS:g} s more: '
                     + '; '.join(missing))
    known = _dds.list_known_endpoints(node) if tapped else []
    endpoints: Dict[str, dict] = {}

    def record(gid: str, kind: str) -> dict:
        return endpoints.setdefault(gid, {
            'kind': kind, 'gid': gid, 'node_name': None, 'node_namespace': None,
            'topic_type': None, 'qos': None, 'advertisement': 'unknown',
            'buffer_aware': None, 'legacy': None, 'backends': None})

    for kind, infos in (('publisher', node.get_publishers_info_by_topic(topic)),
                        ('subscription', node.get_subscriptions_info_by_topic(topic))):
        for info in infos:
            gid = _gid_hex(info.endpoint_gid)
            if gid in own:
                continue
            item = record(gid, kind)
            item.update(node_name=info.node_name, node_namespace=info.node_namespace,
                        topic_type=info.topic_type, qos=_qos(info.qos_profile))
    main = dds_topic(topic)
    for event in known:
        gid = _gid_hex(event.gid)
        if event.topic != main or event.kind not in _KIND or gid in own or event.local:
            continue
        item = record(gid, _KIND[event.kind])
        backends = advertisement.decode(event.user_data)
        item.update(advertisement='seen', buffer_aware=backends is not None,
                    legacy=backends is None, backends=dict(backends) if backends else None)
    for entity in probes:
        if isinstance(entity, Subscription):
            node.destroy_subscription(entity)
        else:
            node.destroy_publisher(entity)
    unknown = {gid for gid, e in endpoints.items() if e['advertisement'] == 'unknown'}
    if unknown and tapped:
        for event in _second_look(topic, unknown):
            gid = _gid_hex(event.gid)
            backends = advertisement.decode(event.user_data)
            endpoints[gid].update(advertisement='seen', buffer_aware=backends is not None,
                                  legacy=backends is None,
                                  backends=dict(backends) if backends else None)
    if any(e['advertisement'] == 'unknown' for e in endpoints.values()):
        notes.append('advertisement unknown: endpoint discovered before the discovery tap was '
                     'installed' + ('' if probe else '; run with --probe to make buffer-aware '
                                    'endpoints re-announce'))
    if not tapped:
        notes.append(f'rmw {rclpy.get_rmw_implementation_identifier()} is not '
                     'rmw_fastrtps_cpp: advertisements cannot be read')
    ordered = sorted(endpoints.values(), key=lambda e: (e['kind'], e['node_namespace'] or '',
                                                        e['node_name'] or '', e['gid']))
    for item in ordered:
        item['channels'] = []
    by_gid = {e['gid']: e for e in ordered}
    channels = _channels(topic, node, known)
    for channel in channels:
        for side in ('publisher_gid', 'subscription_gid'):
            if channel[side] in by_gid:
                by_gid[channel[side]]['channels'].append(channel['dds_topic'])
    types = sorted({e['topic_type'] for e in ordered if e['topic_type']})
    return {'topic': topic, 'types': types, 'wait_sec': wait, 'probe': probe,
            'publisher_count': sum(1 for e in ordered if e['kind'] == 'publisher'),
            'subscription_count': sum(1 for e in ordered if e['kind'] == 'subscription'),
            'endpoints': ordered, 'channels': channels, 'notes': notes}


def format_text(result: dict) -> str:
    """Human-readable output in the style of ``ros2 topic info -v``."""
    def transport(e):
        if e['advertisement'] == 'unknown':
            return 'unknown (advertisement not seen)'
        return 'buffer-aware' if e['buffer_aware'] else 'legacy'

    lines = [f"Topic: {result['topic']}",
             f"Type: {', '.join(result['types']) or '(unknown)'}", '']
    for kind, title in (('publisher', 'Publisher'), ('subscription', 'Subscription')):
        group = [e for e in result['endpoints'] if e['kind'] == kind]
        aware = sum(1 for e in group if e['buffer_aware'])
        legacy = sum(1 for e in group if e['legacy'])
        lines += [f'{title} count: {len(group)} ({aware} buffer-aware, {legacy} legacy, '
                  f'{len(group) - aware - legacy} unknown)', '']
        for e in group:
            lines.append(f"Node name: {e['node_name'] or '(not in the ROS graph yet)'}")
            lines.append(f"Node namespace: {e['node_namespace'] or '?'}")
            lines.append(f"Topic type: {e['topic_type'] or '?'}")
            lines.append(f'Endpoint type: {kind.upper()}')
            lines.append(f"GID: {e['gid']}")
            lines.append(f'Transport: {transport(e)}')
            if e['backends'] is not None:
                lines.append('Backends:')
                for name, metadata in e['backends'].items():
                    lines.append(f'  {name}' + (f': {metadata}' if metadata else ''))
            if e['channels']:
                lines.append('Channels:')
                lines += [f'  {c}' for c in e['channels']]
            if e['qos']:
                q = e['qos']
                lines.append('QoS profile:')
                lines.append(f"  Reliability: {q['reliability']}")
                lines.append(f"  History (Depth): {q['history']} ({q['depth']})")
                lines.append(f"  Durability: {q['durability']}")
            lines.append('')
    lines.append(f"Channels: {len(result['channels'])}")
    for c in result['channels']:
        ends = '+'.join(n for n, ok in (('writer', c['writer']), ('reader', c['reader'])) if ok)
        lines.append(f"  {c['publisher_gid']} -> {c['subscription_gid']} ({ends or 'none'})")
    for note in result['notes']:
        lines.append(f'Note: {note}')
    return '\n'.join(lines)


class _Parser(argparse.ArgumentParser):
    """argparse, with usage errors in one line (as the image nodes report bad parameters)."""

    def error(self, message: str):
        self.exit(2, f'{self.prog}: {message} (see --help)\n')


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog='buffer_topic_info',
        description='Show the publishers, subscriptions, buffer backends and descriptor '
                    'channels of a topic (like "ros2 topic info -v").')
    parser.add_argument('topic', help='topic name (relative names use the node namespace)')
    parser.add_argument('--wait', type=float, default=DEFAULT_WAIT_SECONDS, metavar='SECONDS',
                        help=f'how long to listen to discovery (default '
                             f'{DEFAULT_WAIT_SECONDS:g}; shorter may miss endpoints; up to '
                             f'{COMPLETION_GRACE_SECONDS:g} s more while the view is visibly '
                             'incomplete)')
    parser.add_argument('--probe', action='store_true',
                        help='create a temporary plain subscription and publisher on the topic '
                             'so that running buffer-aware endpoints re-announce their '
                             'backends (briefly disturbs the topic)')
    parser.add_argument('--json', action='store_true', help='print one JSON object')
    return parser


def main(argv=None) -> int:
    argv = list(sys.argv if argv is None else argv)
    options = _parser().parse_args(remove_ros_args(argv)[1:])
    if options.wait < 0:
        _parser().error(f'argument --wait: {options.wait:g} is not accepted; expected >= 0')
    native_stdout_to_stderr()  # Fast DDS's log lines are not this tool's output (--json)
    rclpy.init(args=argv)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM ends it like Ctrl-C
    node = None
    try:
        # a hidden node; the tap goes on its participant before anything else happens
        node = rclpy.create_node(
            f'_buffer_topic_info_{os.getpid()}', enable_rosout=False,
            start_parameter_services=False,
            parameter_overrides=[Parameter('start_type_description_service', value=False)])
        from rosidl_buffer_py import _dds, _native
        tapped = _dds.is_supported()
        if tapped:
            _native.install_discovery(node)
        topic = node.resolve_topic_name(options.topic)
        result = inspect_topic(node, topic, options.wait, options.probe, tapped)
    except KeyboardInterrupt:
        return 130
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if not result['endpoints']:
        print(f'buffer_topic_info: no publishers or subscriptions on {topic} '
              f'(listened for {options.wait:g} s'
              + (f'; a shorter --wait than {DEFAULT_WAIT_SECONDS:g} s may miss running ones'
                 if options.wait < DEFAULT_WAIT_SECONDS else '') + ')', file=sys.stderr)
        return 1
    if options.json:
        print(json.dumps(result, indent=2, sort_keys=True))
    else:
        print(format_text(result))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
