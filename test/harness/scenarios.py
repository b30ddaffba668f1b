"""Named multi-process scenarios: upstream's launch tests, runnable without ros2 launch.

Each scenario starts publisher and subscriber node processes, waits for the subscribers'
reports and checks them: every frame exactly once, checksums right, and the payload backend each
subscriber must see. ``.venv/bin/python test/harness/scenarios.py [NAME ...]`` runs them and
prints a table; the integration tests run the same scenarios.
"""
import argparse
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

if __package__ in (None, ''):  # run as a file: launch_free_demos (not installed) is the
    sys.path.append(str(Path(__file__).resolve().parents[2]))  # checkout's, after the others

from launch_free_demos.runner import Run  # noqa: E402 (after the path fix)

#: Frame size used by the scenarios (small: these check behaviour, the benchmark checks speed).
SMALL = {'width': 64, 'height': 48, 'encoding': 'rgb8'}
#: image_subscriber's summary line once it has a frame
FIRST_FRAMES = re.compile(r'\breceived [1-9][0-9]* \(')


@dataclass
class Sub:
    label: str
    expect_backend: Optional[str]  #: backend every frame must arrive as (None: do not check)
    acceptable: str = '__default__'
    legacy: bool = False
    raw: bool = False


@dataclass
class Pub:
    label: str
    backend: str = 'cpu'
    legacy: bool = False
    fill: str = 'allocate'


@dataclass
class Scenario:
    name: str
    description: str
    publishers: List[Pub]
    subscribers: List[Sub]
    count: int = 20
    subscribers_first: bool = True
    rate_hz: float = 50.0
    #: label of a subscriber to SIGKILL mid-stream: ``kill_after`` seconds after it logged
    #: its first frame (a timer from the publishers' start would, on a loaded machine, kill it
    #: before the publisher matched it, and the publisher would wait for it forever)
    kill: Optional[str] = None
    kill_after: float = 2.0
    #: how long publishers may take to leave once their subscribers are done (a SIGKILLed
    #: subscriber stays matched until its DDS lease expires, about 20 s by default)
    publisher_exit_timeout: float = 15.0
    #: KEEP_LAST depth of every endpoint; None: every frame of the run. The scenarios check
    #: that each frame arrives, which RELIABLE delivery promises only while the history holds
    #: what a stalled subscriber has not acknowledged yet: depth 10 at 50 Hz is 0.2 s, and a
    #: loaded CI machine stops processes for longer than that.
    depth: Optional[int] = None

    @property
    def topic(self) -> str:
        # one token, never starting with a digit (rcl rejects such tokens)
        return f'/scenario_{self.name}'

    def run(self, echo: bool = False, timeout: float = 60.0) -> 'Result':
        result = Result(self)
        total = self.count * len(self.publishers)
        buffer_subs = sum(1 for s in self.subscribers if not s.legacy)
        depth = self.depth or total
        with Run(echo=echo) as run:
            def start_subscribers():
                for sub in self.subscribers:
                    params = dict(topic=self.topic, expected_count=total,
                                  timeout_sec=timeout, depth=depth)
                    if sub.expect_backend:
                        params['expected_backend'] = sub.expect_backend
                    if sub.legacy:
                        params['raw'] = sub.raw
                    else:
                        params['acceptable_buffer_backends'] = sub.acceptable
                    if sub.label == self.kill:
                        params['report_period_sec'] = 0.1  # its first frame shows in its log
                    run.start(sub.label, 'legacy_image_subscriber' if sub.legacy
                              else 'image_subscriber', **params)

            def start_publishers():
                for index, pub in enumerate(self.publishers):
                    params = dict(topic=self.topic, backend=pub.backend,
                                  count=self.count, first_frame=index * self.count,
                                  rate_hz=self.rate_hz,
                                  wait_for_subscribers=len(self.subscribers), depth=depth,
                                  # before the subscribers give up: its report then says
                                  # what it matched, not what was left once they had gone
                                  wait_timeout_sec=timeout * 0.75,
                                  linger_sec=self.publisher_exit_timeout, **SMALL)
                    if not pub.legacy:
                        params.update(fill=pub.fill, wait_for_buffer_peers=buffer_subs)
                    run.start(pub.label, 'legacy_image_publisher' if pub.legacy
                              else 'image_publisher', **params)

            order = [start_subscribers, start_publishers] if self.subscribers_first else \
                [start_publishers, start_subscribers]
            order[0]()
            time.sleep(0.5)
            order[1]()
            survivors = [s.label for s in self.subscribers if s.label != self.kill]
            if self.kill:
                victim = run.nodes[self.kill]
                deadline = time.monotonic() + timeout
                while not any(FIRST_FRAMES.search(line) for line in list(victim.stderr)):
                    if time.monotonic() > deadline or victim.process.poll() is not None:
                        result.failures.append(f'{self.kill}: no frame before {timeout} s, '
                                               'not killed mid-stream')
                        break
                    time.sleep(0.05)
                time.sleep(self.kill_after)
                victim.kill()
            finished = run.wait(survivors, timeout + 15)
            run.wait([p.label for p in self.publishers], self.publisher_exit_timeout + 5)
            run.stop_all()
            result.reports = run.reports()
            if not finished:
                result.failures.append('subscribers did not finish in time')
            result.diagnostics = run.diagnostics()
        result.check()
        return result


