"""Where one message's time goes on the hot path, stage by stage, at camera rates.

For stock rclpy, this package's CPU path and the demo backend, a publisher and a subscriber run in
two processes and exchange ``--frames`` frames at ``--rate`` Hz: every message wakes a node that
was idle, its caches cold, as a camera's frames find it. Each transport runs twice, once with
the publisher in this process and once with the subscriber here; the side in this process has
the stages of its hot path timed (``perf_counter_ns`` around the named functions, about a
microsecond each). Prints:

- the latency split at the DDS timestamps: from the frame's stamp (taken right before
  ``publish()``) to its reception by the subscriber's DataReader (the publisher's work and DDS),
  and from there to the start of the callback (the subscriber's wake-up, take and delivery);
- every timed stage's time per message (its total over the run / the messages), from the
  moment the route is up (the publisher once its subscriber is served, the subscriber from its
  10th message: a route's bring-up probes are no per-message cost);
- one native call of the publish path timed back to back and after ``--rate``'s idle time: the
  factor by which this machine's cold caches multiply everything above.

With ``--rounds N`` the transports run N times, interleaved round by round: the latency cells
are medians over the rounds, the stages' means are over all of them, and the totals' ratios to
stock's are printed round by round (issue #30's hotpath target: demo / stock at most 1.15).

A benchmark: it prints and asserts nothing.
``./dev bench hotpath [--frames 60] [--rate 10] [--rounds 1]``
"""
import argparse
import functools
import os
import statistics
import sys
import time
from collections import defaultdict
from typing import Callable, Dict, List, Optional, Tuple

import rclpy
import rclpy.publisher
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image

import rosidl_buffer_py
from demo_buffer_backend import DemoBuffer, backend as demo_backend, links, mappings
from launch_free_demos.bench.stats import per_round_line
from launch_free_demos.domains import claim_domain_ids
from launch_free_demos.runner import Run
from rosidl_buffer_py import codec, publisher, routes, subscription

#: Frames left out of the latency medians (the first after bring-up); calls left out of the
#: warm and cold medians.
SKIP = 5
#: The subscriber's stages are timed from this message on (at most half the frames): by then
#: its route is up, and the bring-up's probes on the channel are no per-message cost.
STAGES_FROM = 10
TOPIC = '/bench/hotpath'
TRANSPORTS = ('stock rclpy', 'cpu', 'demo')


class Stages:
    """Timers around functions: ``wrap(owner, name)`` records the duration of every call."""

    def __init__(self) -> None:
        self.samples: Dict[str, List[int]] = defaultdict(list)
        self._undo: List[Tuple[object, str, Callable]] = []

    def wrap(self, owner, name: str, label: str) -> None:
        original = getattr(owner, name)
        samples = self.samples[label]

        @functools.wraps(original)
        def timed(*args, **kwargs):
            started = time.perf_counter_ns()
            try:
                return original(*args, **kwargs)
            finally:
                samples.append(time.perf_counter_ns() - started)

        setattr(owner, name, timed)
        self._undo.append((owner, name, original))

    def restore(self) -> None:
        for owner, name, original in reversed(self._undo):
            setattr(owner, name, original)
        self._undo.clear()

    def per_message_us(self, messages: int) -> Dict[str, Tuple[float, int]]:
        """Per stage: its total time over the run / ``messages``, in µs, and its call count
        (a take that finds nothing is a call too: a median per call would hide the others)."""
        return {label: (sum(v) / messages / 1e3, len(v))
                for label, v in self.samples.items() if v}


def _publisher_stages(stages: Stages, transport: str) -> None:
    if transport == 'stock rclpy':
        stages.wrap(rclpy.publisher.Publisher, 'publish', 'publish()')
        return
    stages.wrap(publisher.Publisher, 'publish', 'publish()')
    stages.wrap(publisher.Publisher, '_publish_steady',
                '  steady lane (its prepared writes; declined calls and re-plans too)')
    stages.wrap(publisher.Publisher, '_write', '  writes (descriptor or CPU message)')
    stages.wrap(routes.RouteTable, 'dispatch', '  route dispatch (plan cached while current)')
    if transport == 'demo':
        stages.wrap(publisher.Publisher, '_describe', '    backend describe (demo ledger)')
        stages.wrap(links.Links, 'drain', '      acks and hang-ups from the peer')
        stages.wrap(publisher._Encoder, 'write_described',
                    '    descriptor message write (encoded in the DDS write\'s call)')


def _subscriber_stages(stages: Stages, transport: str) -> None:
    if transport == 'stock rclpy':
        return  # rclpy's take and conversion are one C call
    # (the channel's guard condition holds the bound _deliver_available: _next is timed)
    stages.wrap(subscription.Subscription, '_next', 'delivery path: take to message')
    stages.wrap(subscription.Subscription, '_steady_step',
                '  steady step (the one channel\'s take, decoded in C; empty ones too)')
    stages.wrap(subscription._PublisherPeer, 'take',
                '  channel takes (empty ones too; descriptor messages decoded in them)')
    if transport == 'demo':
        # (a steady step opens through the backend's steady opener, the general path through
        # from_descriptor_with_endpoint: both run the pool's native open, timed alone)
        stages.wrap(demo_backend.DemoBackend, 'from_descriptor_with_endpoint',
                    '  backend open, general path (demo pool)')
        stages.wrap(mappings.Mappings, 'take_steady',
                    '  native open, either path: segment checks and hold lock')
    stages.wrap(subscription.Subscription, '_call', 'the callback (this benchmark\'s)')


