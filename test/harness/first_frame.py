"""How soon a timer-driven publisher's frames reach a subscriber that is already running.

A camera driver written the simple way publishes from a timer as soon as it starts, without
waiting for subscribers: the frames before the first match are lost (volatile durability), for
stock rclpy as for this package. This measures, for stock and this package's publisher against
one subscriber kind, A B A B, in one domain of its own:

- ``first``: the index of the first frame the subscriber got (frames 0, 1, ... at ``--rate``);
- ``matched ms``: from ``create_publisher`` returning to the publisher's first non-zero
  ``get_subscription_count()`` (checked at each tick);
- ``first frame ms``: from ``create_publisher`` returning to the subscriber's first callback.

A run without a frame matched later than the publisher's last frame: Fast DDS's discovery of a
new participant now and then waits for the running one's next periodic announcement (about
2.4 s here), with stock endpoints as with ours; compare those counts over many runs.

``python test/harness/first_frame.py [--runs 10] [--subscriber stock|ours|both] [--rate 30]``
prints a table per subscriber kind: each run's figures, then median and worst per publisher.
"""
import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

if __package__ in (None, ''):  # run as a file: harness is a package of test/, and
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    # launch_free_demos (not installed) is the checkout's, after the installed packages
    sys.path.append(str(Path(__file__).resolve().parents[2]))

from launch_free_demos.domains import fresh_domain  # noqa: E402 (after the path fix)

KINDS = ('stock', 'ours')
#: Publishers between the two, to tell which part of ours changes matching (``--publishers``):
#: stock rclpy after ``import rosidl_buffer_py``; after the discovery tap is installed on its
#: participant as a buffer-aware endpoint's creation does; and a stock publisher whose USER_DATA
#: is then set again, unchanged, as ours sets its advertisement (a re-announcement).
PUBLISHER_VARIANTS = ('stock', 'import', 'tap', 'userdata', 'ours')
TOPIC = 'first_frame/image'

#: The subscriber: prints READY once created, then one JSON line per frame (index, monotonic
#: time of the callback), until stdin closes.
SUBSCRIBER = '''
import json, sys, threading, time
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import Image
import rosidl_buffer_py

rclpy.init()
node = rclpy.create_node('first_frame_sub')

def on_frame(msg):
    print(json.dumps({'index': int(msg.header.frame_id), 't': time.monotonic()}), flush=True)

if sys.argv[1] == 'stock':
    node.create_subscription(Image, sys.argv[2], on_frame, 10)
else:
    rosidl_buffer_py.create_subscription(node, Image, sys.argv[2], on_frame, 10,
                                         acceptable_buffer_backends='any')
executor = SingleThreadedExecutor()
executor.add_node(node)
threading.Thread(target=lambda: (sys.stdin.read(), rclpy.try_shutdown()), daemon=True).start()
print('READY', flush=True)
try:
    executor.spin()
except Exception:
    pass
'''

#: The publisher: a 640x480 rgb8 frame per timer tick from creation on; prints one JSON line
#: (creation time, time of the first matched tick) at the end.
PUBLISHER = '''
import json, sys, time
import numpy
import rclpy
from sensor_msgs.msg import Image
import rosidl_buffer_py
from rosidl_buffer_py.image import to_msg

kind, topic, rate, count = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
rclpy.init()
node = rclpy.create_node('first_frame_pub')
if kind in ('import', 'tap', 'userdata'):
    from rosidl_buffer_py import discovery
    if kind == 'tap':
        discovery.for_node(node)
    pub = node.create_publisher(Image, topic, 10)
    if kind == 'userdata':
        from rosidl_buffer_py._dds import get_user_data, set_user_data
        set_user_data(pub, get_user_data(pub, 'publisher'), 'publisher')
elif kind == 'stock':
    pub = node.create_publisher(Image, topic, 10)
else:
    pub = rosidl_buffer_py.create_publisher(node, Image, topic, 10)
created = time.monotonic()
frame = numpy.zeros((480, 640, 3), numpy.uint8)
state = {'index': 0, 'matched': None}

def tick():
    if state['matched'] is None and pub.get_subscription_count() > 0:
        state['matched'] = time.monotonic()
    msg = Image()
    to_msg(msg, frame, encoding='rgb8')
    msg.header.frame_id = str(state['index'])
    pub.publish(msg)
    state['index'] += 1

timer = node.create_timer(1.0 / rate, tick)
while state['index'] < count:
    rclpy.spin_once(node, timeout_sec=0.1)
timer.cancel()
end = time.monotonic() + 0.5
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
print(json.dumps({'created': created, 'matched': state['matched']}), flush=True)
node.destroy_node()
rclpy.shutdown()
'''


