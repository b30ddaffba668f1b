"""What a legacy listener costs the buffer-aware subscribers beside it: CPU per frame per process.

Graphs, each a demo publisher (frames filled in place) of ``--payload`` at ``--rate`` Hz:

- ``pure``: one subscriber accepting ``demo``;
- ``mixed``: the same, plus one plain rclpy subscriber (what rviz or a bag recorder is);
- ``stock``: a stock rclpy publisher and one plain rclpy subscriber (the reference for what the
  publisher pays to serve a legacy subscriber);
- ``stock mixed``: ``mixed`` with stock endpoints only (the demo subscriber's place taken by a
  plain subscriber): what the same graph costs without this package;
- ``cpu``, ``cpu mixed``: ``pure`` and ``mixed`` with a publisher of CPU frames (the
  buffer-aware subscriber then gets whole frames on its channel; its column is still "demo");
- ``pure 2``, ``pure 4``: ``pure`` with 2 and 4 subscribers accepting ``demo`` (the
  publisher's column: what each more zero-copy subscriber costs it);
- ``neighbour``: ``pure``, with a stock publisher and a plain subscriber of the same frames on
  *another* topic: the machine as loaded as in ``mixed`` (two more processes copying 25 MB
  frames, on 2 cores), with nothing shared. What ``mixed`` costs the demo subscriber beyond this
  is what the legacy listener's traffic costs it; the rest is the neighbours' load (CPU caches,
  memory bandwidth) on its own per-frame work (a CRC32 of every frame).

CPU per frame is differential, so start-up and discovery cancel out: every graph runs twice,
with ``--frames`` and with ``--frames`` + ``--extra`` frames, and each process's CPU time
(``os.wait4`` rusage, all threads) of the short run is subtracted from the long run's and divided
by ``--extra``. Every frame is checked (counter and CRC32) by every subscriber. It prints a
table; it asserts nothing about time.

``--threads`` shows instead where the demo subscriber's CPU goes, by thread (the executor,
Fast DDS's receive and event threads) with their wake-ups per frame: what a legacy listener's
traffic costs it, thread by thread.

``python -m launch_free_demos.bench.mixed [--payload 3840x2160] [--rate 10] [--rounds 2]
[--threads]``
"""
import argparse
import os
import statistics
import sys
import time
from typing import Dict, List, NamedTuple, Tuple

from launch_free_demos.bench.measured import MeasuredRun

GRAPHS: Dict[str, List[Tuple[str, str, dict]]] = {
    # label -> [(node label, executable, parameters)]: subscribers first, the publisher last
    'pure': [('demo_sub', 'image_subscriber', {'acceptable_buffer_backends': 'demo'}),
             ('pub', 'image_publisher', {'backend': 'demo', 'fill': 'allocate',
                                         'wait_for_buffer_peers': 1})],
    'mixed': [('demo_sub', 'image_subscriber', {'acceptable_buffer_backends': 'demo'}),
              ('plain_sub', 'legacy_image_subscriber', {}),
              ('pub', 'image_publisher', {'backend': 'demo', 'fill': 'allocate',
                                          'wait_for_buffer_peers': 1})],
    'stock': [('plain_sub', 'legacy_image_subscriber', {}),
              ('pub', 'legacy_image_publisher', {})],
    'stock mixed': [('demo_sub', 'legacy_image_subscriber', {}),
                    ('plain_sub', 'legacy_image_subscriber', {}),
                    ('pub', 'legacy_image_publisher', {})],
    # a publisher of CPU frames: buffer-aware subscribers get the whole frame on their channel
    'cpu': [('demo_sub', 'image_subscriber', {}),
            ('pub', 'image_publisher', {'backend': 'cpu', 'wait_for_buffer_peers': 1})],
    'cpu mixed': [('demo_sub', 'image_subscriber', {}),
                  ('plain_sub', 'legacy_image_subscriber', {}),
                  ('pub', 'image_publisher', {'backend': 'cpu', 'wait_for_buffer_peers': 1})],
    # the publisher's cost in the number of zero-copy subscribers (1: pure)
    'pure 2': [*[(f'demo_sub{n}', 'image_subscriber', {'acceptable_buffer_backends': 'demo'})
                 for n in ('', '2')],
               ('pub', 'image_publisher', {'backend': 'demo', 'fill': 'allocate',
                                           'wait_for_buffer_peers': 2})],
    'pure 4': [*[(f'demo_sub{n}', 'image_subscriber', {'acceptable_buffer_backends': 'demo'})
                 for n in ('', '2', '3', '4')],
               ('pub', 'image_publisher', {'backend': 'demo', 'fill': 'allocate',
                                           'wait_for_buffer_peers': 4})],
    'neighbour': [('demo_sub', 'image_subscriber', {'acceptable_buffer_backends': 'demo'}),
                  ('plain_sub', 'legacy_image_subscriber', {'topic_suffix': '_neighbour'}),
                  ('neighbour_pub', 'legacy_image_publisher', {'topic_suffix': '_neighbour'}),
                  ('pub', 'image_publisher', {'backend': 'demo', 'fill': 'allocate',
                                              'wait_for_buffer_peers': 1})],
}


