"""Bring-up: how long a new buffer-aware subscriber gets CPU bytes before its first zero-copy frame.

A demo publisher (``image_publisher``, demo backend, frames filled in place) of ``--payload`` rgb8
at ``--rate`` Hz runs throughout. Each of ``--trials`` trials starts a fresh subscriber process
(this module with ``--subscriber``) accepting ``demo``, which records:

- (a) the instant its main-topic reader matched the publisher (rclpy's subscription *matched*
  event; if a frame is delivered before that event's callback runs, that frame's arrival);
- (b) the arrival of the first frame delivered as a demo Buffer, and how many frames came as CPU
  bytes before it;

then takes ``--after`` more frames, checks every frame (counter, CRC32), that none was lost or
duplicated from the first one on, and exits with a report. The bench prints a table: p50 / p90 /
max of (b) - (a), CPU frames before the first zero-copy frame, and each trial. It asserts nothing
about time.

``python -m launch_free_demos.bench.bringup [--payload 1920x1080] [--rate 30] [--trials 20]``
"""
import argparse
import os
import sys
import time
from dataclasses import dataclass
from typing import List, Optional

from launch_free_demos.bench.stats import percentile
from launch_free_demos.domains import claim_domain_ids
from launch_free_demos.runner import NodeProcess, Run, remove_fastdds_leftovers

#: How long the publisher runs before the first trial (its own start-up is not measured).
WARM_UP_SECONDS = 2.0
#: Frames a stock subscriber (``--stock``) takes.
STOCK_FRAMES = 15
#: Pause between trials: the publisher sees the previous subscriber leave.
GAP_SECONDS = 0.5


# --- the subscriber process -------------------------------------------------------------------

def run_subscriber(topic: str, after: int, timeout: float, stock: bool = False) -> int:
    """One trial's subscriber: record the match, the frames and their routes; print a report.

    ``stock``: a plain rclpy subscription instead, which takes ``STOCK_FRAMES`` frames (what a
    stock subscriber loses at bring-up, for comparison).
    """
    started = time.monotonic()
    import rclpy
    from rclpy.event_handler import SubscriptionEventCallbacks
    from rclpy.node import Node
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import Image

    import rosidl_buffer_py
    from rosidl_buffer_py.nodes.common import run_node
    from rosidl_buffer_py.nodes.frames import check_frame
    from rosidl_buffer_py.report import print_report

    class BringupSubscriber(Node):
        def __init__(self) -> None:
            super().__init__('bringup_subscriber')
            self.matched_at: Optional[float] = None
            self.frames: List[list] = []  # [arrival, backend, counter, ok]
            self.zero_copy = 0
            self.created_at = time.monotonic()
            callbacks = SubscriptionEventCallbacks(matched=self.on_matched)
            self.subscription = self.create_subscription(
                Image, topic, self.on_image, QoSProfile(depth=10),
                event_callbacks=callbacks) if stock else rosidl_buffer_py.create_subscription(
                self, Image, topic, self.on_image, QoSProfile(depth=10),
                event_callbacks=callbacks, acceptable_buffer_backends='demo')
            self.subscribed_at = time.monotonic()

        def on_matched(self, info) -> None:
            if info.current_count_change > 0 and self.matched_at is None:
                self.matched_at = time.monotonic()

        def on_image(self, msg) -> None:
            now = time.monotonic()
            backend = (msg.data.backend_type if isinstance(msg.data, rosidl_buffer_py.Buffer)
                       else 'cpu')
            check = check_frame(msg)
            self.frames.append([now, backend, check.counter, check.ok])
            if backend == 'demo':
                self.zero_copy += 1

        def done(self) -> bool:
            return (self.zero_copy > after or (stock and len(self.frames) >= STOCK_FRAMES) or
                    time.monotonic() - started > timeout)

        def run(self) -> None:
            while not self.done():
                rclpy.spin_once(self, timeout_sec=0.1)

        def finish(self) -> None:
            print_report({'started': started, 'created': self.created_at,
                          'subscribed': self.subscribed_at, 'matched': self.matched_at,
                          'frames': self.frames,
                          'statistics': {} if stock else self.subscription.statistics().as_dict()})

    return run_node(BringupSubscriber, lambda node: node.run(), program='bench_bringup')


class SubscriberProcess(NodeProcess):
    """This module run with ``--subscriber`` (its command line is not an image node's)."""

    def command(self) -> List[str]:
        return [sys.executable, '-m', 'launch_free_demos.bench.bringup', '--subscriber',
                *self.arguments,
                '--ros-args', '-r', f'__node:={self.label}']


# --- the bench --------------------------------------------------------------------------------

@dataclass
class Trial:
    """What one subscriber saw (times in seconds, on the machine's monotonic clock)."""

    matched: Optional[float] = None
    first_frame: Optional[float] = None
    first_zero_copy: Optional[float] = None
    cpu_before: int = 0
    frames: int = 0
    lost: int = 0
    duplicated: int = 0
    corrupt: int = 0
    start_to_match: Optional[float] = None
    problem: str = ''
    fence_timeouts: int = 0
    rejected: int = 0

    @property
    def bringup(self) -> Optional[float]:
        """(b) - (a): match to the first zero-copy frame."""
        if self.matched is None or self.first_zero_copy is None:
            return None
        return self.first_zero_copy - self.matched


