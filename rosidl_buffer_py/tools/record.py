"""buffer_record: record topics into an MCAP bag, zero-copy for buffer-backed payloads.

Like ``ros2 bag record -s mcap`` (rosbag2 is not installable from PyPI for Jazzy): the bag is a
directory with ``<name>_0.mcap``, ``<name>_1.mcap``, ... and ``metadata.yaml``
(:mod:`.bag`). What is written for a message is its legacy CDR: ``serialize_message`` of the
CPU equivalent, whatever backend carried it, with the alignment padding written as zeros
(``serialize_message`` leaves those few bytes uninitialized).

Topics whose type has a ``uint8[]`` payload are taken with a buffer-aware subscription that
accepts every installed backend (``acceptable_buffer_backends='any'``). A buffer-aware
publisher then serves the recorder on its own channel, with a descriptor for shared-memory
frames: no CPU copy on the main topic. The recorder writes the message's small fields, the
payload's length, the payload straight from the shared-memory view and the trailing fields
(:func:`rosidl_buffer_py.codec.encode_parts`; large frames with ``O_DIRECT``, see
:mod:`.bag`): the payload is never copied into a Python object. Other types are taken as
serialized bytes by a plain rclpy subscription and written as they came.

A topic is subscribed as soon as DDS discovery reports a writer of it: this package's
discovery tap (:mod:`.discovery`) triggers a guard condition that wakes the executor, no poll
(a poll of the ROS graph remains where the tap is unavailable). The subscription is created
before the type's definition is read, so that DDS matches it sooner.

Messages are handed from the executor to one writer thread through a queue bounded by
``--max-cache-size`` bytes; a message that does not fit is dropped and counted. The files stay
readable after a crash or SIGKILL once ``buffer_bag_reindex`` (:mod:`.reindex`) finished them
(see :mod:`.bag`: chunks written within a second). SIGINT (Ctrl-C) and SIGTERM stop taking
messages, write what is queued, finish the file and print a summary; a full disk stops the
recording and finishes the file after its last complete chunk.

Usage: ``buffer_record [topics ...] [--all] [-o DIR] [--duration S] [--max-bag-size BYTES]
[--qos-reliability ...] [--qos-durability ...] [--qos-depth N]
[--qos-profile-overrides-path YAML]``; also ``python -m rosidl_buffer_py.tools.record``.
"""
import argparse
import collections
import datetime
import re
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import yaml

from rosidl_buffer_py import _dds, discovery
from rosidl_buffer_py.report import print_report
from rosidl_buffer_py.tools.bag import (
    FLUSH_PERIOD_SEC, BagError, BagWriter, Topic, format_size, qos_from_dict)
from rosidl_buffer_py.tools.message_definition import (
    full_definition, import_message_type, DefinitionNotFoundError)
from rosidl_buffer_py.tools.native_output import native_stdout_to_stderr

__all__ = ['main']

#: Where the discovery tap is unavailable (an rmw_fastrtps the native extension was not built
#: against), how often the ROS graph is polled for topics to record instead.
DISCOVERY_PERIOD_SEC = 0.5
#: A writer the tap reported but the ROS graph does not list yet is looked up again this soon.
GRAPH_RETRY_SEC = 0.01
#: ... at most this many times in a row (a DDS writer that never becomes a ROS topic).
GRAPH_RETRIES = 200
#: rosbag2's default --max-cache-size.
DEFAULT_MAX_CACHE_SIZE = 100 * 1024 * 1024
#: Stop waiting for the writer thread after this long once stopped (it then gets reported).
DRAIN_TIMEOUT_SEC = 120.0
EXIT_USAGE = 2


class UsageError(Exception):
    """A bad command line or input; printed as one line, exit status 2."""


@dataclass
class TopicStats:
    """What the recorder did with one topic."""

    type: str
    buffer_aware: bool
    received: int = 0
    written: int = 0
    zero_copy: int = 0
    dropped: int = 0
    bytes: int = 0
    backends: Dict[str, int] = field(default_factory=dict)
    #: From the first sign of a writer of the topic (the tap's discovery event, or the graph
    #: listing it an instant before) to its subscription (None when the topic was found by
    #: polling the graph, without the tap)
    subscribe_delay_ms: Optional[float] = None


# --- the writer thread --------------------------------------------------------------------------

