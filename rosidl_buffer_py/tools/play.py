"""buffer_play: publish a recorded MCAP bag, payloads in a buffer backend.

Like ``ros2 bag play``: every message of the selected topics is published at the time it was
recorded (log time), scaled by ``--rate``, with ``--loop`` to start over. Topics whose type has
a ``uint8[]`` payload get a buffer-aware publisher, and each message's payload is put into
memory of ``--backend`` (``demo`` by default where it is installed, else ``cpu``): the bytes
read from the file are copied once, straight into shared memory, and subscribers that accept the
backend get them zero-copy, so a perception pipeline can be replayed as it runs live. With
``--backend cpu`` (and for other types) the recorded CDR is published as it is.

Publishers offer the QoS the bag recorded for the topic (when its publishers agreed) with a
history of ``--qos-depth``. ``--wait-for-subscribers N`` starts only once every publisher has
``N`` subscriptions and every buffer-aware one among them is served on its channel.

Usage: ``buffer_play <bag> [--topics T ...] [--rate R] [--loop] [--backend NAME]
[--wait-for-subscribers N]``; also ``python -m rosidl_buffer_py.tools.play``.
"""
import argparse
import itertools
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import Dict, List, Optional

from rosidl_buffer_py import _dds, discovery
from rosidl_buffer_py.report import print_report
from rosidl_buffer_py.tools.bag import BagError, BagReader, qos_from_yaml
from rosidl_buffer_py.tools.message_definition import import_message_type
from rosidl_buffer_py.tools.native_output import native_stdout_to_stderr

__all__ = ['main']

#: --wait-for-subscribers: how long every subscription must look served before playback starts
#: (a subscription whose advertisement our tap missed announces it again 0.25 to 0.5 s after it
#: found us: see rosidl_buffer_py.reannounce).
SERVED_SETTLE_SECONDS = 1.0

EXIT_USAGE = 2


class UsageError(Exception):
    """A bad command line or bag; printed as one line, exit status 2."""


@dataclass
class _Output:
    """One played topic: its publisher and how its messages are published."""

    publisher: object
    msg_type: type
    buffer_aware: bool
    published: int = 0
    in_backend: int = 0
    #: How late publishing began against the message's recorded time (scaled by --rate):
    #: the topic's first message, and the worst one
    first_late_ms: Optional[float] = None
    max_late_ms: float = 0.0


def default_backend() -> str:
    from rosidl_buffer_py import get_installed_backends
    return 'demo' if 'demo' in get_installed_backends() else 'cpu'


def playback_qos(offered_yaml: str, depth: int):
    """rosbag2's rule: the recorded offer when every publisher made the same one (history
    aside), else the default profile; the history is always keep-last ``depth``."""
    from rclpy.qos import HistoryPolicy, QoSProfile
    try:
        offered = qos_from_yaml(offered_yaml)
    except ValueError:
        offered = []
    if offered and all((p.reliability, p.durability, p.deadline, p.liveliness,
                        p.liveliness_lease_duration) ==
                       (offered[0].reliability, offered[0].durability, offered[0].deadline,
                        offered[0].liveliness, offered[0].liveliness_lease_duration)
                       for p in offered):
        first = offered[0]
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                          reliability=first.reliability, durability=first.durability,
                          deadline=first.deadline, lifespan=first.lifespan,
                          liveliness=first.liveliness,
                          liveliness_lease_duration=first.liveliness_lease_duration)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='buffer_play',
        description='Publish a recorded MCAP bag; uint8[] payloads go into a buffer backend.')
    parser.add_argument('bag', help='bag directory or .mcap file')
    parser.add_argument('--topics', nargs='+', default=None, help='play only these topics')
    parser.add_argument('-r', '--rate', type=float, default=1.0,
                        help='playback speed factor (default 1.0)')
    parser.add_argument('-l', '--loop', action='store_true', help='play again and again')
    parser.add_argument('--backend', default=None,
                        help='backend for uint8[] payloads: demo (default where installed), '
                             'cpu, or any installed backend that can allocate')
    parser.add_argument('--qos-depth', type=int, default=10,
                        help='history depth of the publishers (default 10)')
    parser.add_argument('--wait-for-subscribers', type=int, default=0, metavar='N',
                        help='start once every publisher has N subscriptions')
    parser.add_argument('--wait-timeout', type=float, default=30.0,
                        help='seconds to wait for subscribers before giving up (default 30)')
    parser.add_argument('--linger', type=float, default=1.0,
                        help='after the last message, stay up to this many seconds while '
                             'subscribers remain (reliable delivery of the last messages)')
    return parser