def trial_of(report: Optional[dict]) -> Trial:
    """A :class:`Trial` from a subscriber's report."""
    if report is None:
        return Trial(problem='no report')
    trial = Trial()
    frames = report['frames']
    trial.frames = len(frames)
    matched = report['matched']
    if frames:
        trial.first_frame = frames[0][0]
        matched = frames[0][0] if matched is None else min(matched, frames[0][0])
    trial.matched = matched
    if matched is not None:
        trial.start_to_match = matched - report['started']
    for arrival, backend, _, _ in frames:
        if backend == 'demo':
            trial.first_zero_copy = arrival
            break
        trial.cpu_before += 1
    counters = [counter for _, _, counter, _ in frames if counter is not None]
    trial.corrupt = sum(1 for *_, ok in frames if not ok)
    trial.duplicated = len(counters) - len(set(counters))
    if counters:
        missing = sorted(set(range(min(counters), max(counters) + 1)) - set(counters))
        trial.lost = len(missing)
        if missing:
            routes = ' '.join(f'{c}:{b}' for _, b, c, _ in frames)
            trial.problem = f'missing {missing} of {routes}'
        if counters != sorted(counters):
            trial.problem = (trial.problem + '; ' if trial.problem else '') + 'out of order'
    trial.fence_timeouts = report['statistics'].get('fence_timeouts', 0)
    trial.rejected = report['statistics'].get('rejected', 0)
    if trial.first_zero_copy is None and report['statistics']:
        trial.problem = trial.problem or 'no zero-copy frame'
    return trial


def run_trials(width: int, height: int, rate: float, trials: int, after: int,
               stock: bool = False, echo: bool = False) -> List[Trial]:
    """Start the publisher, then one subscriber per trial, in turn; return what each saw."""
    topic = f'/bench_bringup_{os.getpid()}/image'
    results = []
    with Run(echo=echo) as run:
        publisher = run.start('pub', 'image_publisher', topic=topic, backend='demo',
                              fill='allocate', width=width, height=height, encoding='rgb8',
                              rate_hz=rate, count=0, settle_sec=0.0, linger_sec=0.0)
        time.sleep(WARM_UP_SECONDS)
        for index in range(trials):
            if publisher.process.poll() is not None:
                raise RuntimeError('the publisher exited:\n' + run.diagnostics())
            label = f'sub{index}'
            node = run.add(SubscriberProcess(label, 'bench_bringup', arguments=[
                '--topic', topic, '--after', str(after), '--timeout', '30',
                *(['--stock'] if stock else [])]))
            if not run.wait([label], timeout=60.0):
                node.stop()
            results.append(trial_of(node.report))
            time.sleep(GAP_SECONDS)
    return results


def _ms(value: Optional[float]) -> str:
    return '-' if value is None else f'{1000 * value:.0f}'


def table(results: List[Trial], payload: str, rate: float, stock: bool = False) -> str:
    """The summary and one row per trial, as markdown."""
    bringups = [t.bringup for t in results if t.bringup is not None]
    cpu = [t.cpu_before for t in results if t.bringup is not None]
    who = ('a plain rclpy subscriber (for comparison: no zero-copy)' if stock else
           'a buffer-aware subscriber accepting demo: from its main-topic match to its first '
           'zero-copy frame')
    lines = [f'Bring-up of {who}; demo publisher, {payload} rgb8 at {rate:g} Hz, '
             f'{len(results)} trials ({len(bringups)} reached zero-copy); frames lost after '
             f'the first: {sum(t.lost for t in results)} in '
             f'{sum(1 for t in results if t.lost)} trials.', '']
    if bringups:
        lines += ['| | p50 | p90 | max |', '|---|---|---|---|',
                  '| match to first zero-copy frame, ms | ' + ' | '.join(
                      _ms(percentile(bringups, q)) for q in (50, 90, 100)) + ' |',
                  '| CPU frames before it | ' + ' | '.join(
                      f'{percentile(cpu, q):g}' for q in (50, 90, 100)) + ' |']
    lines += ['', '| trial | start to match, ms | match to first frame, ms | '
              'match to zero-copy, ms | CPU frames first | frames | lost | duplicated | '
              'corrupt | rejected | fence timeouts | problem |', '|' + '---|' * 12]
    for index, t in enumerate(results):
        first = None if t.first_frame is None or t.matched is None else t.first_frame - t.matched
        lines.append(f'| {index} | {_ms(t.start_to_match)} | {_ms(first)} | {_ms(t.bringup)} | '
                     f'{t.cpu_before} | {t.frames} | {t.lost} | {t.duplicated} | {t.corrupt} | '
                     f'{t.rejected} | {t.fence_timeouts} | {t.problem} |')
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--payload', default='1920x1080', help='WIDTHxHEIGHT of rgb8 frames')
    parser.add_argument('--rate', type=float, default=30.0, help='frames per second')
    parser.add_argument('--trials', type=int, default=20)
    parser.add_argument('--after', type=int, default=5,
                        help='zero-copy frames each subscriber takes after the first')
    parser.add_argument('--stock', action='store_true',
                        help='plain rclpy subscribers instead (what they lose at bring-up)')
    parser.add_argument('--echo', action='store_true', help="show the processes' output")
    parser.add_argument('--subscriber', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--topic', help=argparse.SUPPRESS)
    parser.add_argument('--timeout', type=float, default=30.0, help=argparse.SUPPRESS)
    args, _ros_args = parser.parse_known_args(argv)
    if args.subscriber:
        return run_subscriber(args.topic, args.after, args.timeout, args.stock)
    width, height = (int(v) for v in args.payload.split('x'))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if not os.environ.get('ROS_DOMAIN_ID'):
        os.environ['ROS_DOMAIN_ID'] = str(claim_domain_ids()[0])
    began = time.time()
    try:
        results = run_trials(width, height, args.rate, args.trials, args.after, args.stock,
                             args.echo)
    finally:
        remove_fastdds_leftovers(began, int(os.environ['ROS_DOMAIN_ID']))
    print(table(results, args.payload, args.rate, args.stock))
    return 0


if __name__ == '__main__':
    sys.exit(main())