class _WriteQueue:
    """Messages waiting for the writer thread, bounded by their total size in bytes."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.items = collections.deque()
        self.nbytes = 0
        self.closed = False
        self.condition = threading.Condition()

    def put(self, item, nbytes: int) -> bool:
        with self.condition:
            # one message always fits, so a frame larger than the cache is still recorded
            if self.items and self.nbytes + nbytes > self.max_bytes:
                return False
            self.items.append((item, nbytes))
            self.nbytes += nbytes
            self.condition.notify()
            return True

    def get(self, timeout: float):
        """The next item; :data:`IDLE` when none came within ``timeout`` seconds; None once
        closed and empty."""
        with self.condition:
            if not self.items and not self.closed:
                self.condition.wait(timeout)
            if not self.items:
                return None if self.closed else IDLE
            item, nbytes = self.items.popleft()
            self.nbytes -= nbytes
            return item

    def close(self) -> None:
        with self.condition:
            self.closed = True
            self.condition.notify_all()


#: What :meth:`_WriteQueue.get` returns when nothing came in time.
IDLE = object()


def _writer_loop(bag: BagWriter, queue: _WriteQueue, stats: Dict[str, TopicStats],
                 errors: List[str], stop: threading.Event) -> None:
    """Write queued messages; every FLUSH_PERIOD_SEC at most, let the bag write its waiting
    chunk and fdatasync (crash safety), busy or idle."""
    try:
        while True:
            item = queue.get(FLUSH_PERIOD_SEC / 4)
            bag.tick()
            if item is None:
                return
            if item is IDLE:
                continue
            topic, log_time, publish_time, parts, _keepalive = item
            size = bag.write(topic, log_time, publish_time, parts)
            entry = stats[topic]
            entry.written += 1
            entry.bytes += size
            del item, parts, _keepalive  # release the shared-memory view now
    except Exception as exc:  # disk full, I/O error: stop the recording, report it
        errors.append(f'writing the bag failed: {type(exc).__name__}: {exc}')
        bag.failed = True
        stop.set()
        with queue.condition:
            queue.items.clear()
            queue.nbytes = 0


# --- the recorder node ---------------------------------------------------------------------------

def _ros_topic_name(dds_topic: str) -> Optional[str]:
    """The ROS topic of a DDS topic name ('rt/camera/image' -> '/camera/image'); None for
    services, actions' internals and other non-topic names."""
    return '/' + dds_topic[3:] if dds_topic.startswith('rt/') else None