def parse_args(argv: List[str]) -> argparse.Namespace:
    from rosidl_buffer_py import get_installed_backends
    args = build_parser().parse_args(argv)
    if args.rate <= 0:
        raise UsageError(f'--rate must be > 0, got {args.rate}')
    if args.qos_depth < 1:
        raise UsageError(f'--qos-depth must be >= 1, got {args.qos_depth}')
    if args.backend is None:
        args.backend = default_backend()
    installed = get_installed_backends()
    if args.backend != 'cpu' and args.backend not in installed:
        raise UsageError(f'--backend {args.backend!r} is not installed; installed: '
                         f'{", ".join(sorted(set(installed) | {"cpu"}))}')
    return args


def _select_topics(bag: BagReader, wanted: Optional[List[str]]) -> Dict[str, dict]:
    if wanted is None:
        return dict(bag.topics)
    names = [t if t.startswith('/') else '/' + t for t in wanted]
    unknown = [t for t in names if t not in bag.topics]
    if unknown:
        raise UsageError(f'topic {", ".join(unknown)} is not in {bag.path} (its topics: '
                         f'{", ".join(sorted(bag.topics)) or "none"})')
    return {name: bag.topics[name] for name in names}


class Player:
    """Publishers for the selected topics and the timed publishing loop."""

    def __init__(self, node, bag: BagReader, topics: Dict[str, dict],
                 args: argparse.Namespace, stop: threading.Event) -> None:
        import rosidl_buffer_py
        from rosidl_buffer_py import codec
        self.node = node
        self.bag = bag
        self.args = args
        self.stop = stop
        self.outputs: Dict[str, _Output] = {}
        self.backend = None if args.backend == 'cpu' else \
            rosidl_buffer_py.get_backend(args.backend)
        for name, entry in topics.items():
            try:
                msg_type = import_message_type(entry['type'])
            except ValueError as exc:
                if args.topics is not None:
                    raise UsageError(f'cannot play {name}: {exc}') from None
                node.get_logger().warning(f'skipping {name}: {exc}')
                continue
            qos = playback_qos(entry['offered_qos_profiles'], args.qos_depth)
            try:
                codec.payload_field(msg_type)
                publisher = rosidl_buffer_py.create_publisher(node, msg_type, name, qos)
                self.outputs[name] = _Output(publisher, msg_type, True)
            except codec.UnsupportedMessageTypeError:
                self.outputs[name] = _Output(node.create_publisher(msg_type, name, qos),
                                             msg_type, False)

    def _spin_until(self, executor, deadline: float) -> None:
        while not self.stop.is_set() and (remaining := deadline - time.monotonic()) > 0:
            executor.spin_once(timeout_sec=min(remaining, 0.1))

    def wait_for_subscribers(self, executor) -> None:
        needed = self.args.wait_for_subscribers
        if needed <= 0:
            return
        deadline = time.monotonic() + self.args.wait_timeout

        def missing() -> List[str]:
            lacking = []
            for name, output in self.outputs.items():
                publisher = output.publisher
                if publisher.get_subscription_count() < needed:
                    lacking.append(f'{name}: {publisher.get_subscription_count()} of {needed} '
                                   'subscriptions')
                elif output.buffer_aware and not all(
                        peer.channel_serving for peer in publisher.buffer_peers()):
                    lacking.append(f'{name}: a buffer-aware subscription not served yet')
            return lacking

        # a matched subscription's advertisement can reach us a moment after the match: what
        # is ready must stay so for SERVED_SETTLE_SECONDS (no buffer-aware peer appeared)
        ready_since = None
        while not self.stop.is_set():
            lacking = missing()
            now = time.monotonic()
            if lacking:
                ready_since = None
            elif ready_since is None:
                ready_since = now
            elif now - ready_since >= SERVED_SETTLE_SECONDS:
                return
            if now > deadline:
                raise TimeoutError(f'after {self.args.wait_timeout} s: '
                                   f'{"; ".join(lacking) or "subscriptions still changing"}')
            executor.spin_once(timeout_sec=0.05)

    def _publish(self, output: _Output, data: bytes) -> None:
        from rosidl_buffer_py import codec
        if output.buffer_aware and self.backend is not None:
            msg, payload = codec.split_payload(data, output.msg_type)
            if payload.nbytes:
                buffer = self.backend.allocate(payload.nbytes)
                memoryview(buffer)[:] = payload  # the one copy: file bytes -> backend memory
                setattr(msg, codec.payload_field(output.msg_type), buffer)
                output.in_backend += 1
            output.publisher.publish(msg)
        else:
            output.publisher.publish(data)  # recorded CDR, as it is
        output.published += 1

    def warm_up(self) -> None:
        """Do once, before the clock starts, what would otherwise delay each topic's first
        message: the backend's first allocation and the codec's per-type set-up."""
        from rosidl_buffer_py import codec
        if self.backend is not None:
            self.backend.allocate(1)
        for output in self.outputs.values():
            if output.buffer_aware:
                codec.payload_field(output.msg_type)

    def play(self, executor) -> None:
        """Publish the messages in log-time order, each at its recorded time: the clock starts
        when the first message is ready to go (read from the file, set-up done)."""
        topics = list(self.outputs)
        self.warm_up()
        while not self.stop.is_set():
            messages = self.bag.messages(topics)
            first = next(messages, None)
            if first is None:
                return  # nothing to play (or to loop over)
            first_log_time = first[1].log_time
            start = time.monotonic()
            for channel, message in itertools.chain([first], messages):
                if self.stop.is_set():
                    return
                due = start + (message.log_time - first_log_time) / 1e9 / self.args.rate
                self._spin_until(executor, due)
                if self.stop.is_set():
                    return
                output = self.outputs[channel.topic]
                late_ms = max(0.0, (time.monotonic() - due) * 1e3)
                if output.first_late_ms is None:
                    output.first_late_ms = round(late_ms, 2)
                output.max_late_ms = round(max(output.max_late_ms, late_ms), 2)
                self._publish(output, message.data)
            if not self.args.loop:
                return

    def linger(self, executor) -> None:
        deadline = time.monotonic() + self.args.linger
        while (not self.stop.is_set() and time.monotonic() < deadline and
               any(o.publisher.get_subscription_count() for o in self.outputs.values())):
            executor.spin_once(timeout_sec=0.05)


