"""Subscriber churn: what it costs the steady subscribers, ours against the same graph of stock
endpoints, and what the publisher writes to peers that cannot use it.

The graph: a publisher of ``--payload`` at ``--rate`` Hz (RELIABLE KEEP_LAST 50) with three
steady subscribers (one accepting ``demo``, one CPU only, one plain rclpy), while one subscriber
process after another comes for ``--come-go`` seconds and leaves (Ctrl-C), and another is started
and SIGKILLed every ``--kill-every`` seconds. ``ours``: a demo publisher and buffer-aware
subscribers (the plain one stays plain); ``stock``: the same processes with stock endpoints.
``--load N`` adds N busy processes (a loaded machine). Both graphs run one after the other, in
``--rounds`` rounds.

Printed per graph: frames each steady subscriber received of those published (for ``ours``'
demo subscriber, how many as zero-copy Buffers), and the ``ours`` publisher's CPU copies on
channels to peers that share the frame's backend (``cpu_copies_to_buffer_capable_peers``: the
backend declined to describe the frame for them); under the table, the frames a steady
subscriber missed (the first 20). It asserts nothing about time.

``python -m launch_free_demos.bench.churn [--seconds 20] [--payload 1920x1080] [--load 2]``
"""
import argparse
import multiprocessing
import re
import sys
import time
from typing import Dict, List, Tuple

from launch_free_demos.runner import NodeProcess, Run

STEADY = {'demo': {'acceptable_buffer_backends': 'demo'}, 'cpu': {}, 'plain': {'legacy': True}}

#: What a steady subscriber logs once it has frames (its summary, every REPORT_SEC).
FIRST_FRAMES = re.compile(r'\breceived [1-9][0-9]* \(')
REPORT_SEC = 0.1
#: How long the steady subscribers may take to get their first frame.
START_TIMEOUT_SEC = 60.0

#: After the last frame: how long the publisher stays for subscribers still taking, and then
#: how long the steady subscribers may go on taking what is in flight. A subscriber that got
#: every frame leaves at once; one that lost some (stock's under load) would otherwise keep
#: the graph up for nothing: a RELIABLE sample not in flight 4 s after the last frame is lost.
#: (2 s was once too short for a plain subscriber beside four busy processes on 2 cores.)
DRAIN_SEC = 4.0


def _busy(stop) -> None:
    while not stop.is_set():
        sum(range(10000))


def _wait_for_first_frames(run: Run, labels: List[str]) -> None:
    """Until each of ``labels`` logged frames (or exited, or START_TIMEOUT_SEC passed: the
    table then shows what it got)."""
    deadline = time.monotonic() + START_TIMEOUT_SEC
    waiting = set(labels)
    while waiting and time.monotonic() < deadline:
        for label in list(waiting):
            node = run.nodes[label]
            if node.process.poll() is not None or any(
                    FIRST_FRAMES.search(line) for line in list(node.stderr)):
                waiting.discard(label)
        time.sleep(0.05)


