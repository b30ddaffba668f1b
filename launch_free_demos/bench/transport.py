"""Cross-process latency: stock rclpy, this package's CPU path and the demo backend.

For each payload, a publisher process sends ``--frames`` frames at ``--rate`` Hz to a subscriber
process; the subscriber measures publish -> callback latency (wall clock, same machine) and
verifies every frame's checksum. Prints a markdown table of medians and p90s and the ratios the
project targets. With ``--rounds N`` every payload is measured N times, payloads and transports
interleaved round by round, and each cell is the median over the rounds (run-to-run noise on a
shared machine is larger than the differences at small payloads). With 1 KiB and 3840x2160
both measured, it prints a 4K demo frame's p50 against stock's 1 KiB message, per round.

``--attribution`` adds two variants to each round, which say what of that ratio is not this
package's per-message work: the demo backend with its channels on Fast DDS's shared memory
instead of UDP (``ROSIDL_BUFFER_PY_CHANNEL_TRANSPORT=participant``; design.md says why channels
listen on UDP), and stock rclpy's 1 KiB message from a publisher that fills and checksums a 4K
frame's bytes of other memory before each frame (``scratch_bytes``), as a 4K frame's publisher
does before its stamp: the same small message on the caches a big frame leaves. A benchmark: it
prints, it asserts nothing. ``./dev bench transport``.
"""
import argparse
import os
import statistics
import sys
from typing import Dict, NamedTuple, Optional

from launch_free_demos.bench.stats import per_round_line
from launch_free_demos.runner import NodeProcess, Run

PAYLOADS = [  # label, width, height, encoding
    ('1 KiB', 1024, 1, 'mono8'),
    ('1 MiB', 1024, 1024, 'mono8'),
    ('1920x1080 rgb8', 1920, 1080, 'rgb8'),
    ('3840x2160 rgb8', 3840, 2160, 'rgb8'),
]
TRANSPORTS = {  # label: (publisher executable, backend, subscriber executable, accept)
    'stock rclpy': ('legacy_image_publisher', 'cpu', 'legacy_image_subscriber', None),
    'rosidl_buffer_py cpu': ('image_publisher', 'cpu', 'image_subscriber', 'cpu'),
    'rosidl_buffer_py demo': ('image_publisher', 'demo', 'image_subscriber', 'demo'),
}
FOUR_K = 3840 * 2160 * 3  #: bytes of a 3840x2160 rgb8 frame


class Variant(NamedTuple):
    """A transport of :data:`TRANSPORTS` measured another way (``--attribution``)."""

    transport: str  #: the key of :data:`TRANSPORTS` it varies
    env: Dict[str, str]  #: for both processes
    publisher: Dict[str, object]  #: more image_publisher parameters
    payload: Optional[str] = None  #: the one payload it is measured with (None: every one)


VARIANTS = {
    'demo, channels on SHM': Variant(
        'rosidl_buffer_py demo', {'ROSIDL_BUFFER_PY_CHANNEL_TRANSPORT': 'participant'}, {}),
    'stock rclpy, 4K fill before': Variant('stock rclpy', {}, {'scratch_bytes': FOUR_K}, '1 KiB'),
}