def main(argv: Optional[List[str]] = None) -> int:
    import faulthandler

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from rclpy.utilities import remove_ros_args

    argv = sys.argv if argv is None else ['buffer_play'] + list(argv)
    try:
        args = parse_args(remove_ros_args(argv)[1:])
        bag = BagReader(args.bag)
        topics = _select_topics(bag, args.topics)
    except (UsageError, BagError) as exc:
        print(f'buffer_play: error: {exc}', file=sys.stderr)
        return EXIT_USAGE

    native_stdout_to_stderr()  # Fast DDS's log lines are not this tool's output
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda signum, frame: stop.set())
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('buffer_play')
    if _dds.is_supported():
        # the discovery tap from the node's first moment, not from its first publisher's
        # (which comes after the message types are imported): subscriptions that its
        # participant discovers meanwhile show it their advertisements
        discovery.for_node(node)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    status = 0
    player = None
    started = time.monotonic()
    try:
        player = Player(node, bag, topics, args, stop)
        player.wait_for_subscribers(executor)
        player.play(executor)
        player.linger(executor)
    except UsageError as exc:
        print(f'buffer_play: error: {exc}', file=sys.stderr)
        status = EXIT_USAGE
    except (BagError, TimeoutError) as exc:
        print(f'buffer_play: error: {exc}', file=sys.stderr)
        status = 1
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if player is not None:
            print_report({
                'role': 'player', 'bag': str(bag.path), 'backend': args.backend,
                'seconds': round(time.monotonic() - started, 3),
                'topics': {name: {'published': o.published, 'in_backend': o.in_backend,
                                  'buffer_aware': o.buffer_aware,
                                  'first_late_ms': o.first_late_ms,
                                  'max_late_ms': o.max_late_ms}
                           for name, o in player.outputs.items()}})
        faulthandler.dump_traceback_later(20.0, exit=True)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        faulthandler.cancel_dump_traceback_later()
    return status


if __name__ == '__main__':
    raise SystemExit(main())