class Recorder:
    """Subscribe to the selected topics as they appear and queue their messages for writing."""

    def __init__(self, node, bag: BagWriter, args: argparse.Namespace,
                 queue: _WriteQueue) -> None:
        from rclpy.expand_topic_name import expand_topic_name
        self.node = node
        self.bag = bag
        self.args = args
        self.queue = queue
        self.stats: Dict[str, TopicStats] = {}
        self.subscriptions = {}
        self.skipped: Dict[str, str] = {}
        self.wanted = {expand_topic_name(t, node.get_name(), node.get_namespace())
                       for t in args.topics}
        self.exclude = re.compile(args.exclude_regex) if args.exclude_regex else None
        self.overrides = args.qos_overrides
        self.timer = None   # the graph poll, where the discovery tap is unavailable
        self.retry = None   # a one-shot look at the graph for a writer it does not list yet
        self.retries = 0
        self.first_seen: Dict[str, float] = {}  # topic -> when a writer was first seen
        self.discovery = None
        if _dds.is_supported():
            # subscribe the moment discovery reports a writer: the tap wakes the executor
            self.discovery = discovery.for_node(node)
            self.wakeup = node.create_guard_condition(self._on_discovery_event)
            self.discovery.add_wakeup(node, self.wakeup)
        else:
            self.timer = node.create_timer(DISCOVERY_PERIOD_SEC, self.discover)

    def close(self) -> None:
        """Stop discovering (before the subscriptions are destroyed)."""
        for timer in (self.timer, self.retry):
            if timer is not None:
                timer.cancel()
        if self.discovery is not None:
            self.discovery.remove_wakeup(self.wakeup)

    def _on_discovery_event(self) -> None:
        self.discovery.process()  # also what buffer-aware subscriptions wait for
        self.discover()

    def _selected(self, name: str) -> bool:
        from rclpy.topic_or_service_is_hidden import topic_or_service_is_hidden
        if '/_buf/' in name + '/':
            return False  # this package's per-endpoint channels, never a user topic
        if self.exclude is not None and self.exclude.search(name):
            return False
        if name in self.wanted:
            return True
        if not self.args.all:
            return False
        return self.args.include_hidden_topics or not topic_or_service_is_hidden(name)

    def discover(self) -> None:
        """Subscribe to every selected topic that has a publisher and no subscription yet.

        The tap reports a writer from the DDS discovery thread, perhaps before rmw's graph cache
        lists it (its QoS comes from there): such a topic is looked up again shortly.
        """
        graph = self.node.get_topic_names_and_types()
        writers = set() if self.discovery is None else {
            _ros_topic_name(t) for t in self.discovery.remote_writers()}
        now = time.monotonic()
        for name in writers:
            self.first_seen.setdefault(name, now)
        # a writer the tap knows and the graph does not list yet (or without its QoS)
        listed = {name for name, _ in graph}
        unlisted = any(name is not None and name not in listed and self._wanted(name)
                       for name in writers)
        for name, types in graph:
            if not self._wanted(name):
                continue
            if not self.node.get_publishers_info_by_topic(name):
                unlisted |= name in writers
                continue  # no publisher: nothing to record yet, nor a QoS to match
            if self.discovery is not None:
                # the tap forwards each discovery callback to rmw's graph before it records
                # the event: the graph may list a writer an instant before the tap reports it
                self.first_seen.setdefault(name, now)
            if len(types) > 1:
                self.node.get_logger().warning(
                    f'{name} has more than one type ({", ".join(types)}); recording {types[0]}')
            try:
                self._subscribe(name, types[0])
            except (ValueError, TypeError, DefinitionNotFoundError, RecursionError) as exc:
                self.skipped[name] = str(exc)
                self.node.get_logger().error(f'not recording {name}: {exc}')
        if not unlisted:
            self.retries = 0
        elif self.retry is None and self.retries < GRAPH_RETRIES:
            self.retries += 1
            self.retry = self.node.create_timer(GRAPH_RETRY_SEC, self._retry)

    def _wanted(self, name: str) -> bool:
        return name not in self.subscriptions and name not in self.skipped and \
            self._selected(name)

    def _retry(self) -> None:
        self.node.destroy_timer(self.retry)
        self.retry = None
        self.discover()

    def _qos(self, name: str, offered):
        """rosbag2's rule: reliable / transient local only if every publisher offers it."""
        from rclpy.qos import (
            DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
        if name in self.overrides:
            return self.overrides[name]
        reliable = bool(offered) and all(
            p.reliability == ReliabilityPolicy.RELIABLE for p in offered)
        transient = bool(offered) and all(
            p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in offered)
        if self.args.qos_reliability:
            reliable = self.args.qos_reliability == 'reliable'
        if self.args.qos_durability:
            transient = self.args.qos_durability == 'transient_local'
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=self.args.qos_depth,
            reliability=ReliabilityPolicy.RELIABLE if reliable else
            ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else
            DurabilityPolicy.VOLATILE)

    def _subscribe(self, name: str, type_name: str) -> None:
        import rosidl_buffer_py
        from rosidl_buffer_py import codec
        msg_type = import_message_type(type_name)
        infos = self.node.get_publishers_info_by_topic(name)
        offered = [info.qos_profile for info in infos]
        hashes = {str(info.topic_type_hash) for info in infos} - {'INVALID'}
        qos = self._qos(name, offered)
        try:
            codec.payload_field(msg_type)
            buffer_aware = True
        except codec.UnsupportedMessageTypeError:
            buffer_aware = False
        self.stats[name] = TopicStats(type_name, buffer_aware)
        if name in self.first_seen:
            self.stats[name].subscribe_delay_ms = round(
                (time.monotonic() - self.first_seen[name]) * 1e3, 1)
        # The subscription first: DDS matches it (and its history fills) while the type's
        # definition is read, which takes tens of ms. No callback runs before this method
        # returns (it runs in the executor), so the channel is in the bag before any message.
        if buffer_aware:
            subscription = rosidl_buffer_py.create_subscription(
                self.node, msg_type, name, self._buffer_callback(name), qos,
                acceptable_buffer_backends='any')
        else:
            subscription = self.node.create_subscription(
                msg_type, name, self._raw_callback(name), qos, raw=True)
        try:
            self.bag.add_topic(Topic(name, type_name, full_definition(type_name), offered,
                                     sorted(hashes)[0] if hashes else ''))
        except Exception:
            if buffer_aware:
                subscription.destroy()
            else:
                self.node.destroy_subscription(subscription)
            del self.stats[name]
            raise
        self.subscriptions[name] = subscription
        print(f'buffer_record: recording {name} ({type_name}, '
              f'{"buffer-aware" if buffer_aware else "serialized"})', flush=True)

    def _enqueue(self, name: str, publish_time: int, parts, keepalive, nbytes: int,
                 log_time: int) -> None:
        entry = self.stats[name]
        entry.received += 1
        if not self.queue.put((name, log_time, publish_time or log_time, parts, keepalive),
                              nbytes):
            entry.dropped += 1

    def _buffer_callback(self, name: str):
        from rosidl_buffer_py import Buffer, codec
        stats = self.stats[name]

        def on_message(msg, info) -> None:
            log_time = time.time_ns()
            parts = codec.encode_parts(msg)  # the payload stays where it is (shared memory)
            payload = getattr(msg, codec.payload_field(type(msg)))
            if isinstance(payload, Buffer) and not payload.is_cpu:
                stats.backends[payload.backend_type] = \
                    stats.backends.get(payload.backend_type, 0) + 1
                if payload.host_addressable:
                    stats.zero_copy += 1
            else:
                stats.backends['cpu'] = stats.backends.get('cpu', 0) + 1
            self._enqueue(name, info.get('source_timestamp', 0), parts, msg, parts.nbytes,
                          log_time)
        return on_message

    def _raw_callback(self, name: str):
        def on_message(data: bytes, info) -> None:
            log_time = time.time_ns()
            self._enqueue(name, info.get('source_timestamp', 0), (data,), None, len(data),
                          log_time)
        return on_message


