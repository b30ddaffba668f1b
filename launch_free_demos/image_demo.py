"""The cross-process image demo: ``./dev demo``.

Starts an image_publisher filling 1920x1080 rgb8 frames in place in shared memory (the demo
backend) and an image_subscriber that accepts the demo backend, in two processes. The subscriber
logs what arrives (backend, size, latency) every second; at the end a summary table shows what
was published and received, and a legend says what each row means. The demo ends when the
publisher has sent its last frame and the subscriber has had :data:`DRAIN_SEC` to take it: lost
frames are then named, with the likely reason, instead of waiting for the subscriber's timeout.

When a node exits with an error (a bad option reaches it as a bad parameter), the demo stops at
once and shows that node's last error lines. Ctrl-C stops both nodes and prints the summary so
far.
"""
import argparse
import os
import signal
import sys
from typing import List, Optional

from launch_free_demos.runner import Run

#: After the publisher's last frame (and its linger), how long the subscriber may still take
#: frames before the demo stops it.
DRAIN_SEC = 3.0
#: The publisher stays this long after its last frame while the subscriber is matched
#: (reliable delivery of the last frames).
LINGER_SEC = 2.0
#: The demo's topic.
TOPIC = '/demo/image'

DESCRIPTION = ('The cross-process image demo: an image_publisher fills frames in place in '
               'shared memory (the demo backend) and an image_subscriber in another process '
               'receives them; a summary table follows.')
EPILOG = """The summary table:
  frames published             what the publisher sent
  frames received (distinct)   callbacks the subscriber ran (different frame counters)
  backends seen ...            how the frames arrived: demo = zero-copy shared memory,
                               cpu = a copy of the bytes
  duplicates / gaps / ...      frames seen twice / never seen / with a wrong CRC32
  latency publish -> callback  from the publisher's stamp to the subscriber's callback
  messages ... main topic      serialized copies the publisher made for the DDS topic itself
                               (0: every subscriber got descriptors on its channel)
Exit status: 0 when every frame arrived intact, 1 otherwise (the lost ones are named)."""

#: Printed under the table: what it showed, in one paragraph.
LEGEND = ('The table: frames the publisher sent, and what the subscriber got: how many '
          '(distinct counters), how they arrived (demo: a descriptor to shared memory, zero-copy; '
          'cpu: a copy of the bytes), frames seen twice, never seen or corrupted, the latency from '
          "the publisher's stamp to the subscriber's callback, and the serialized copies the "
          'publisher made on the DDS topic itself (0: the subscriber got every frame on its own '
          'channel).')


