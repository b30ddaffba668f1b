"""The cross-process image demo: ``./dev demo``.

Starts an image_publisher filling 1920x1080 rgb8 frames in place in shared memory (the demo
backend) and an image_subscriber that accepts the demo backend, in two processes. The subscriber
logs what arrives (backend, size, latency) every second; at the end a summary table shows every
frame's route and checksum result. Options change the size, rate, duration and backend.
"""
import argparse
import os
import sys

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
    with Run(echo=True) as run:
        run.start('demo_subscriber', 'image_subscriber', topic='/demo/image',
                  acceptable_buffer_backends=args.accept, expected_count=count,
                  timeout_sec=args.seconds + 60.0, report_period_sec=1.0, depth=args.depth)
        run.start('demo_publisher', 'image_publisher', topic='/demo/image',
                  backend=args.backend, rate_hz=args.rate, count=count,
                  wait_for_subscribers=1, wait_for_buffer_peers=1, linger_sec=10.0,
                  depth=args.depth, **frame)
        finished = run.wait(timeout=args.seconds + 90.0)
        run.stop_all()
        sub = run.nodes['demo_subscriber'].report
        pub = run.nodes['demo_publisher'].report
    if not finished or sub is None or pub is None:
        print('\nThe demo did not finish:\n' + run.diagnostics(), file=sys.stderr)
        return 1
    nbytes = args.width * args.height * {'rgb8': 3, 'bgr8': 3, 'mono8': 1, 'rgba8': 4,
                                         'bgra8': 4, 'mono16': 2}.get(args.encoding, 0)
    latency = sub['latency_ms']
    print('\n| what | value |\n|---|---|')
    for label, value in [
            ('frames published', pub['published']),
            ('frames received (distinct)', f"{sub['received']} ({sub['distinct']})"),
            ('payload bytes per frame', f'{nbytes:,}' if nbytes else 'n/a'),
            ('backends seen by the subscriber', sub['backends']),
            ('duplicates / gaps / checksum failures',
             f"{sub['duplicates']} / {sub['gaps']} / {sub['checksum_failures']}"),
            ('latency publish -> callback, ms (p50 / p90 / p99 / max)',
             f"{latency['p50']} / {latency['p90']} / {latency['p99']} / {latency['max']}"),
            ('messages the publisher wrote on the main topic',
             pub['statistics']['sent_on_main_topic'])]:
        print(f'| {label} | {value} |')
    ok = (sub['distinct'] == count and sub['duplicates'] == 0 and
          sub['checksum_failures'] == 0)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