def mono8_frame(width: int, stamp_ns: int, data) -> Image:
    """A one-row mono8 Image of ``data`` stamped ``stamp_ns`` (this benchmark's frame, and
    ``./dev bench bare``'s)."""
    msg = Image()
    msg.width, msg.height, msg.encoding, msg.step = width, 1, 'mono8', width
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    msg.data = data
    return msg


def stamp_split(msg, info: dict, now_ns: int) -> Tuple[int, int]:
    """A frame's (stamp to its reception by the DataReader, reception to ``now_ns``) in ns."""
    stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    return info['received_timestamp'] - stamp, now_ns - info['received_timestamp']


def run_publisher_here(transport: str, width: int, frames: int, rate: float,
                       stages: Stages) -> None:
    """This process publishes ``frames`` frames; a subscriber process takes them."""
    context = rclpy.Context()
    rclpy.init(context=context)
    sub_exe, params = (('legacy_image_subscriber', {}) if transport == 'stock rclpy' else
                       ('image_subscriber', {'acceptable_buffer_backends': transport}))
    try:
        node = rclpy.create_node('hotpath_pub', context=context)
        if transport == 'stock rclpy':
            pub = node.create_publisher(Image, TOPIC, QoSProfile(depth=10))
        else:
            pub = rosidl_buffer_py.create_publisher(node, Image, TOPIC,
                                                    QoSProfile(depth=10))
        backend = rosidl_buffer_py.get_installed_backends()['demo'] if transport == 'demo' \
            else None
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        with Run() as run:
            run.start('hotpath_sub', sub_exe, topic=TOPIC, timeout_sec=frames / rate + 60.0,
                      report_period_sec=0.0, **params)
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline and not _ready(pub, transport):
                executor.spin_once(timeout_sec=0.05)
            time.sleep(0.5)
            _publisher_stages(stages, transport)
            try:
                for _ in range(frames):
                    data = backend.allocate(width) if backend else bytes(width)
                    executor.spin_once(timeout_sec=0.0)
                    time.sleep(1.0 / rate)
                    pub.publish(mono8_frame(width, time.time_ns(), data))
            finally:
                stages.restore()
            time.sleep(0.5)
            run.stop_all()
        executor.shutdown()
        # gone from DDS before the next run's subscriber starts in this process: a context's
        # shutdown leaves its nodes (and their publishers) alive until they are collected
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def _ready(pub, transport: str) -> bool:
    if transport == 'stock rclpy':
        return pub.get_subscription_count() > 0
    return any(peer.channel_serving for peer in pub.buffer_peers())


