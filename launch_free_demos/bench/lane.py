"""What one ``publish()`` costs a steady demo publisher, through its lane and through the full
path, next to stock rclpy's ``publish()``; and what a demo subscription's delivery costs,
through its steady step and otherwise.

A publisher in this process sends ``--frames`` 1 KiB ``sensor_msgs/Image`` frames at ``--rate``
Hz to a subscriber process: stock rclpy endpoints, then rosidl_buffer_py's with the demo backend
(frames allocated in the pool before each publish), interleaved round by round, each once its
route serves and discovery has settled (``publisher.EPOCH_GRACE_SECONDS``). Each
``publish()`` is timed alone (``perf_counter_ns``), cold as a camera's frames find it. The
demo publisher's calls are split by the path they took: the steady lane (its count,
``statistics().published_on_lane``, moved: the writes prepared for the route table's steady
dispatch, the periodic re-plan's messages included when it gives the same answer) or the full
path. The demo subscriber process times each delivery, from its channel
guard's callback to the start of the user's callback, split by whether
``Subscription._steady_step`` took the sample (the one channel's descriptor message, taken
without the route protocol's general step). A benchmark: it prints medians, it asserts
nothing.
``./dev bench lane [--frames 60] [--rate 10] [--rounds 2]``
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from typing import Dict, List, Optional

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image

from launch_free_demos.bench.hotpath import mono8_frame
from launch_free_demos.domains import claim_domain_ids
from rosidl_buffer_py.publisher import EPOCH_GRACE_SECONDS

MODES = ('stock rclpy', 'demo')
TOPIC = '/bench/lane'
WIDTH = 1024  #: one mono8 row: 1 KiB
#: Calls left out (the first after bring-up).
SKIP = 5
QOS = QoSProfile(depth=10)
#: The printed lines that carry the publisher's and the subscriber's timings to the bench.
TIMES_LINE = 'publish times: '
DELIVERY_LINE = 'delivery times: '


def _subscribe(mode: str, frames: int, rate: float) -> None:
    """Receives; a demo subscription times each delivery (its channel guard's callback to the
    user's callback) by the way the sample was taken, and prints them."""
    rclpy.init()
    try:
        node = rclpy.create_node('lane_sub')
        got: List[int] = []
        times: Dict[str, List[int]] = {}
        if mode == 'demo':
            import rosidl_buffer_py
            entered, steady = [0], [False]

            def on_frame(msg) -> None:
                if len(got) >= SKIP:
                    path = 'steady step' if steady[0] else 'other'
                    times.setdefault(path, []).append(time.perf_counter_ns() - entered[0])
                got.append(1)
            sub = rosidl_buffer_py.create_subscription(node, Image, TOPIC, on_frame, QOS,
                                                       acceptable_buffer_backends='demo')
            deliver, steady_step = sub._deliver_available, sub._steady_step

            def timed_delivery() -> None:
                entered[0], steady[0] = time.perf_counter_ns(), False
                deliver()

            def seen_step(now):
                step = steady_step(now)
                steady[0] = steady[0] or step is not None
                return step
            sub._steady_step = seen_step
            sub._channel_guard.callback = timed_delivery  # (the guard calls what it was given)
        else:
            node.create_subscription(Image, TOPIC, lambda m: got.append(1), QOS)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        deadline = time.monotonic() + frames / rate + 60.0
        while len(got) < frames and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        if times:
            print(DELIVERY_LINE + json.dumps(times), flush=True)
    finally:
        rclpy.try_shutdown()


def _publish(mode: str, frames: int, rate: float) -> Dict[str, List[int]]:
    """Each publish()'s ns, by path: 'stock rclpy', or 'lane' and 'full path'."""
    subscriber = subprocess.Popen(_command('sub', mode, frames, rate))
    rclpy.init()
    times: Dict[str, List[int]] = {}
    try:
        node = rclpy.create_node('lane_pub')
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        if mode == 'demo':
            import rosidl_buffer_py
            from demo_buffer_backend import DemoBuffer
            pub = rosidl_buffer_py.create_publisher(node, Image, TOPIC, QOS)

            def ready() -> bool:  # its route serves, its re-announcer retired
                return any(peer.channel_serving for peer in pub.buffer_peers()) and \
                    pub._peers.reannouncer.retired

            def payload():
                return DemoBuffer.allocate(WIDTH)

            def on_lane_count() -> int:  # statistics().published_on_lane, without its lock
                return pub._on_lane
        else:
            pub = node.create_publisher(Image, TOPIC, QOS)

            def ready() -> bool:
                return pub.get_subscription_count() > 0

            def payload():
                return bytes(WIDTH)

            def on_lane_count() -> int:
                return 0
        deadline = time.monotonic() + 30.0
        while not ready() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        # steady: past discovery's grace, in which the routes' view reads DDS on every message
        settled = time.monotonic() + EPOCH_GRACE_SECONDS + 0.2
        while time.monotonic() < settled:
            executor.spin_once(timeout_sec=0.05)
        for index in range(frames):
            data = payload()
            executor.spin_once(timeout_sec=0)
            time.sleep(1.0 / rate)
            msg = mono8_frame(WIDTH, time.time_ns(), data)
            on_lane = on_lane_count()
            start = time.perf_counter_ns()
            pub.publish(msg)
            elapsed = time.perf_counter_ns() - start
            if index >= SKIP:
                path = mode if mode != 'demo' else (
                    'lane' if on_lane_count() > on_lane else 'full path')
                times.setdefault(path, []).append(elapsed)
            del data, msg
        subscriber.wait(timeout=60.0)
    finally:
        if subscriber.poll() is None:
            subscriber.kill()
            subscriber.wait()
        rclpy.try_shutdown()
    return times


def _command(role: str, mode: str, frames: int, rate: float) -> List[str]:
    return [sys.executable, '-m', 'launch_free_demos.bench.lane', '--role', role, '--mode', mode,
            '--frames', str(frames), '--rate', str(rate)]


def _cell(samples: Optional[List[int]]) -> str:
    if not samples:
        return '-'
    return f'{statistics.median(samples) / 1e3:.0f} ({len(samples)})'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--frames', type=int, default=60)
    parser.add_argument('--rate', type=float, default=10.0)
    parser.add_argument('--rounds', type=int, default=2)
    parser.add_argument('--role', choices=('bench', 'pub', 'sub'), default='bench',
                        help=argparse.SUPPRESS)
    parser.add_argument('--mode', choices=MODES, default='demo', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.role == 'sub':
        _subscribe(args.mode, args.frames, args.rate)
        return 0
    if args.role == 'pub':
        print(TIMES_LINE + json.dumps(_publish(args.mode, args.frames, args.rate)), flush=True)
        return 0
    os.environ['ROS_DOMAIN_ID'] = str(claim_domain_ids(1)[0])  # the processes inherit it
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rows = []
    for index in range(args.rounds):
        row: Dict[str, List[int]] = {}
        for mode in MODES:
            completed = subprocess.run(_command('pub', mode, args.frames, args.rate),
                                       capture_output=True, text=True, timeout=300)
            lines = [line for line in completed.stdout.splitlines()
                     if line.startswith(TIMES_LINE)]
            if completed.returncode != 0 or not lines:
                print(completed.stdout + completed.stderr, file=sys.stderr)
                return 1
            row.update(json.loads(lines[-1][len(TIMES_LINE):]))
            row.update({f'delivery: {path}': samples for line in completed.stdout.splitlines()
                        if line.startswith(DELIVERY_LINE)
                        for path, samples in json.loads(line[len(DELIVERY_LINE):]).items()})
        rows.append(row)
        print(f'round {index + 1}: ' + ', '.join(f'{path} {_cell(samples)}'
                                                  for path, samples in row.items()), flush=True)
    print(f'\nOne 1 KiB frame at {args.rate:g} Hz, publisher and subscriber in two processes: '
          'publish() alone, and the demo subscription\'s delivery (its channel guard\'s '
          'callback to the start of the user\'s), median µs (calls), per round.\n')
    print('| round | stock rclpy publish() | demo publish(): steady lane | demo publish(): full '
          'path | demo delivery: steady step | demo delivery: other |')
    print('|---|---|---|---|---|---|')
    for index, row in enumerate(rows):
        print(f'| {index + 1} | {_cell(row.get("stock rclpy"))} | {_cell(row.get("lane"))} | '
              f'{_cell(row.get("full path"))} | {_cell(row.get("delivery: steady step"))} | '
              f'{_cell(row.get("delivery: other"))} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