def run_graph(ours: bool, seconds: float, width: int, height: int, rate: float,
              come_go: float, kill_every: float) -> Dict[str, object]:
    topic = f'/churn_{"ours" if ours else "stock"}_{time.monotonic_ns()}'
    count = int(seconds * rate)
    common = {'topic': topic, 'depth': 50, 'timeout_sec': seconds + 60.0,
              'report_period_sec': REPORT_SEC}
    with Run() as run:
        for label, params in STEADY.items():
            run.start(label, 'image_subscriber', expected_count=count, **common,
                      **(params if ours else {'legacy': True}))
        run.start('pub', 'image_publisher', topic=topic, depth=50, count=count, rate_hz=rate,
                  width=width, height=height, wait_for_subscribers=3, wait_timeout_sec=60.0,
                  linger_sec=DRAIN_SEC, **({'backend': 'demo', 'wait_for_buffer_peers': 2}
                                     if ours else {'legacy': True}))
        # the churners come once every steady subscriber has frames: the publisher's wait for
        # three subscriptions (two served on channels) then counts the steady ones in both
        # graphs. A churner counted instead let the publisher start while a steady one had not
        # matched, and that one lost the first frames (a volatile reader), in one graph only.
        _wait_for_first_frames(run, list(STEADY))
        churn = {'acceptable_buffer_backends': 'demo'} if ours else {'legacy': True}
        # label -> (period, how the previous one ends: Ctrl-C or SIGKILL), next start
        churners = {'come_go': (come_go, NodeProcess.stop),
                    'killed': (kill_every, NodeProcess.kill)}
        started = time.monotonic()
        next_at = {'come_go': started, 'killed': started + kill_every / 2}
        while run.nodes['pub'].process.poll() is None:
            now = time.monotonic()
            for label, (period, end) in churners.items():
                if now >= next_at[label]:
                    if label in run.nodes:
                        end(run.nodes[label])
                    run.start(label, 'image_subscriber', topic=topic, depth=50,
                              timeout_sec=period + 30.0, **churn)
                    next_at[label] = now + period
            time.sleep(0.05)
        for label in ('come_go', 'killed'):
            if label in run.nodes:
                run.nodes[label].kill()
        run.wait(list(STEADY), DRAIN_SEC)  # what they still take; Ctrl-C, they report
        run.stop_all()
        reports = run.reports()
    result: Dict[str, object] = {label: (reports.get(label) or {}).get('distinct', 0)
                                 for label in STEADY}
    result['missing'] = {label: (reports.get(label) or {}).get('missing', 'no report')
                         for label in STEADY
                         if (reports.get(label) or {}).get('distinct', 0) != count}
    pub = reports.get('pub') or {}
    result['published'] = pub.get('published', 0)
    stats = pub.get('statistics') or {}
    result['cpu_to_capable'] = stats.get('cpu_copies_to_buffer_capable_peers', '-')
    result['zero_copy'] = ((reports.get('demo') or {}).get('backends') or {}).get('demo', 0)
    return result


def table(rows: List[Tuple[str, Dict[str, object]]], payload: str, rate: float, seconds: float,
          come_go: float, kill_every: float, load: int) -> str:
    """A markdown table, a row per graph run (see :func:`run_graph`), with its caption."""
    lines = [f'churn: {payload} rgb8 at {rate:g} Hz for {seconds:g} s, a subscriber coming and '
             f'going every {come_go:g} s, one SIGKILLed every {kill_every:g} s, {load} busy '
             'processes',
             '| graph | published | steady demo (of them zero-copy) | steady cpu | steady plain '
             '| CPU copies to backend-capable peers |',
             '|---|---|---|---|---|---|']
    for graph, r in rows:
        zero_copy = f' ({r["zero_copy"]})' if graph == 'ours' else ''
        lines.append(f'| {graph} | {r["published"]} | {r["demo"]}{zero_copy} | {r["cpu"]} | '
                     f'{r["plain"]} | {r["cpu_to_capable"] if graph == "ours" else "-"} |')
    missed = [f'{graph} {label}: frames {frames} missing' for graph, r in rows
              for label, frames in r['missing'].items()]
    return '\n'.join(lines + (['', *missed] if missed else []))


def main(argv: List[str] = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m launch_free_demos.bench.churn',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--payload', default='1920x1080', help='WIDTHxHEIGHT rgb8')
    parser.add_argument('--rate', type=float, default=30.0)
    parser.add_argument('--come-go', type=float, default=2.0)
    parser.add_argument('--kill-every', type=float, default=3.0)
    parser.add_argument('--load', type=int, default=0, help='busy processes beside the graph')
    parser.add_argument('--rounds', type=int, default=1)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.payload.lower().split('x'))
    stop = multiprocessing.Event()
    busy = [multiprocessing.Process(target=_busy, args=(stop,), daemon=True)
            for _ in range(args.load)]
    for process in busy:
        process.start()
    rows = []
    try:
        for _ in range(args.rounds):
            for ours in (False, True):
                rows.append(('ours' if ours else 'stock', run_graph(
                    ours, args.seconds, width, height, args.rate, args.come_go,
                    args.kill_every)))
    finally:
        stop.set()
        for process in busy:
            process.join(5)
    print(table(rows, args.payload, args.rate, args.seconds, args.come_go, args.kill_every,
                args.load))
    return 0


if __name__ == '__main__':
    sys.exit(main())