def run_subscriber_here(transport: str, width: int, frames: int, rate: float,
                        stages: Stages) -> List[Tuple[int, int]]:
    """A publisher process sends ``frames`` frames; this process takes them. Returns, per frame,
    (stamp to reception, reception to callback) in ns."""
    context = rclpy.Context()
    rclpy.init(context=context)
    split: List[Tuple[int, int]] = []
    stages_from = min(STAGES_FROM, frames // 2)

    def on_frame(msg, info) -> None:
        split.append(stamp_split(msg, info, time.time_ns()))
        if len(split) == stages_from:
            _subscriber_stages(stages, transport)

    pub_params = dict(topic=TOPIC, count=frames, rate_hz=rate, wait_for_subscribers=1,
                      width=width, height=1, encoding='mono8', linger_sec=1.0)
    try:
        node = rclpy.create_node('hotpath_sub', context=context)
        if transport == 'stock rclpy':
            node.create_subscription(Image, TOPIC, on_frame, QoSProfile(depth=10))
            pub_exe = 'legacy_image_publisher'
        else:
            rosidl_buffer_py.create_subscription(node, Image, TOPIC, on_frame,
                                                 QoSProfile(depth=10),
                                                 acceptable_buffer_backends=transport)
            pub_exe = 'image_publisher'
            pub_params.update(backend=transport, wait_for_buffer_peers=1)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            with Run() as run:
                run.start('hotpath_pub', pub_exe, **pub_params)
                deadline = time.monotonic() + frames / rate + 60.0
                while len(split) < frames and time.monotonic() < deadline:
                    executor.spin_once(timeout_sec=0.25)
                run.stop_all()
        finally:
            stages.restore()
        executor.shutdown()
        node.destroy_node()  # as the publisher's run does
    finally:
        rclpy.try_shutdown(context=context)
    return split


def cold_penalty(idle: float, count: int = 30) -> Tuple[float, float]:
    """Median µs of one descriptor-message encode (native) back to back, and after ``idle``."""
    msg = mono8_frame(1024, time.time_ns(), DemoBuffer.allocate(1024))
    descriptor = ('demo', bytes(70))
    warm, cold = [], []
    for pause, sink in ((0.0, warm), (idle, cold)):
        for _ in range(count):
            if pause:
                time.sleep(pause)
            started = time.perf_counter_ns()
            codec.encode(msg, descriptor)
            sink.append(time.perf_counter_ns() - started)
    return statistics.median(warm[SKIP:]) / 1e3, statistics.median(cold[SKIP:]) / 1e3


def _us(value: Optional[float]) -> str:
    return '' if value is None else f'{value:.0f}'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=60)
    parser.add_argument('--rate', type=float, default=10.0)
    parser.add_argument('--bytes', type=int, default=1024, dest='nbytes',
                        help='payload size (a mono8 image one row high)')
    parser.add_argument('--rounds', type=int, default=1,
                        help='run every transport this many times, interleaved; latency cells '
                             'are medians over the rounds')
    args = parser.parse_args(argv)
    if args.frames <= SKIP:
        parser.error(f'--frames must be more than {SKIP}, got {args.frames}')
    if args.rounds < 1:
        parser.error(f'--rounds must be at least 1, got {args.rounds}')
    os.environ['ROS_DOMAIN_ID'] = str(claim_domain_ids(1)[0])
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    # per transport: its stages over every round, the messages they were timed over, and per
    # round the medians of (stamp -> reception, reception -> callback) in µs
    pub_stages = {t: Stages() for t in TRANSPORTS}
    sub_stages = {t: Stages() for t in TRANSPORTS}
    timed = {t: [0, 0] for t in TRANSPORTS}
    rounds: Dict[str, List[List[float]]] = {t: [] for t in TRANSPORTS}
    for index in range(args.rounds):
        for transport in TRANSPORTS:
            run_publisher_here(transport, args.nbytes, args.frames, args.rate,
                               pub_stages[transport])
            split = run_subscriber_here(transport, args.nbytes, args.frames, args.rate,
                                        sub_stages[transport])
            if len(split) <= SKIP:
                print(f'{transport}: only {len(split)} frames arrived', file=sys.stderr)
                return 1
            rounds[transport].append([statistics.median(s[i] for s in split[SKIP:]) / 1e3
                                      for i in (0, 1)])
            timed[transport][0] += args.frames
            timed[transport][1] += len(split) - min(STAGES_FROM, args.frames // 2)
            print(f'{transport}: {len(split)} frames (round {index + 1}/{args.rounds})',
                  file=sys.stderr, flush=True)
    splits = {t: [statistics.median(r[i] for r in rounds[t]) for i in (0, 1)]
              for t in TRANSPORTS}
    stage_rows = {t: (pub_stages[t].per_message_us(timed[t][0]),
                      sub_stages[t].per_message_us(timed[t][1])) for t in TRANSPORTS}
    over = f', medians over {args.rounds} interleaved rounds' if args.rounds > 1 else ''
    print(f'\nOne {args.nbytes}-byte frame at {args.rate:g} Hz, publisher and subscriber in '
          f'two processes; medians of {args.frames - SKIP} frames{over}, in µs.\n')
    print('| | ' + ' | '.join(TRANSPORTS) + ' |')
    print('|---' * (len(TRANSPORTS) + 1) + '|')
    for i, what in enumerate(('stamp -> reception (publisher, DDS)',
                              'reception -> callback (subscriber)')):
        print(f'| {what} | ' + ' | '.join(f'{splits[t][i]:.0f}' for t in TRANSPORTS) + ' |')
    print('| total | ' + ' | '.join(f'{sum(splits[t]):.0f}' for t in TRANSPORTS) + ' |')
    print()
    for transport in TRANSPORTS[1:]:  # the totals against stock's, round by round
        ratios = [sum(ours) / sum(stock)
                  for ours, stock in zip(rounds[transport], rounds[TRANSPORTS[0]])]
        print(per_round_line(f'{transport} / {TRANSPORTS[0]} total', ratios))
    for side, index in (('publisher', 0), ('subscriber', 1)):
        labels = list(dict.fromkeys(label for t in reversed(TRANSPORTS)  # demo's: all of them
                                    for label in stage_rows[t][index]))
        if not labels:
            continue
        print(f'\n{side} stages, mean µs per message (calls in the run):\n')
        print('| stage | ' + ' | '.join(TRANSPORTS) + ' |')
        print('|---' * (len(TRANSPORTS) + 1) + '|')
        for label in labels:
            cells = []
            for t in TRANSPORTS:
                found = stage_rows[t][index].get(label)
                cells.append('' if found is None else f'{found[0]:.0f} ({found[1]})')
            print(f'| {label} | ' + ' | '.join(cells) + ' |')
    warm, cold = cold_penalty(1.0 / args.rate)
    print(f'\nThe same native call (a descriptor message encode): {warm:.1f} µs back to back, '
          f'{cold:.1f} µs after {1000 / args.rate:.0f} ms idle ({cold / warm:.0f}x).')
    return 0


if __name__ == '__main__':
    sys.exit(main())