def measure(transport: str, width: int, height: int, encoding: str, frames: int,
            rate: float, variant: Optional[Variant] = None) -> dict:
    pub_exe, backend, sub_exe, accept = TRANSPORTS[transport]
    topic = '/bench/image'
    # the subscriber's timeout covers discovery, the frames and the publisher's linger
    sub_params = dict(topic=topic, expected_count=frames, timeout_sec=frames / rate + 60.0)
    pub_params = dict(topic=topic, count=frames, rate_hz=rate, wait_for_subscribers=1,
                      linger_sec=20.0, width=width, height=height, encoding=encoding)
    if accept is not None:
        sub_params['acceptable_buffer_backends'] = accept
        pub_params.update(backend=backend, wait_for_buffer_peers=1)
    env = variant.env if variant is not None else {}
    if variant is not None:
        pub_params.update(variant.publisher)
    with Run() as run:
        run.add(NodeProcess('bench_sub', sub_exe, sub_params, env=env))
        run.add(NodeProcess('bench_pub', pub_exe, pub_params, env=env))
        run.wait(timeout=frames / rate + 150.0)
        run.stop_all()
        report = run.nodes['bench_sub'].report
    if report is None or not report['distinct'] or report['checksum_failures']:
        raise RuntimeError(f'{transport} {width}x{height}: failed run: {report}\n'
                           f'{run.diagnostics()}')
    if report['distinct'] != frames:  # a transport that loses frames is measured as it is
        print(f'{transport} {width}x{height}: {frames - report["distinct"]} of {frames} frames '
              f'lost (missing {report["missing"]})', file=sys.stderr, flush=True)
    return report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=30)
    parser.add_argument('--rate', type=float, default=10.0)
    parser.add_argument('--payloads', nargs='*', default=[p[0] for p in PAYLOADS],
                        help='labels from: ' + ', '.join(p[0] for p in PAYLOADS))
    parser.add_argument('--rounds', type=int, default=1,
                        help='measure each payload this many times, transports interleaved; '
                             'cells are medians over the rounds')
    parser.add_argument('--attribution', action='store_true',
                        help='also measure ' + ', '.join(VARIANTS) + ' (see above)')
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error(f'--rounds must be at least 1, got {args.rounds}')
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rounds = {}
    lost = []
    # round by round, every payload and transport in each: the cross-payload ratio below
    # compares measurements made minutes apart at most, as the transports of one payload
    for index in range(args.rounds):
        for label, width, height, encoding in PAYLOADS:
            if label not in args.payloads:
                continue
            measured = [(transport, None) for transport in TRANSPORTS]
            if args.attribution:
                measured += [(name, variant) for name, variant in VARIANTS.items()
                             if variant.payload in (None, label)]
            for transport, variant in measured:
                report = measure(variant.transport if variant else transport, width, height,
                                 encoding, args.frames, args.rate, variant)
                rounds.setdefault((label, transport), []).append(report['latency_ms'])
                if report['distinct'] != args.frames:
                    lost.append(f'{label}, {transport}, round {index + 1}: '
                                f'{args.frames - report["distinct"]} of {args.frames} lost')
                lat = report['latency_ms']
                print(f'{label:>16} {transport:<22} round {index + 1}/{args.rounds} p50 '
                      f'{lat["p50"]:9.3f} ms  p90 {lat["p90"]:9.3f} ms  backends '
                      f'{report["backends"]}', file=sys.stderr, flush=True)
    results = {key: {'latency_ms': {q: statistics.median(r[q] for r in runs)
                                    for q in ('p50', 'p90')}}
               for key, runs in rounds.items()}
    over = f', medians over {args.rounds} interleaved rounds' if args.rounds > 1 else ''
    print(f'\nLatency publish -> callback in ms, median / p90 of {args.frames} frames at '
          f'{args.rate:g} Hz{over}, publisher and subscriber in separate processes.\n')
    print('| payload | ' + ' | '.join(TRANSPORTS) + ' | cpu / stock | stock / demo |')
    print('|---' * (len(TRANSPORTS) + 3) + '|')
    per_round = []
    for label, *_ in PAYLOADS:
        if (label, 'stock rclpy') not in results:
            continue
        cells = [f"{results[(label, t)]['latency_ms']['p50']:.2f} / "
                 f"{results[(label, t)]['latency_ms']['p90']:.2f}" for t in TRANSPORTS]
        stock = results[(label, 'stock rclpy')]['latency_ms']['p50']
        cpu = results[(label, 'rosidl_buffer_py cpu')]['latency_ms']['p50']
        demo = results[(label, 'rosidl_buffer_py demo')]['latency_ms']['p50']
        print(f'| {label} | ' + ' | '.join(cells) + f' | {cpu / stock:.2f} | {stock / demo:.1f} |')
        if args.rounds > 1:
            ratios = [c['p50'] / s['p50'] for c, s in zip(
                rounds[(label, 'rosidl_buffer_py cpu')], rounds[(label, 'stock rclpy')])]
            per_round.append(per_round_line(f'{label}: CPU path / stock p50', ratios))
    if per_round:
        print('\n' + '\n'.join(per_round))
    if lost:
        print('\nFrames lost (latency figures are over the frames that arrived): '
              + '; '.join(lost))
    small, big = ('1 KiB', 'rosidl_buffer_py demo'), ('3840x2160 rgb8', 'rosidl_buffer_py demo')
    if small in results and big in results:
        print(f"\ndemo 3840x2160 / demo 1 KiB latency: "
              f"{results[big]['latency_ms']['p50'] / results[small]['latency_ms']['p50']:.2f}")
        # what a 4K zero-copy frame costs against the smallest stock message (issue #30's
        # target: at most 1.0), round by round
        ratios = [b['p50'] / s['p50'] for b, s in zip(rounds[big],
                                                      rounds[('1 KiB', 'stock rclpy')])]
        print(per_round_line('demo 3840x2160 / stock 1 KiB p50', ratios))
    if args.attribution:
        print_attribution(rounds)
    return 0


def print_attribution(rounds: Dict[tuple, list]) -> None:
    """The variants' p50 against what they vary, per round (``--attribution``)."""
    def per_round(what: str, over: tuple, under: tuple) -> None:
        if over in rounds and under in rounds:
            print(per_round_line(f'{what} p50', [o['p50'] / u['p50'] for o, u in zip(
                rounds[over], rounds[under])]))

    filled = ('1 KiB', 'stock rclpy, 4K fill before')
    print('\nAttribution:')
    for label, *_ in PAYLOADS:
        per_round(f'{label}: demo, channels on SHM / demo (on UDP)',
                  (label, 'demo, channels on SHM'), (label, 'rosidl_buffer_py demo'))
    per_round('1 KiB: stock rclpy, 4K fill before / stock rclpy', filled, ('1 KiB', 'stock rclpy'))
    per_round('demo 3840x2160 / stock 1 KiB with a 4K fill before',
              ('3840x2160 rgb8', 'rosidl_buffer_py demo'), filled)
    per_round('demo 3840x2160, channels on SHM / stock 1 KiB with a 4K fill before',
              ('3840x2160 rgb8', 'demo, channels on SHM'), filled)


if __name__ == '__main__':
    sys.exit(main())