def _positive(kind):
    """An argparse type: a number > 0 (the message names the bad value)."""
    def convert(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
        if value <= 0:
            raise argparse.ArgumentTypeError(f'must be > 0, got {text}')
        return value
    return convert


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='./dev demo', description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--width', type=_positive(int), default=1920)
    parser.add_argument('--height', type=_positive(int), default=1080)
    parser.add_argument('--encoding', default='rgb8')
    parser.add_argument('--rate', type=_positive(float), default=30.0,
                        help='frames per second (> 0)')
    parser.add_argument('--seconds', type=_positive(float), default=5.0,
                        help='how long to publish (> 0)')
    parser.add_argument('--backend', default='demo', help='payload backend: demo or cpu')
    parser.add_argument('--accept', default='demo',
                        help="subscriber's acceptable_buffer_backends (default: demo)")
    parser.add_argument('--depth', type=_positive(int), default=30,
                        help='KEEP_LAST depth of both endpoints (default 30: one second at 30 Hz, '
                             'so that a subscriber stalled by a busy machine loses nothing)')
    parser.add_argument('--slow-subscriber', type=float, default=0.0, metavar='SEC',
                        help='the subscriber spends SEC in each callback (shows what a small '
                             '--depth loses); default 0')
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    count = max(1, int(args.rate * args.seconds))
    frame = dict(width=args.width, height=args.height, encoding=args.encoding)
    print(f'Publishing {count} {args.width}x{args.height} {args.encoding} frames at '
          f'{args.rate:g} Hz with backend {args.backend!r}; the subscriber accepts '
          f'{args.accept!r}. Publisher and subscriber are separate processes.\n', flush=True)
    interrupted = False
    drained = True
    with Run(echo=True) as run:
        try:
            run.start('demo_subscriber', 'image_subscriber', topic=TOPIC,
                      acceptable_buffer_backends=args.accept, expected_count=count,
                      timeout_sec=args.seconds + 60.0, report_period_sec=1.0, depth=args.depth,
                      work_sec=max(0.0, args.slow_subscriber))
            run.start('demo_publisher', 'image_publisher', topic=TOPIC,
                      backend=args.backend, rate_hz=args.rate, count=count,
                      wait_for_subscribers=1, wait_for_buffer_peers=1, linger_sec=LINGER_SEC,
                      depth=args.depth, **frame)
            # the publisher ends after its last frame; the subscriber then gets DRAIN_SEC for
            # what is still on its way, and is stopped if frames never came
            finished = run.wait(['demo_publisher'], timeout=args.seconds + 90.0,
                                fail_fast=True)
            if finished:
                drained = run.wait(['demo_subscriber'], timeout=DRAIN_SEC, fail_fast=True)
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
    if sub.get('publishers', 1) > 1:
        print('\n' + explain_other_publishers(sub['publishers']))
    lost = lost_frames(pub, sub)
    if lost:
        print('\n' + explain_loss(args, lost, pub['published'] - sub['distinct'], drained))
    ok = (not lost and sub['distinct'] == count and sub['duplicates'] == 0 and
          sub['checksum_failures'] == 0)
    return 0 if ok else 1


def lost_frames(pub: dict, sub: dict) -> List[int]:
    """Counters of frames the publisher sent and the subscriber never saw (the subscriber's
    report lists the first 20 it missed, and those after its last frame)."""
    published = pub.get('published', 0)
    last = sub.get('last_frame')
    after_last = range(last + 1 if last is not None else 0, published)
    return sorted(set(sub.get('missing', [])) | set(after_last))


def explain_other_publishers(count: int) -> str:
    """The subscriber matched ``count`` publishers of /demo/image: what that does to the
    counts, in words."""
    return (f'demo: the subscriber matched {count} publishers on {TOPIC}: another demo (or '
            'image_publisher) runs in this ROS domain, and its frames, numbered from 0 too, count '
            "as this demo's duplicates. Run one demo at a time, or each in a domain of its own "
            '(ROS_DOMAIN_ID=<n> ./dev demo).')


def explain_loss(args: argparse.Namespace, lost: List[int], total: int, drained: bool) -> str:
    """Which frames were lost (``total`` of them, the first of which are ``lost``), and the
    likely reason, in words."""
    total = max(total, len(lost))
    shown = ', '.join(str(c) for c in lost[:20]) + (' ...' if total > min(len(lost), 20) else '')
    lines = [f'demo: {total} frame{"s" if total != 1 else ""} published and never '
             f'received: {shown}.']
    busy = (f'--slow-subscriber {args.slow_subscriber:g} s per frame' if args.slow_subscriber
            else 'a moment of machine load')
    lines.append(
        f'Likely why: a KEEP_LAST history of depth {args.depth} holds {args.depth} '
        f'frame{"s" if args.depth != 1 else ""} the subscriber has not taken; while it is busy '
        f'({busy}), a newer frame replaces the oldest of them. A larger --depth keeps more (the '
        'default, 30, is one second at 30 Hz).')
    if not drained:
        lines.append(f'The subscriber was stopped {DRAIN_SEC:g} s after the publisher ended, '
                     'still waiting for them.')
    return '\n'.join(lines)


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
    print('\n' + LEGEND)


if __name__ == '__main__':
    sys.exit(main())
