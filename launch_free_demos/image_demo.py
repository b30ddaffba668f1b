"""The cross-process image demo: ``./dev demo``.

Starts an image_publisher filling 1920x1080 rgb8 frames in place in shared memory (the demo
backend) and an image_subscriber that accepts the demo backend, in two processes. The subscriber
logs what arrives (backend, size, latency) every second; at the end a summary table shows every
frame's route and checksum result. Options change the size, rate, duration and backend.

When a node exits with an error (a bad option reaches it as a bad parameter), the demo stops at
once and shows that node's last error lines. Ctrl-C stops both nodes and prints the summary so
far.
"""
import argparse
import os
import signal
import sys
from typing import Optional

from launch_free_demos.runner import Run


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--width', type=int, default=1920)
    parser.add_argument('--height', type=int, default=1080)
    parser.add_argument('--encoding', default='rgb8')
    parser.add_argument('--rate', type=float, default=30.0, help='frames per second')
    parser.add_argument('--seconds', type=float, default=5.0, help='how long to publish')
    parser.add_argument('--backend', default='demo', help='payload backend: demo or cpu')
    parser.add_argument('--accept', default='demo',
                        help="subscriber's acceptable_buffer_backends (default: demo)")
    parser.add_argument('--depth', type=int, default=30,
                        help='KEEP_LAST depth of both endpoints (default 30: one second at 30 Hz, '
                             'so that a subscriber stalled by a busy machine loses nothing)')
    args = parser.parse_args(argv)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    count = max(1, int(args.rate * args.seconds))
    frame = dict(width=args.width, height=args.height, encoding=args.encoding)
    print(f'Publishing {count} {args.width}x{args.height} {args.encoding} frames at '
          f'{args.rate:g} Hz with backend {args.backend!r}; the subscriber accepts '
          f'{args.accept!r}. Publisher and subscriber are separate processes.\n', flush=True)
    interrupted = False
    with Run(echo=True) as run:
        try:
            run.start('demo_subscriber', 'image_subscriber', topic='/demo/image',
                      acceptable_buffer_backends=args.accept, expected_count=count,
                      timeout_sec=args.seconds + 60.0, report_period_sec=1.0, depth=args.depth)
            run.start('demo_publisher', 'image_publisher', topic='/demo/image',
                      backend=args.backend, rate_hz=args.rate, count=count,
                      wait_for_subscribers=1, wait_for_buffer_peers=1, linger_sec=10.0,
                      depth=args.depth, **frame)
            finished = run.wait(timeout=args.seconds + 90.0, fail_fast=True)
        except KeyboardInterrupt:
            interrupted, finished = True, False
        # Ctrl-C again while the nodes stop must not cut their reports short
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        failed = run.failed()
        run.stop_all()
        signal.signal(signal.SIGINT, previous)
    if failed:
        for node in failed:
            print(f'\ndemo: {node.label} ({node.executable}) exited with status '
                  f'{node.process.returncode}; its last error lines:', file=sys.stderr)
            print('\n'.join('  ' + line for line in node.stderr[-10:]) or '  (none)',
                  file=sys.stderr)
        return 1
    sub = run.nodes['demo_subscriber'].report if 'demo_subscriber' in run.nodes else None
    pub = run.nodes['demo_publisher'].report if 'demo_publisher' in run.nodes else None
    if interrupted:
        print('\ndemo: interrupted; the summary so far:')
        print_summary(args, pub, sub)
        return 130
    if not finished or sub is None or pub is None:
        print('\nThe demo did not finish:\n' + run.diagnostics(), file=sys.stderr)
        return 1
    print_summary(args, pub, sub)
    ok = (sub['distinct'] == count and sub['duplicates'] == 0 and
          sub['checksum_failures'] == 0)
    return 0 if ok else 1


def print_summary(args: argparse.Namespace, pub: Optional[dict], sub: Optional[dict]) -> None:
    """The table of what the publisher sent and the subscriber received (n/a: no report)."""
    nbytes = args.width * args.height * {'rgb8': 3, 'bgr8': 3, 'mono8': 1, 'rgba8': 4,
                                         'bgra8': 4, 'mono16': 2}.get(args.encoding, 0)
    pub = pub or {}
    sub = sub or {}
    latency = sub.get('latency_ms', {})
    na = 'n/a'
    print('\n| what | value |\n|---|---|')
    for label, value in [
            ('frames published', pub.get('published', na)),
            ('frames received (distinct)',
             f"{sub['received']} ({sub['distinct']})" if sub else na),
            ('payload bytes per frame', f'{nbytes:,}' if nbytes else na),
            ('backends seen by the subscriber', sub.get('backends', na)),
            ('duplicates / gaps / checksum failures',
             f"{sub['duplicates']} / {sub['gaps']} / {sub['checksum_failures']}" if sub else na),
            ('latency publish -> callback, ms (p50 / p90 / p99 / max)',
             ' / '.join(str(latency[k]) for k in ('p50', 'p90', 'p99', 'max'))
             if latency else na),
            ('messages the publisher wrote on the main topic',
             pub.get('statistics', {}).get('sent_on_main_topic', na))]:
        print(f'| {label} | {value} |')


if __name__ == '__main__':
    sys.exit(main())