def start_graph(run: MeasuredRun, graph: str, width: int, height: int, frames: int,
                rate: float, topic: str, depth: int, **subscriber_params) -> Dict[str, object]:
    """Start ``graph``'s nodes in ``run``, subscribers first: ``frames`` frames at ``rate`` Hz
    on ``topic`` (plus each node's suffix), every publisher waiting for its topic's
    subscribers. Their MeasuredNodes by label."""
    nodes = GRAPHS[graph]
    started = {}
    for label, executable, params in nodes:
        params = dict(params)
        suffix = params.pop('topic_suffix', '')
        subscribers = sum(1 for _, exe, other in nodes if exe.endswith('subscriber')
                          and other.get('topic_suffix', '') == suffix)
        params.update(topic=topic + suffix, width=width, height=height, encoding='rgb8',
                      depth=depth)
        if executable.endswith('publisher'):
            params.update(count=frames, rate_hz=rate, wait_for_subscribers=subscribers,
                          wait_timeout_sec=30.0, linger_sec=3.0)
        else:
            params.update(expected_count=frames, timeout_sec=60.0 + frames / rate,
                          **subscriber_params)
        started[label] = run.start(label, executable, **params)
    return started


def run_graph(graph: str, width: int, height: int, frames: int, rate: float,
              topic: str) -> Dict[str, float]:
    """CPU seconds of each process for one run of ``frames`` frames; also checks delivery."""
    nodes = GRAPHS[graph]
    with MeasuredRun() as run:
        started = start_graph(run, graph, width, height, frames, rate, topic, depth=frames)
        deadline = time.monotonic() + 90.0 + frames / rate
        while not all([node.try_reap() for node in started.values()]) and \
                time.monotonic() < deadline:
            time.sleep(0.05)  # reaped with os.wait4 (MeasuredNode), which keeps the rusage
        run.stop_all()
        reports = run.reports()
    for label, executable, _ in nodes:
        report = reports.get(label)
        if executable.endswith('subscriber') and (report is None or report['distinct'] != frames
                                                 or report['checksum_failures']):
            raise RuntimeError(f'{graph}: {label} did not get every frame intact: {report}')
    for label in started:  # where the frames went (stderr: the table stays on stdout)
        stats = (reports.get(label) or {}).get('statistics') or {}
        counters = [f'{k}={stats[k]}' for k in ('from_main_topic', 'from_channels',
                    'duplicates_dropped', 'sent_on_main_topic', 'main_topic_withheld',
                    'main_topic_doubled')
                    if k in stats]
        if counters:
            print(f'bench_mixed: {graph}, {frames} frames, {label}: ' + ', '.join(counters),
                  file=sys.stderr)
    cpu = {}
    for label, node in started.items():
        usage = node.rusage
        cpu[label] = usage.ru_utime + usage.ru_stime
    return cpu


