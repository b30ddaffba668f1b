"""What this package's per-message Python costs above the bare descriptor path, at 1 KiB.

Three ways of sending one 1 KiB ``sensor_msgs/Image`` frame at ``--rate`` Hz between two
processes, interleaved round by round (the machine drifts within a run):

- ``stock rclpy``: a plain rclpy publisher and subscription;
- ``bare``: the descriptor path of the demo backend without anything of ours around it: the
  descriptor form written by the one native call the publisher makes
  (``_native.write_message`` with a slot program) on a channel DataWriter, a guard condition
  woken by the channel's DataReader in rclpy's executor, and the one native call that takes and
  decodes it (``ChannelSubscription.take_described``); no route, no pool, no endpoint
  bookkeeping (the 52 descriptor bytes name nothing, and nothing opens them);
- ``demo``: rosidl_buffer_py's endpoints with the demo backend, as users run them.

Each subscriber measures the frame's stamp (taken right before the publish) to its reception
by the DataReader, and from there to the callback. ``bare`` is the floor of the design (a DDS
topic per route, woken through a guard condition); ``demo`` minus ``bare`` is what our routes,
pool and endpoints cost per message.

With ``--opcodes`` it times nothing and counts instead: the Python opcodes each side runs per
message, by where their code lives (this package, rclpy, the generated message classes, Python's
library, this benchmark), one run per mode. A count does not drift with the machine: it shows
what a change of the per-message Python removes where timings at camera rates are too noisy to.
A benchmark: it prints, it asserts nothing.
``./dev bench bare [--frames 40] [--rate 10] [--rounds 3] [--opcodes]``
"""
import argparse
import collections
import contextlib
import json
import os
import statistics
import subprocess
import sys
import time
from typing import Any, Callable, Dict, Iterator, List, NamedTuple, Optional, Tuple

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image

from launch_free_demos.bench.hotpath import mono8_frame, stamp_split
from launch_free_demos.domains import claim_domain_ids

MODES = ('stock rclpy', 'bare', 'demo')
TOPIC = '/bench/bare'
WIDTH = 1024  #: one mono8 row: 1 KiB
#: Frames left out of each run's medians (the first after bring-up).
SKIP = 5
QOS = QoSProfile(depth=10)


def _image(stamp_ns: int, data) -> Image:
    return mono8_frame(WIDTH, stamp_ns, data)


# --- counting opcodes --------------------------------------------------------------------------

#: Where traced code lives, by a part of its file name (the first that matches), and the name
#: the table gives it; code found under none of them is Python's library.
ORIGINS = (
    (('/rosidl_buffer_py/', '/demo_buffer_backend/'), 'this package'),
    (('/rclpy/',), 'rclpy'),
    (('/msg/_',), 'generated message classes'),
    (('/launch_free_demos/',), 'this benchmark'),
)
LIBRARY = "Python's library"
#: The printed line that carries one side's counts from a process to the bench.
OPCODES_LINE = 'opcodes per message: '


class OpcodeCount:
    """Python opcodes run by this thread inside :meth:`tracing`, by origin (``ORIGINS``),
    over ``messages`` messages."""

    def __init__(self) -> None:
        self.by_origin: collections.Counter = collections.Counter()
        self.messages = 0
        self._origins: Dict[str, str] = {}

    def _origin(self, filename: str) -> str:
        origin = self._origins.get(filename)
        if origin is None:
            origin = self._origins[filename] = next(
                (name for parts, name in ORIGINS if any(p in filename for p in parts)), LIBRARY)
        return origin

    def _call(self, frame, event, arg):
        frame.f_trace_opcodes = True
        origin = self._origin(frame.f_code.co_filename)
        by_origin = self.by_origin

        def opcode(frame, event, arg):
            if event == 'opcode':
                by_origin[origin] += 1
            return opcode
        return opcode

    @contextlib.contextmanager
    def tracing(self) -> Iterator[None]:
        sys.settrace(self._call)
        try:
            yield
        finally:
            sys.settrace(None)

    def line(self) -> str:
        """Per message, by origin, as the printed line the bench reads back."""
        return OPCODES_LINE + json.dumps(
            {origin: count / max(self.messages, 1) for origin, count in self.by_origin.items()})