# --- command line --------------------------------------------------------------------------------

def _size(text: str) -> int:
    match = re.fullmatch(r'\s*(\d+)\s*([kKmMgG]i?[bB]?|[bB])?\s*', text)
    if not match:
        raise argparse.ArgumentTypeError(
            f'{text!r} is not a size; use bytes, or a number with K, M or G (e.g. 500M)')
    unit = (match.group(2) or 'b')[0].lower()
    return int(match.group(1)) * {'b': 1, 'k': 1024, 'm': 1024 ** 2, 'g': 1024 ** 3}[unit]


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f'must be > 0, got {text}')
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='buffer_record',
        description='Record topics into an MCAP bag (rosbag2 layout and profile); payloads in '
                    'shared memory are written without copies.')
    parser.add_argument('topics', nargs='*', help='topics to record (they may appear later)')
    parser.add_argument('-a', '--all', action='store_true',
                        help='record every topic (hidden ones only with '
                             '--include-hidden-topics; never /_buf/ channels)')
    parser.add_argument('--include-hidden-topics', action='store_true')
    parser.add_argument('-x', '--exclude-regex', default='',
                        help='do not record topics matching this regular expression')
    parser.add_argument('-o', '--output', default='',
                        help='bag directory (default rosbag2_YYYY_MM_DD-HH_MM_SS); must not '
                             'exist')
    parser.add_argument('-d', '--duration', type=_positive, default=None,
                        help='stop after this many seconds')
    parser.add_argument('-b', '--max-bag-size', type=_size, default=0,
                        help='start a new file once one holds this many bytes (e.g. 1G); '
                             '0: no splitting')
    parser.add_argument('--max-bag-duration', type=_positive, default=None,
                        help='start a new file every this many seconds')
    parser.add_argument('--max-cache-size', type=_size, default=DEFAULT_MAX_CACHE_SIZE,
                        help='bytes of messages waiting for the disk before new ones are '
                             'dropped (default 100M)')
    parser.add_argument('--qos-reliability', choices=('reliable', 'best_effort'),
                        help='subscribe with this reliability (default: reliable if every '
                             'publisher offers it, as rosbag2)')
    parser.add_argument('--qos-durability', choices=('volatile', 'transient_local'),
                        help='subscribe with this durability (default: transient_local if '
                             'every publisher offers it)')
    parser.add_argument('--qos-depth', type=int, default=10, help='history depth (default 10)')
    parser.add_argument('--qos-profile-overrides-path', default='',
                        help="YAML mapping topic -> QoS profile, as rosbag2's option")
    return parser


def _load_overrides(path: str) -> dict:
    if not path:
        return {}
    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise UsageError(f'--qos-profile-overrides-path {path}: {exc.strerror}') from None
    except yaml.YAMLError as exc:
        raise UsageError(f'--qos-profile-overrides-path {path}: not YAML: {exc}') from None
    if not isinstance(data, dict):
        raise UsageError(f'--qos-profile-overrides-path {path}: expected a mapping topic -> '
                         'profile')
    try:
        return {topic: qos_from_dict(profile) for topic, profile in data.items()}
    except (ValueError, TypeError) as exc:
        raise UsageError(f'--qos-profile-overrides-path {path}: {exc}') from None