def run_latency(graph: str, width: int, height: int, frames: int, rate: float, depth: int,
                topic: str, patience: float = 60.0) -> Dict[str, dict]:
    """One run of ``graph``: each subscriber's latency percentiles (ms, publisher's stamp to
    the callback), how many frames came over 200 ms late and how many never came (a reliable
    KEEP_LAST writer drops a sample not acknowledged before ``depth`` newer ones); checks
    the frames' contents. A subscriber missing frames gives up ``patience`` seconds after the
    last frame is due."""
    nodes = GRAPHS[graph]
    with MeasuredRun() as run:
        started = {}
        subscribers = sum(1 for _, exe, other in nodes if exe.endswith('subscriber')
                          and not other.get('topic_suffix'))
        for label, executable, params in nodes:
            params = dict(params)
            suffix = params.pop('topic_suffix', '')
            params.update(topic=topic + suffix, width=width, height=height, encoding='rgb8',
                          depth=depth)
            if executable.endswith('publisher'):
                params.update(count=frames, rate_hz=rate, wait_timeout_sec=30.0, linger_sec=3.0,
                              wait_for_subscribers=subscribers if not suffix else 1)
            else:
                params.update(expected_count=frames, timeout_sec=patience + frames / rate)
            started[label] = run.start(label, executable, **params)
        deadline = time.monotonic() + patience + 30.0 + frames / rate
        while not all([node.try_reap() for node in started.values()]) and \
                time.monotonic() < deadline:
            time.sleep(0.05)
        run.stop_all()
        reports = run.reports()
    result = {}
    for label, executable, _ in nodes:
        report = reports.get(label)
        if not executable.endswith('subscriber') or label.startswith('neighbour'):
            continue
        if report is None or report['checksum_failures'] or not report['distinct']:
            raise RuntimeError(f'{graph}: {label} did not get its frames intact: {report}')
        stats = report.get('statistics') or {}
        result[label] = dict(report['latency_ms'], late=report.get('late_over_200ms'),
                             lost=frames - report['distinct'],
                             channels=stats.get('from_channels'),
                             main=stats.get('from_main_topic'))
    return result


#: Clock ticks per second of /proc/<pid>/task/<tid>/stat's CPU times.
_TICKS = os.sysconf('SC_CLK_TCK')


class ThreadSample(NamedTuple):
    """One thread's counters at one moment."""

    group: str         #: its name without its number (``main`` for the main thread)
    cpu_seconds: float
    switches: int      #: voluntary context switches: its wake-ups


class ThreadCost(NamedTuple):
    """A thread group's cost per frame over a run."""

    cpu_ms: float
    wakeups: float


def thread_sample(pid: int) -> Dict[str, ThreadSample]:
    """Per thread id of ``pid``, its :class:`ThreadSample`. Fast DDS names its threads
    (``dds.shm.<port>``, ``dds.udp.<port>``, ``dds.ev.<n>``...): the group is the name without
    its number; the main thread is ``main``, other unnamed ones ``python``."""
    sample = {}
    try:
        tids = os.listdir(f'/proc/{pid}/task')
    except OSError:
        return sample
    for tid in tids:
        try:
            with open(f'/proc/{pid}/task/{tid}/stat') as f:
                stat = f.read()
            with open(f'/proc/{pid}/task/{tid}/comm') as f:
                name = f.read().strip()
            with open(f'/proc/{pid}/task/{tid}/status') as f:
                switches = next(int(line.split()[1]) for line in f
                                if line.startswith('voluntary_ctxt_switches'))
        except (OSError, StopIteration):
            continue
        fields = stat[stat.rindex(')') + 2:].split()
        group = 'main' if int(tid) == pid else name.rstrip('0123456789').rstrip('.') or name
        sample[tid] = ThreadSample(group, (int(fields[11]) + int(fields[12])) / _TICKS,
                                   switches)
    return sample