# --- the publisher process ---------------------------------------------------------------------

class Sender(NamedTuple):
    """One mode's publisher side: ``frame()`` makes a frame's payload before the wait (as a
    camera's frame is ready before the next tick: the publish then runs on cold caches, as
    in ``./dev bench hotpath``), ``send(payload)`` stamps and publishes it."""

    ready: Callable[[], bool]
    frame: Callable[[], Any]
    send: Callable[[Any], None]


def _stock_sender(node) -> Sender:
    pub = node.create_publisher(Image, TOPIC, QOS)
    return Sender(lambda: pub.get_subscription_count() > 0, lambda: bytes(WIDTH),
                  lambda payload: pub.publish(_image(time.time_ns(), payload)))


def _bare_sender(node) -> Sender:
    from rosidl_buffer_py import _dds, _native, codec
    channel = _dds.create_channel_publisher(node, Image, 'rt' + TOPIC, QOS)
    program = codec.descriptor_program(Image)

    def send(descriptor: bytes) -> None:
        stamp = time.time_ns()
        if not _native.write_message(_image(stamp, []), stamp, (channel,), program,
                                     descriptor=('demo', descriptor)):
            raise RuntimeError('the descriptor form of Image has no slot program here')
    # a demo descriptor's size (52 bytes); nothing opens it
    return Sender(lambda: channel.matched_count() > 0, lambda: bytes(52), send)


def _demo_sender(node) -> Sender:
    import rosidl_buffer_py
    from demo_buffer_backend import DemoBuffer
    pub = rosidl_buffer_py.create_publisher(node, Image, TOPIC, QOS)
    return Sender(lambda: any(peer.channel_serving for peer in pub.buffer_peers()),
                  lambda: DemoBuffer.allocate(WIDTH),
                  lambda payload: pub.publish(_image(time.time_ns(), payload)))


SENDERS = {'stock rclpy': _stock_sender, 'bare': _bare_sender, 'demo': _demo_sender}


def run_publisher(mode: str, frames: int, rate: float, count: Optional[OpcodeCount] = None
                  ) -> None:
    """With ``count``, the publishes after the first ``SKIP`` are counted, and printed."""
    rclpy.init()
    try:
        node = rclpy.create_node('bare_pub')
        sender = SENDERS[mode](node)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        deadline = time.monotonic() + 30.0
        while not sender.ready() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        time.sleep(0.5)
        for index in range(frames):
            payload = sender.frame()
            executor.spin_once(timeout_sec=0.0)
            time.sleep(1.0 / rate)
            if count is None or index < SKIP:
                sender.send(payload)
                continue
            with count.tracing():
                sender.send(payload)
            count.messages += 1
        if count is not None:
            print(count.line(), flush=True)
        time.sleep(1.0)
    finally:
        rclpy.try_shutdown()


# --- the subscriber process --------------------------------------------------------------------

def _bare_receiver(node, on_frame: Callable) -> None:
    from rosidl_buffer_py import _dds, codec
    reading = codec.descriptor_reading(Image)
    channels = []

    def on_wake() -> None:
        channel = channels[0]
        while channel.pending:
            taken = channel.take_described(*reading.args)
            if taken is None:
                return
            _, _, info, described = taken
            if described is not None:  # (only this bench's publisher writes there)
                on_frame(described[0], info)
    guard = node.create_guard_condition(on_wake)
    channels.append(_dds.create_channel_subscription(node, Image, 'rt' + TOPIC, QOS, guard))