def parse_args(argv: List[str]) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.topics and not args.all:
        raise UsageError('name topics to record, or --all')
    if args.qos_depth < 1:
        raise UsageError(f'--qos-depth must be >= 1, got {args.qos_depth}')
    if args.exclude_regex:
        try:
            re.compile(args.exclude_regex)
        except re.error as exc:
            raise UsageError(f'--exclude-regex {args.exclude_regex!r}: {exc}') from None
    args.qos_overrides = _load_overrides(args.qos_profile_overrides_path)
    if not args.output:
        args.output = datetime.datetime.now().strftime('rosbag2_%Y_%m_%d-%H_%M_%S')
    return args


def print_summary(bag: BagWriter, stats: Dict[str, TopicStats], seconds: float,
                  errors: List[str]) -> None:
    """The table a user reads, then one JSON line for scripts."""
    files = bag.file_paths
    for name, entry in stats.items():  # what is in the finished files, not what was queued
        entry.written = bag.topic_counts.get(name, 0)
    print(f'buffer_record: wrote {bag.directory} ({len(files)} file'
          f'{"s" if len(files) != 1 else ""}, {format_size(bag.size)}) in {seconds:.1f} s')
    # messages: in the finished files; received, zero-copy (of those received), dropped (no
    # room in --max-cache-size): what the subscriptions delivered
    rows = [('topic', 'type', 'messages', 'received', 'zero-copy', 'dropped', 'bytes')]
    for name, entry in sorted(stats.items()):
        rows.append((name, entry.type, str(entry.written), str(entry.received),
                     str(entry.zero_copy), str(entry.dropped), format_size(entry.bytes)))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for index, row in enumerate(rows):
        print('| ' + ' | '.join(cell.ljust(w) for cell, w in zip(row, widths)) + ' |')
        if index == 0:
            print('|' + '|'.join('-' * (w + 2) for w in widths) + '|')
    print_report({
        'role': 'recorder', 'output': str(bag.directory), 'files': [str(f) for f in files],
        'seconds': round(seconds, 3), 'errors': errors,
        'topics': {name: vars(entry) for name, entry in stats.items()}})


def main(argv: Optional[List[str]] = None) -> int:
    import faulthandler

    import rclpy
    import rclpy.subscription
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from rclpy.utilities import remove_ros_args

    argv = sys.argv if argv is None else ['buffer_record'] + list(argv)
    try:
        args = parse_args(remove_ros_args(argv)[1:])
        bag = BagWriter(Path(args.output), max_bag_size=args.max_bag_size,
                        max_bag_duration_ns=int((args.max_bag_duration or 0) * 1e9),
                        library='rosidl_buffer_py buffer_record')
    except (UsageError, BagError) as exc:
        print(f'buffer_record: error: {exc}', file=sys.stderr)
        return EXIT_USAGE

    native_stdout_to_stderr()  # Fast DDS's log lines are not this tool's output
    stop = threading.Event()

    def on_signal(signum, frame) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    queue = _WriteQueue(args.max_cache_size)
    errors: List[str] = []
    node = rclpy.create_node('buffer_record')
    recorder = Recorder(node, bag, args, queue)
    writer = threading.Thread(target=_writer_loop, name='bag_writer',
                              args=(bag, queue, recorder.stats, errors, stop), daemon=True)
    writer.start()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    started = time.monotonic()
    deadline = started + args.duration if args.duration else None
    recorder.discover()
    try:
        while not stop.is_set():
            timeout = 0.1 if deadline is None else max(0.0, min(0.1, deadline - time.monotonic()))
            executor.spin_once(timeout_sec=timeout)
            if deadline is not None and time.monotonic() >= deadline:
                break
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        recorder.close()
        for subscription in recorder.subscriptions.values():  # take nothing more
            if isinstance(subscription, rclpy.subscription.Subscription):
                node.destroy_subscription(subscription)
            else:
                subscription.destroy()
        queue.close()
        writer.join(DRAIN_TIMEOUT_SEC)
        if writer.is_alive():
            errors.append(f'the writer thread did not finish within {DRAIN_TIMEOUT_SEC} s')
        else:
            try:
                bag.close(failed=bag.failed)
            except (OSError, BagError) as exc:
                errors.append(f'finishing the bag failed: {exc}')
        print_summary(bag, recorder.stats, time.monotonic() - started, errors)
        for error in errors:
            print(f'buffer_record: error: {error}', file=sys.stderr)
        # Fast DDS 2.14 can spin in participant teardown (see nodes/common.py): the bag is
        # complete by now, so end the process if that happens.
        faulthandler.dump_traceback_later(20.0, exit=True)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        faulthandler.cancel_dump_traceback_later()
    return 1 if errors else 0


if __name__ == '__main__':
    raise SystemExit(main())
