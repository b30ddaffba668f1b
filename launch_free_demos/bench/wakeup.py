"""What buffer-aware endpoints add to every wake-up of their node's executor.

rclpy's executor rebuilds its wait set from every entity of its nodes on each wake-up (the one
that delivers a message too), in Python. A camera node with several topics: one process, a
node with ``--topics`` publishers of ``sensor_msgs/Image`` and a node with as many
subscriptions, one ``SingleThreadedExecutor``, every topic served (one frame each, and for
buffer-aware endpoints their channels up and their routes steady). Then a guard condition of
the user's, triggered ``--wakeups`` times, ``--period`` seconds apart (cold, as at camera
rates): the time from its trigger to its callback and the executor thread's CPU time for that
spin, with stock rclpy endpoints and with this package's (the demo backend accepted),
interleaved round by round, each run a process of its own. Prints the medians per run, the
guard conditions and timers the nodes hold in steady state, and ours against stock's.
A benchmark: it prints, it asserts nothing.
``./dev bench wakeup [--topics 4] [--wakeups 40] [--period 0.1] [--rounds 3]``
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from typing import Dict, List, NamedTuple

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image

from launch_free_demos.domains import claim_domain_ids

MODES = ('stock rclpy', 'rosidl_buffer_py')
QOS = QoSProfile(depth=10)
#: seconds to spin after every topic is served (routes settle, bring-up timers go)
SETTLE_SECONDS = 2.0


class Wakeups(NamedTuple):
    """One run's medians (µs) and what its nodes held in steady state."""

    latency_us: float  #: trigger to callback
    cpu_us: float      #: the executor thread's CPU time for the spin
    guards: int
    timers: int


def _frame(width: int = 64):
    msg = Image()
    msg.height, msg.width, msg.step, msg.encoding = 1, width, width, 'mono8'
    msg.data = bytes(width)
    return msg


def run(mode: str, topics: int, wakeups: int, period: float) -> Wakeups:
    """One run in this process (a context of its own)."""
    import rosidl_buffer_py
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        camera = rclpy.create_node('wakeup_camera', context=context)
        viewer = rclpy.create_node('wakeup_viewer', context=context)
        received: Dict[str, int] = {}
        publishers = []
        for index in range(topics):
            topic = f'/bench/wakeup_{index}'

            def on_frame(msg, topic=topic) -> None:
                received[topic] = received.get(topic, 0) + 1
            if mode == 'stock rclpy':
                publishers.append(camera.create_publisher(Image, topic, QOS))
                viewer.create_subscription(Image, topic, on_frame, QOS)
            else:
                publishers.append(rosidl_buffer_py.create_publisher(camera, Image, topic, QOS))
                rosidl_buffer_py.create_subscription(viewer, Image, topic, on_frame, QOS,
                                                     acceptable_buffer_backends='demo')
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(camera)
        executor.add_node(viewer)

        def served() -> bool:
            return all(pub.get_subscription_count() > 0 and
                       all(peer.channel_serving for peer in getattr(pub, 'buffer_peers', list)())
                       for pub in publishers)
        deadline = time.monotonic() + 30.0
        while not served() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        if not served():
            raise RuntimeError(f'{mode}: {topics} topics not served within 30 s')
        for pub in publishers:
            pub.publish(_frame())
        settle = time.monotonic() + SETTLE_SECONDS
        while time.monotonic() < settle or len(received) < topics:
            executor.spin_once(timeout_sec=0.05)
            if time.monotonic() > deadline + SETTLE_SECONDS:
                raise RuntimeError(f'{mode}: {len(received)} of {topics} topics delivered')
        called: List[int] = []
        guard = camera.create_guard_condition(lambda: called.append(time.perf_counter_ns()))
        latencies, cpu = [], []
        for _ in range(wakeups):
            time.sleep(period)
            before = len(called)
            started, cpu_started = time.perf_counter_ns(), time.thread_time_ns()
            guard.trigger()
            while len(called) == before:
                executor.spin_once(timeout_sec=1.0)
            cpu.append((time.thread_time_ns() - cpu_started) / 1e3)
            latencies.append((called[-1] - started) / 1e3)
        nodes = (camera, viewer)
        result = Wakeups(statistics.median(latencies), statistics.median(cpu),
                         sum(len(list(node.guards)) for node in nodes) - 1,  # (the user's)
                         sum(len(list(node.timers)) for node in nodes))
        executor.shutdown()
        camera.destroy_node()
        viewer.destroy_node()
        return result
    finally:
        rclpy.try_shutdown(context=context)


def measure(mode: str, topics: int, wakeups: int, period: float) -> Wakeups:
    """One run in a process of its own."""
    completed = subprocess.run(
        [sys.executable, '-m', 'launch_free_demos.bench.wakeup', '--mode', mode, '--topics',
         str(topics), '--wakeups', str(wakeups), '--period', str(period)],
        stdout=subprocess.PIPE, text=True, timeout=120 + wakeups * (period + 1.0), check=True)
    return Wakeups(*json.loads(completed.stdout.strip().splitlines()[-1]))


def table(results: Dict[str, List[Wakeups]], topics: int, wakeups: int, period: float) -> str:
    head = (f'One executor wake-up (a guard condition of the user\'s) with {topics} topics '
            f'served, a publisher and a subscription each, in two nodes of one process; '
            f'medians of {wakeups} wake-ups {period:g} s apart, µs, per run.\n\n'
            '| run | ' + ' | '.join(f'{mode}: trigger -> callback / CPU' for mode in MODES) +
            ' | ours / stock (latency) |\n|---|' + '---|' * (len(MODES) + 1))
    rows = []
    for index, runs in enumerate(zip(*(results[mode] for mode in MODES))):
        cells = [f'{r.latency_us:.0f} / {r.cpu_us:.0f}' for r in runs]
        rows.append(f'| {index + 1} | ' + ' | '.join(cells) +
                    f' | {runs[1].latency_us / runs[0].latency_us:.2f} |')
    held = '; '.join(f'{mode}: {results[mode][-1].guards} guard conditions, '
                     f'{results[mode][-1].timers} timers' for mode in MODES)
    return head + '\n' + '\n'.join(rows) + f'\n\nWhat the nodes hold besides stock\'s own ' \
        f'entities, in steady state: {held}.'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--topics', type=int, default=4)
    parser.add_argument('--wakeups', type=int, default=40)
    parser.add_argument('--period', type=float, default=0.1)
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--mode', choices=MODES, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.topics < 1 or args.wakeups < 1:
        parser.error(f'--topics and --wakeups must be at least 1, got {args.topics} and '
                     f'{args.wakeups}')
    if args.mode is not None:
        print(json.dumps(run(args.mode, args.topics, args.wakeups, args.period)))
        return 0
    os.environ['ROS_DOMAIN_ID'] = str(claim_domain_ids(1)[0])  # the processes inherit it
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    results: Dict[str, List[Wakeups]] = {mode: [] for mode in MODES}
    for index in range(args.rounds):
        for mode in MODES:
            results[mode].append(measure(mode, args.topics, args.wakeups, args.period))
            print(f'round {index + 1}, {mode}: {results[mode][-1].latency_us:.0f} µs',
                  flush=True)
    print()
    print(table(results, args.topics, args.wakeups, args.period))
    return 0


if __name__ == '__main__':
    sys.exit(main())