def run_threads(graph: str, width: int, height: int, frames: int, rate: float,
                topic: str) -> Dict[str, ThreadCost]:
    """The demo subscriber's threads over one run of ``graph``: per thread group, CPU ms and
    wake-ups (voluntary context switches) per frame, between its 5th frame and 3 frames
    before the last (start-up and teardown left out)."""
    with MeasuredRun() as run:
        started = start_graph(run, graph, width, height, frames, rate, topic, depth=10,
                              report_period_sec=0.2)
        sub = started['demo_sub']

        def frames_now() -> int:
            sub.read_log()
            return sub.distinct_now()

        deadline = time.monotonic() + 90.0 + frames / rate
        while frames_now() < 5 and time.monotonic() < deadline and not sub.try_reap():
            time.sleep(0.02)
        first, first_frames = thread_sample(sub.process.pid), frames_now()
        while frames_now() < frames - 3 and time.monotonic() < deadline and not sub.try_reap():
            time.sleep(0.02)
        last, last_frames = thread_sample(sub.process.pid), frames_now()
        while not all([node.try_reap() for node in started.values()]) and \
                time.monotonic() < deadline:
            time.sleep(0.05)
        run.stop_all()
    counted = last_frames - first_frames
    if counted < 1:
        raise RuntimeError(f'{graph}: the demo subscriber got no frames to measure between its '
                           f'5th and its {frames - 3}th of {frames}')
    costs: Dict[str, ThreadCost] = {}
    for tid, now in last.items():
        before = first.get(tid, ThreadSample(now.group, 0.0, 0))  # a thread started between
        cost = costs.get(now.group, ThreadCost(0.0, 0.0))
        costs[now.group] = ThreadCost(
            cost.cpu_ms + (now.cpu_seconds - before.cpu_seconds) * 1000.0 / counted,
            cost.wakeups + (now.switches - before.switches) / counted)
    return costs