@dataclass
class Result:
    scenario: Scenario
    reports: Dict[str, Optional[dict]] = field(default_factory=dict)
    failures: List[str] = field(default_factory=list)
    diagnostics: str = ''

    @property
    def ok(self) -> bool:
        return not self.failures

    def check(self) -> None:
        total = self.scenario.count * len(self.scenario.publishers)
        for pub in self.scenario.publishers:
            report = self.reports.get(pub.label)
            if report is None:
                self.failures.append(f'{pub.label}: no report')
                continue
            if report['published'] != self.scenario.count:
                self.failures.append(f"{pub.label}: published {report['published']}")
            stats = report.get('statistics') or {}
            if self.scenario.kill and stats.get('peers'):
                self.failures.append(f"{pub.label}: still serves {stats['peers']} at exit")
        for sub in self.scenario.subscribers:
            if sub.label == self.scenario.kill:
                continue  # SIGKILLed mid-stream: it reports nothing
            report = self.reports.get(sub.label)
            if report is None:
                self.failures.append(f'{sub.label}: no report')
                continue
            stats = report.get('statistics') or {}
            counters = {k: stats.get(k) for k in ('delivered', 'from_channels', 'from_main_topic',
                                                   'duplicates_dropped', 'rejected')}
            for key, expected in (('distinct', total), ('duplicates', 0), ('gaps', 0),
                                  ('checksum_failures', 0), ('wrong_backend', 0)):
                if report[key] != expected:
                    self.failures.append(f'{sub.label}: {key} = {report[key]}, expected '
                                         f'{expected} (backends {report["backends"]}, '
                                         f'counters {counters}, '
                                         f'missing {report.get("missing")}, '
                                         f'problems {report["problems"][:3]})')
            if sub.expect_backend and report['backends'] != {sub.expect_backend: total}:
                self.failures.append(f"{sub.label}: backends {report['backends']}, expected "
                                     f'all {total} as {sub.expect_backend}')
            if report['received'] != total:
                self.failures.append(f"{sub.label}: received {report['received']} callbacks "
                                     f'for {total} frames')

    def row(self) -> str:
        subs = ', '.join(
            f"{s.label}: {self.reports.get(s.label, {}) and self.reports[s.label]['backends']}"
            for s in self.scenario.subscribers)
        return (f"| {self.scenario.name} | {'PASS' if self.ok else 'FAIL'} | {subs} | "
                f"{'; '.join(self.failures)[:200]} |")