def run_subscriber(mode: str, frames: int, rate: float, count: Optional[OpcodeCount] = None
                   ) -> List[Tuple[int, int]]:
    """Starts the publisher process; returns (stamp to reception, reception to callback) in
    ns per frame. With ``count``, the executor's turns that deliver frames after the first
    ``SKIP`` are counted (its other turns are not), and printed; the publisher counts too."""
    split: List[Tuple[int, int]] = []

    def on_frame(msg, info) -> None:
        split.append(stamp_split(msg, info, time.time_ns()))

    rclpy.init()
    publisher = None
    try:
        node = rclpy.create_node('bare_sub')
        if mode == 'stock rclpy':
            node.create_subscription(Image, TOPIC, on_frame, QOS)
        elif mode == 'bare':
            _bare_receiver(node, on_frame)
        else:
            import rosidl_buffer_py
            rosidl_buffer_py.create_subscription(node, Image, TOPIC, on_frame, QOS,
                                                 acceptable_buffer_backends='demo')
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        publisher = subprocess.Popen(_command('pub', mode, frames, rate, count is not None))
        deadline = time.monotonic() + frames / rate + 60.0
        while len(split) < frames and time.monotonic() < deadline:
            before = len(split)
            if count is None or before < SKIP:
                executor.spin_once(timeout_sec=0.25)
                continue
            counted = count.by_origin.copy()
            with count.tracing():
                executor.spin_once(timeout_sec=0.25)
            if len(split) == before:  # a turn that delivered nothing: not a message's cost
                count.by_origin = counted
            count.messages += len(split) - before
        publisher.wait(timeout=30.0)
        if count is not None:
            print(count.line(), flush=True)
    finally:
        if publisher is not None and publisher.poll() is None:
            publisher.kill()
            publisher.wait()
        rclpy.try_shutdown()
    return split


def _command(role: str, mode: str, frames: int, rate: float, opcodes: bool = False
             ) -> List[str]:
    return [sys.executable, '-m', 'launch_free_demos.bench.bare', '--role', role, '--mode', mode,
            '--frames', str(frames), '--rate', str(rate)] + (['--opcodes'] if opcodes else [])


# --- the bench -------------------------------------------------------------------------------

def measure(mode: str, frames: int, rate: float) -> Tuple[float, float]:
    """Medians (µs) of stamp -> reception and reception -> callback, over one run of ``mode``
    (its subscriber a process of its own, which starts the publisher's)."""
    completed = subprocess.run(_command('sub', mode, frames, rate), capture_output=True,
                               text=True, timeout=frames / rate + 120.0, env=dict(os.environ))
    lines = completed.stdout.strip().splitlines()
    if completed.returncode != 0 or not lines:
        raise RuntimeError(f'{mode}: the subscriber failed\n{completed.stdout}{completed.stderr}')
    split = json.loads(lines[-1])[SKIP:]
    if not split:
        raise RuntimeError(f'{mode}: no frame past the first {SKIP} arrived')
    return (statistics.median(a for a, _ in split) / 1e3,
            statistics.median(b for _, b in split) / 1e3)


class Opcodes(NamedTuple):
    """One mode's Python opcodes per message, by origin."""

    publisher: Dict[str, float]
    subscriber: Dict[str, float]


def count_opcodes(mode: str, frames: int, rate: float) -> Opcodes:
    """One run of ``mode`` with both processes counting (the publisher's line comes first:
    the subscriber prints once it has exited)."""
    completed = subprocess.run(_command('sub', mode, frames, rate, opcodes=True),
                               capture_output=True, text=True, timeout=frames / rate + 180.0,
                               env=dict(os.environ))
    counts = [json.loads(line[len(OPCODES_LINE):]) for line in completed.stdout.splitlines()
              if line.startswith(OPCODES_LINE)]
    if completed.returncode != 0 or len(counts) != 2:
        raise RuntimeError(f'{mode}: the counting run failed\n{completed.stdout}'
                           f'{completed.stderr}')
    return Opcodes(*counts)


