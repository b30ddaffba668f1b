"""A subscriber process stalled (SIGSTOP) while publishers write: the MESSAGE_LOST events each
of its subscriptions reports, with stock endpoints or ours (not collected by pytest).

keep_last_1_mixed's graph (:mod:`harness.equivalence`): a cpu, a demo and a plain publisher in
one process, subscriptions accepting cpu, demo and any and a plain one in another, RELIABLE
KEEP_LAST 1, ``--count`` messages each at 50 Hz; the subscriber process is stopped ``--stalls``
times for ``--stall`` seconds while they publish. ``stock``: every endpoint a plain rclpy one.

``python stalled_reader.py stock|ours [--stall 0.2] [--stalls 2] [--count 60]`` prints one JSON
line: per subscription, the messages it took, the MESSAGE_LOST events' total count and the
descriptors it rejected (stale: their slot was reused before it took them; stock rejects none).
"""
import argparse
import array
import json
import os
import signal
import subprocess
import sys
import time

SUBSCRIPTIONS = ('cpu', 'demo', 'any', 'plain')
RATE_HZ = 50.0


def _qos():
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST)


def subscriber(ours: bool, topic: str) -> None:
    """Spin until standard input closes, then print the counts."""
    import threading
    import rclpy
    from rclpy.event_handler import SubscriptionEventCallbacks
    from sensor_msgs.msg import Image
    rclpy.init()
    node = rclpy.create_node('stalled_reader_sub')
    counts = {label: {'taken': 0, 'lost': 0} for label in SUBSCRIPTIONS}

    def create(label):
        def on_message(_msg):
            counts[label]['taken'] += 1

        def on_lost(info):
            counts[label]['lost'] = info.total_count
        events = SubscriptionEventCallbacks(message_lost=on_lost)
        if ours and label != 'plain':
            import rosidl_buffer_py
            return rosidl_buffer_py.create_subscription(
                node, Image, topic, on_message, _qos(), event_callbacks=events,
                acceptable_buffer_backends=label)
        return node.create_subscription(Image, topic, on_message, _qos(),
                                        event_callbacks=events)
    node.subs = [create(label) for label in SUBSCRIPTIONS]  # kept alive with the node
    print('ready', flush=True)
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    while not done.is_set():
        rclpy.spin_once(node, timeout_sec=0.05)
    for label, sub in zip(SUBSCRIPTIONS, node.subs):  # descriptors it could not open
        counts[label]['rejected'] = getattr(sub.statistics(), 'rejected', 0) \
            if hasattr(sub, 'statistics') else 0
    print(json.dumps(counts), flush=True)


def publisher(ours: bool, topic: str, count: int) -> None:
    """Publish ``count`` messages on each publisher once every subscription is matched."""
    import numpy
    import rclpy
    from sensor_msgs.msg import Image
    rclpy.init()
    node = rclpy.create_node('stalled_reader_pub')
    if ours:
        import demo_buffer_backend
        import rosidl_buffer_py
        pubs = {kind: rosidl_buffer_py.create_publisher(node, Image, topic, _qos())
                for kind in ('cpu', 'demo')}
    else:
        pubs = {kind: node.create_publisher(Image, topic, _qos()) for kind in ('cpu', 'demo')}
    pubs['plain'] = node.create_publisher(Image, topic, _qos())
    deadline = time.monotonic() + 30.0
    while min(p.get_subscription_count() for p in pubs.values()) < len(SUBSCRIPTIONS):
        rclpy.spin_once(node, timeout_sec=0.05)
        if time.monotonic() > deadline:
            sys.exit('the subscriptions were not matched in 30 s')
    if ours:  # served before the stalls: what is measured is the steady state
        pubs['cpu'].wait_for_buffer_peers(3, timeout_sec=10.0)
        pubs['demo'].wait_for_buffer_peers(2, timeout_sec=10.0)
    print('publishing', flush=True)
    next_at = time.monotonic()
    for _ in range(count):
        for kind, pub in pubs.items():
            msg = Image(height=1, width=2048, encoding='mono8', step=2048)
            if ours and kind == 'demo':
                buf = demo_buffer_backend.DemoBuffer.allocate(2048)
                numpy.asarray(buf)[:] = 1
                msg.data = buf
            else:
                msg.data = array.array('B', bytes(2048))
            pub.publish(msg)
        rclpy.spin_once(node, timeout_sec=0)
        next_at += 1 / RATE_HZ
        time.sleep(max(0.0, next_at - time.monotonic()))
    end = time.monotonic() + 2.0  # for what the subscriptions still ask
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('variant', choices=('stock', 'ours'))
    parser.add_argument('--role', choices=('parent', 'sub', 'pub'), default='parent')
    parser.add_argument('--topic', default=f'/stalled_reader_{os.getpid()}')
    parser.add_argument('--stall', type=float, default=0.2)
    parser.add_argument('--stalls', type=int, default=2)
    parser.add_argument('--count', type=int, default=60)
    args = parser.parse_args(argv)
    ours = args.variant == 'ours'
    if args.role == 'sub':
        subscriber(ours, args.topic)
        return 0
    if args.role == 'pub':
        publisher(ours, args.topic, args.count)
        return 0
    me = [sys.executable, os.path.abspath(__file__), args.variant, '--topic', args.topic]
    sub = subprocess.Popen(me + ['--role', 'sub'], stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, text=True)
    pub = None
    try:
        if sub.stdout.readline().strip() != 'ready':
            return 1
        pub = subprocess.Popen(me + ['--role', 'pub', '--count', str(args.count)],
                               stdout=subprocess.PIPE, text=True)
        if pub.stdout.readline().strip() != 'publishing':
            return 1
        time.sleep(0.1)
        for _ in range(args.stalls):
            os.kill(sub.pid, signal.SIGSTOP)
            time.sleep(args.stall)
            os.kill(sub.pid, signal.SIGCONT)
            time.sleep(0.2)
        pub.wait(timeout=60)
        out, _ = sub.communicate('', timeout=30)  # its stdin closes: it prints and exits
    finally:
        for proc in (sub, pub):
            if proc is not None and proc.poll() is None:
                os.kill(proc.pid, signal.SIGCONT)
                proc.kill()
                proc.wait()
    lines = [line for line in out.splitlines() if line.startswith('{')]
    if not lines:
        return 1
    print(lines[-1])
    return 0


if __name__ == '__main__':
    sys.exit(main())