def _matrix() -> Dict[str, Scenario]:
    s: List[Scenario] = []
    for backend, accept in (('cpu', '__default__'), ('demo', 'any')):
        s.append(Scenario(f'1p1s_{backend}', f'{backend} publisher, one subscriber',
                          [Pub('pub', backend)], [Sub('sub', backend, accept)]))
        s.append(Scenario(f'1p2s_{backend}', f'{backend} publisher, two subscribers',
                          [Pub('pub', backend)],
                          [Sub('sub_a', backend, accept), Sub('sub_b', backend, accept)]))
        s.append(Scenario(f'2p2s_{backend}', f'two {backend} publishers, two subscribers',
                          [Pub('pub_a', backend), Pub('pub_b', backend)],
                          [Sub('sub_a', backend, accept), Sub('sub_b', backend, accept)]))
    # upstream's eight acceptable_buffer_backends combinations
    for pub_backend, accept, seen in (
            ('demo', 'any', 'demo'), ('demo', 'demo', 'demo'), ('cpu', '', 'cpu'),
            ('cpu', 'cpu', 'cpu'), ('cpu', '__default__', 'cpu'), ('demo', '', 'cpu'),
            ('demo', 'cpu', 'cpu'), ('demo', '__default__', 'cpu')):
        label = {'': 'empty', '__default__': 'default'}.get(accept, accept)
        s.append(Scenario(f'accept_{pub_backend}_pub_sub_{label}',
                          f'{pub_backend} publisher, subscriber accepts {accept!r}',
                          [Pub('pub', pub_backend)], [Sub('sub', seen, accept)]))
    s.append(Scenario('demo_from_cpu',
                      'demo publisher copying each CPU frame into demo memory (fill from_cpu)',
                      [Pub('pub', 'demo', fill='from_cpu')], [Sub('sub', 'demo', 'demo')]))
    s.append(Scenario('mixed_graph', 'demo publisher; demo-accepting, CPU-only and plain rclpy '
                      'subscribers at once', [Pub('pub', 'demo')],
                      [Sub('sub_demo', 'demo', 'any'), Sub('sub_cpu', 'cpu', 'cpu'),
                       Sub('sub_legacy', 'cpu', legacy=True)]))
    s.append(Scenario('legacy_pub_to_buffer_sub', 'plain rclpy publisher to a buffer-aware '
                      'subscription', [Pub('pub', legacy=True)], [Sub('sub', 'cpu', 'any')]))
    s.append(Scenario('demo_pub_to_legacy_sub', 'demo publisher to a plain rclpy subscription',
                      [Pub('pub', 'demo')], [Sub('sub', 'cpu', legacy=True)]))
    s.append(Scenario('demo_pub_to_raw_legacy_sub', 'a raw plain rclpy subscription (what a bag '
                      'recorder stores) gets canonical CPU bytes from a demo publisher',
                      [Pub('pub', 'demo')], [Sub('sub', 'cpu', legacy=True, raw=True)]))
    s.append(Scenario('subscriber_killed', 'a demo publisher keeps serving one subscriber while '
                      'another is SIGKILLed mid-stream; it drops the dead one when its DDS lease '
                      'expires', [Pub('pub', 'demo')],
                      [Sub('survivor', 'demo', 'any'), Sub('victim', None, 'any')],
                      count=150, rate_hz=30.0, kill='victim', kill_after=1.0,
                      publisher_exit_timeout=60.0))
    s.append(Scenario('publisher_first', 'the publisher starts before the subscriber',
                      [Pub('pub', 'demo')], [Sub('sub', 'demo', 'demo')],
                      subscribers_first=False))
    return {scenario.name: scenario for scenario in s}


SCENARIOS: Dict[str, Scenario] = _matrix()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description='Run named multi-process scenarios.')
    parser.add_argument('names', nargs='*', help=f'default: all of {", ".join(SCENARIOS)}')
    parser.add_argument('--echo', action='store_true', help="show the nodes' output")
    args = parser.parse_args(argv)
    unknown = [n for n in args.names if n not in SCENARIOS]
    if unknown:
        parser.error(f'unknown scenario(s) {unknown}; known: {", ".join(SCENARIOS)}')
    print('| scenario | result | backends seen | failures |\n|---|---|---|---|')
    failed = 0
    for name in args.names or list(SCENARIOS):
        result = SCENARIOS[name].run(echo=args.echo)
        print(result.row(), flush=True)
        failed += not result.ok
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