def threads_table(results: Dict[str, List[Dict[str, ThreadCost]]],
                  graphs: List[str], payload: str, rate: float, frames: int) -> str:
    """A markdown table: per graph, the demo subscriber's CPU and wake-ups per frame by thread
    group (medians over rounds)."""
    groups = sorted({g for runs in results.values() for run in runs for g in run},
                    key=lambda g: (g != 'main', g))
    lines = [f'The demo subscriber\'s threads, {payload} rgb8 at {rate:g} Hz, {frames} frames '
             'per run: CPU ms / wake-ups per frame (median of the runs; wake-ups are voluntary '
             'context switches). main: the executor and callbacks (its CRC32 of every frame '
             'included); dds.*: Fast DDS\'s threads.\n',
             '| graph | total CPU | ' + ' | '.join(groups) + ' |',
             '|---|---|' + '---|' * len(groups)]
    for graph in graphs:
        runs = results.get(graph, [])
        total = statistics.median(sum(c.cpu_ms for c in run.values()) for run in runs)
        cells = []
        for group in groups:
            values = [run[group] for run in runs if group in run]
            cells.append('-' if not values else
                         f'{statistics.median(c.cpu_ms for c in values):.2f} / '
                         f'{statistics.median(c.wakeups for c in values):.0f}')
        lines.append(f'| {graph} | {total:.2f} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def latency_table(results: Dict[str, List[Dict[str, dict]]], graphs: List[str], payload: str,
                  rate: float, frames: int, depth: int) -> str:
    """A markdown table: per graph and run, the demo and plain subscribers' latencies."""
    lines = [f'Latency, ms, publisher stamp -> subscriber callback, {payload} rgb8 at {rate:g} '
             f'Hz, {frames} frames, depth {depth}, each run on its own line; late: frames over '
             '200 ms; lost: frames never received.\n',
             '| graph | demo p50 | demo p90 | demo p99 | demo max | demo late | demo lost | '
             'plain p50 | plain p99 | plain late | demo p99 / plain p99 |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    for graph in graphs:
        for run in results.get(graph, []):
            demo = run.get('demo_sub')
            plain = run.get('plain_sub')
            cells = [f"{demo[k]:.1f}" if demo else '-' for k in ('p50', 'p90', 'p99', 'max')]
            cells += [str(demo[k]) if demo else '-' for k in ('late', 'lost')]
            cells += [f"{plain[k]:.1f}" if plain else '-' for k in ('p50', 'p99')]
            cells.append(str(plain['late']) if plain else '-')
            cells.append(f"{demo['p99'] / plain['p99']:.2f}" if demo and plain and plain['p99']
                         else '-')
            lines.append(f'| {graph} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def measure(width: int, height: int, rate: float, frames: int, extra: int, rounds: int,
            graphs: List[str]) -> Dict[Tuple[str, str], List[float]]:
    """(graph, process label) -> CPU ms per frame of each round."""
    per_frame: Dict[Tuple[str, str], List[float]] = {}
    serial = 0
    for _ in range(rounds):
        for graph in graphs:
            totals = []
            for count in (frames, frames + extra):
                serial += 1
                topic = f'/bench_mixed_{os.getpid()}/{graph.replace(" ", "_")}_{serial}'
                totals.append(run_graph(graph, width, height, count, rate, topic))
            for label in totals[0]:
                per_frame.setdefault((graph, label), []).append(
                    (totals[1][label] - totals[0][label]) * 1000.0 / extra)
    return per_frame


def table(per_frame: Dict[Tuple[str, str], List[float]], graphs: List[str], payload: str,
          rate: float, frames: int, extra: int, rounds: int) -> str:
    """A markdown table of the medians (every round in parentheses), with its caption."""
    lines = [f'CPU per frame of each process, ms (median of {rounds} rounds; each: '
             f'({frames}+{extra} frames) - ({frames} frames), / {extra}), {payload} rgb8 at '
             f'{rate:g} Hz, demo frames filled in place. pure: a demo publisher and a '
             'subscriber accepting demo; mixed: the same and a plain rclpy subscriber; stock: '
             'a stock publisher and a plain rclpy subscriber; stock mixed: mixed with stock '
             'endpoints only (a plain subscriber in the demo subscriber\'s column); neighbour: '
             'pure, beside a stock publisher and a plain subscriber on another topic.\n',
             '| graph | demo subscriber | plain subscriber | publisher |', '|---|---|---|---|']
    for graph in graphs:
        cells = []
        for label in ('demo_sub', 'plain_sub', 'pub'):
            values = per_frame.get((graph, label))
            cells.append('-' if not values else f'{statistics.median(values):.2f} ('
                         + ', '.join(f'{v:.1f}' for v in values) + ')')
        lines.append(f'| {graph} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--payload', default='3840x2160', help='WIDTHxHEIGHT of rgb8 frames')
    parser.add_argument('--rate', type=float, default=10.0)
    parser.add_argument('--frames', type=int, default=10, help='frames of the short run')
    parser.add_argument('--extra', type=int, default=40, help='more frames in the long run')
    parser.add_argument('--rounds', type=int, default=2, help='repeats (medians are shown)')
    parser.add_argument('--graphs', default='pure,mixed,neighbour,stock,stock mixed')
    parser.add_argument('--latency', action='store_true',
                        help='measure latency instead of CPU: --frames frames per run, each '
                        'graph --rounds times (interleaved), at --depth')
    parser.add_argument('--depth', type=int, default=10, help='QoS depth (with --latency)')
    parser.add_argument('--threads', action='store_true',
                        help="the demo subscriber's CPU and wake-ups per frame by thread "
                        '(Fast DDS threads apart) instead of each process\'s CPU: --frames '
                        'frames per run, each graph --rounds times (interleaved)')
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.payload.split('x'))
    graphs = [g.strip() for g in args.graphs.split(',') if g.strip()]
    unknown = [g for g in graphs if g not in GRAPHS]
    if unknown:
        parser.error(f'unknown graph(s) {unknown}; known: {", ".join(GRAPHS)}')
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if args.latency:
        results: Dict[str, List[Dict[str, dict]]] = {}
        serial = 0
        for _ in range(args.rounds):
            for graph in graphs:
                serial += 1
                topic = f'/bench_mixed_{os.getpid()}/{graph.replace(" ", "_")}_{serial}'
                run = run_latency(graph, width, height, args.frames, args.rate, args.depth,
                                  topic)
                print(f'bench_mixed: {graph}: {run}', file=sys.stderr, flush=True)
                results.setdefault(graph, []).append(run)
        print(latency_table(results, graphs, args.payload, args.rate, args.frames, args.depth))
        return 0
    if args.threads:
        by_thread: Dict[str, List[Dict[str, ThreadCost]]] = {}
        for serial in range(args.rounds * len(graphs)):
            graph = graphs[serial % len(graphs)]
            topic = f'/bench_mixed_{os.getpid()}/{graph.replace(" ", "_")}_t{serial}'
            by_thread.setdefault(graph, []).append(
                run_threads(graph, width, height, args.frames, args.rate, topic))
        print(threads_table(by_thread, graphs, args.payload, args.rate, args.frames))
        return 0
    per_frame = measure(width, height, args.rate, args.frames, args.extra, args.rounds, graphs)
    print(table(per_frame, graphs, args.payload, args.rate, args.frames, args.extra,
                args.rounds))
    return 0


if __name__ == '__main__':
    sys.exit(main())