@dataclass
class Trial:
    """One publisher start against a running subscriber."""

    publisher: str
    first: Optional[int]      #: index of the first frame received (None: none arrived)
    received: int
    matched_ms: Optional[float]
    first_frame_ms: Optional[float]


def _python_env() -> Dict[str, str]:
    return dict(os.environ, PYTHONUNBUFFERED='1')


def run_trial(subscriber: str, publisher: str, rate: float, count: int) -> Trial:
    """Start a subscriber, let it settle 1 s, start the publisher, collect what arrived."""
    sub = subprocess.Popen([sys.executable, '-c', SUBSCRIBER, subscriber, TOPIC],
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                           stderr=subprocess.DEVNULL, text=True, env=_python_env())
    pub = None
    try:
        if sub.stdout.readline().strip() != 'READY':
            raise RuntimeError('the subscriber did not start')
        time.sleep(1.0)  # running: its participant announced, as a node that waits for frames
        pub = subprocess.run([sys.executable, '-c', PUBLISHER, publisher, TOPIC, str(rate),
                              str(count)], capture_output=True, text=True, timeout=120,
                             env=_python_env())
        if pub.returncode != 0:
            raise RuntimeError(f'the publisher exited {pub.returncode}: {pub.stderr[-2000:]}')
        times = json.loads(pub.stdout.strip().splitlines()[-1])
        out, _ = sub.communicate(input='', timeout=30)  # stdin closed: it shuts down
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.wait()
    frames = [json.loads(line) for line in out.splitlines() if line.startswith('{')]
    created = times['created']
    return Trial(
        publisher=publisher,
        first=frames[0]['index'] if frames else None,
        received=len(frames),
        matched_ms=None if times['matched'] is None else (times['matched'] - created) * 1e3,
        first_frame_ms=(frames[0]['t'] - created) * 1e3 if frames else None)


def _fmt(value) -> str:
    if value is None:
        return '-'
    return f'{value:.0f}' if isinstance(value, float) else str(value)


def _summary(trials: List[Trial], field: str) -> str:
    values = [getattr(t, field) for t in trials]
    known = [v for v in values if v is not None]
    if not known:
        return '-'
    missing = len(values) - len(known)
    worst = 'none' if missing else _fmt(max(known))
    return f'{_fmt(float(statistics.median(known)))} / {worst}'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--runs', type=int, default=10, help='runs per publisher kind')
    parser.add_argument('--subscriber', choices=(*KINDS, 'both'), default='both')
    parser.add_argument('--publishers', default=','.join(KINDS),
                        help=f'comma-separated, run in turn: {", ".join(PUBLISHER_VARIANTS)}')
    parser.add_argument('--rate', type=float, default=30.0, help='frames per second')
    parser.add_argument('--frames', type=int, default=60, help='frames per run')
    args = parser.parse_args(argv)
    # SIGTERM (a timeout's) takes Ctrl-C's path: the nodes and probes it started are reaped
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    subscribers = KINDS if args.subscriber == 'both' else (args.subscriber,)
    publishers = [p for p in args.publishers.split(',') if p]
    unknown = set(publishers) - set(PUBLISHER_VARIANTS)
    if unknown:
        parser.error(f'unknown publishers {sorted(unknown)}; known: {PUBLISHER_VARIANTS}')
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    with fresh_domain():
        for subscriber in subscribers:
            trials = []
            print(f'\n{subscriber} subscriber, {args.frames} frames at {args.rate:g} Hz\n')
            print('| run | publisher | first | received | matched ms | first frame ms |')
            print('|---|---|---|---|---|---|')
            for run in range(args.runs):
                for publisher in publishers:
                    trial = run_trial(subscriber, publisher, args.rate, args.frames)
                    trials.append(trial)
                    print(f'| {run + 1} | {publisher} | {_fmt(trial.first)} | '
                          f'{trial.received} | {_fmt(trial.matched_ms)} | '
                          f'{_fmt(trial.first_frame_ms)} |', flush=True)
            print('\n| publisher | runs without a frame | first: median / worst | '
                  'matched ms: median / worst | first frame ms: median / worst |')
            print('|---|---|---|---|---|')
            for publisher in publishers:
                mine = [t for t in trials if t.publisher == publisher]
                none = sum(t.first is None for t in mine)
                print(f'| {publisher} | {none} of {len(mine)} | {_summary(mine, "first")} | '
                      f'{_summary(mine, "matched_ms")} | {_summary(mine, "first_frame_ms")} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