def opcode_table(counts: Dict[str, Opcodes], frames: int, rate: float) -> str:
    origins = [name for _, name in ORIGINS] + [LIBRARY]
    lines = [f'Python opcodes per message, by where their code lives (1 KiB at {rate:g} Hz, '
             f'{frames - SKIP} messages counted per side; the subscriber\'s from the executor\'s '
             'wake-up to the callback\'s return).', '',
             '| | ' + ' | '.join(MODES) + ' |', '|---|' + '---|' * len(MODES)]
    for side in Opcodes._fields:
        for origin in origins + ['total']:
            cells = []
            for mode in MODES:
                by_origin = getattr(counts[mode], side)
                value = sum(by_origin.values()) if origin == 'total' else by_origin.get(origin, 0)
                cells.append(f'{value:.0f}')
            lines.append(f'| {side}: {origin} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def table(results: Dict[str, List[Tuple[float, float]]], frames: int, rate: float) -> str:
    rounds = len(results[MODES[0]])
    head = (f'One 1 KiB frame at {rate:g} Hz, publisher and subscriber in two processes; '
            f'medians of {frames - SKIP} frames per run, {rounds} round(s) interleaved, in µs.'
            '\n\n| | ' + ' | '.join(MODES) + ' |\n|---|' + '---|' * len(MODES) + '\n')
    rows = []
    for label, part in (('stamp -> reception (publisher, DDS)', lambda s: s[0]),
                        ('reception -> callback (subscriber)', lambda s: s[1]),
                        ('total', lambda s: s[0] + s[1])):
        cells = [f'{statistics.median(part(s) for s in results[mode]):.0f}' for mode in MODES]
        rows.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    totals = {mode: [a + b for a, b in results[mode]] for mode in MODES}
    ratios = ['\n| round | bare / stock rclpy | demo / stock rclpy | demo - bare (µs) |',
              '|---|---|---|---|']
    for index in range(rounds):
        stock, bare, demo = (totals[mode][index] for mode in MODES)
        ratios.append(f'| {index + 1} | {bare / stock:.2f} | {demo / stock:.2f} | '
                      f'{demo - bare:.0f} |')
    return head + '\n'.join(rows) + '\n' + '\n'.join(ratios)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--frames', type=int, default=40)
    parser.add_argument('--rate', type=float, default=10.0)
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--opcodes', action='store_true',
                        help='count the Python opcodes per message instead of timing (one run '
                             'per mode)')
    parser.add_argument('--role', choices=('pub', 'sub'), help=argparse.SUPPRESS)
    parser.add_argument('--mode', choices=MODES, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.frames <= SKIP:
        parser.error(f'--frames must be more than {SKIP} (the first {SKIP} are left out), '
                     f'got {args.frames}')
    count = OpcodeCount() if args.opcodes else None
    if args.role == 'pub':
        run_publisher(args.mode, args.frames, args.rate, count)
        return 0
    if args.role == 'sub':
        print(json.dumps(run_subscriber(args.mode, args.frames, args.rate, count)))
        return 0
    os.environ['ROS_DOMAIN_ID'] = str(claim_domain_ids(1)[0])  # the processes inherit it
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if args.opcodes:
        counts = {}
        for mode in MODES:
            counts[mode] = count_opcodes(mode, args.frames, args.rate)
            print(f'{mode}: counted', flush=True)
        print()
        print(opcode_table(counts, args.frames, args.rate))
        return 0
    results: Dict[str, List[Tuple[float, float]]] = {mode: [] for mode in MODES}
    for index in range(args.rounds):
        for mode in MODES:
            results[mode].append(measure(mode, args.frames, args.rate))
            print(f'round {index + 1}, {mode}: {sum(results[mode][-1]):.0f} µs', flush=True)
    print()
    print(table(results, args.frames, args.rate))
    return 0


if __name__ == '__main__':
    sys.exit(main())
