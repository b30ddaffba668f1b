"""Benchmark suite: zero-copy images against stock rclpy, side by side, with a plot.

``python -m launch_free_demos.bench.suite [--quick | --smoke] [--rounds N] [--out DIR]``

Every measurement starts a fresh publisher process and fresh subscriber processes (the project's
node executables through ``launch_free_demos.runner``) on a topic of its own, under RELIABLE QoS
with depth 10. Transports:

- ``stock rclpy``: legacy_image_publisher -> legacy_image_subscriber (plain rclpy);
- ``rosidl_buffer_py cpu``: image_publisher backend cpu -> image_subscriber accepting cpu;
- ``demo from_cpu`` / ``demo allocate``: image_publisher backend demo (frame copied into shared
  memory / written in place) -> image_subscriber accepting demo;
- peers, what a user would pick instead (``launch_free_demos/bench/peers``; optional, from
  ``requirements-bench.txt``, skipped with a note when not installed): ``iceoryx2`` (its Python
  bindings: loaned shared-memory samples, WaitSet wake-up) and ``zenoh shm`` (zenoh's Python
  bindings, shared-memory payloads); their nodes send and check the same frames, log the same
  progress lines and print the same report, so they are measured as ours are (the peers
  table, beside stock rclpy, the CPU path and demo allocate, with the time from the callback's
  start to a readable numpy view);
- ``one memcpy``: ``numpy.copyto`` of the payload in this process, the physical reference:
  back to back (caches warm) and after an idle pause as long as the latency runs' frame period
  (what one copy costs a node that wakes up for a frame: ``demo from_cpu`` pays this copy).

Measured, from outside the nodes (nothing in the nodes is changed):

- latency publish -> callback: the subscriber's report (p50 / p90 / p99), frames at a low rate.
  Up to 1 MiB, stock rclpy and the CPU path run at the same time (two publishers, two
  subscribers, two topics), their publishers sending on one wall-clock grid half a frame period
  apart: both meet the same machine, whose load (CPU steal on a shared VM) drifts by more than
  their difference at small payloads. Larger frames would overlap (a stock 1920x1080 frame
  takes 50 to 100 ms): they run one after the other, in alternating order. The full mode
  repeats this in several rounds: the table shows each one's median run, and the CPU path /
  stock checks take the median of the per-round ratios. The CPU steal of every run is logged,
  and the run's total is in the report header;
- maximum sustained rate: rates are tried in ascending order, ``rate x seconds`` frames each; a
  rate is sustained when every frame arrives exactly once (distinct == count, gaps == 0, no
  checksum failure) and the subscriber's receive rate is at least 90 % of it. The search stops
  at the first rate that is not sustained;
- CPU time per message of every process: each process's CPU clock (``clock_getcpuclockid``,
  all threads, nanoseconds) is sampled every 10 ms; the window runs from the first to the last
  progress line the subscribers log (``report_period_sec``), and its CPU time is divided by the
  frames received in it. It includes the nodes' own work on every frame (the publisher writes
  and CRC32s each frame, the subscriber verifies the CRC32), their idle time (timers) and the
  subscriber's progress log: the same for every transport, and visible as the 1 KiB floor;
- peak resident memory of every process: VmHWM from ``/proc/<pid>/status``, read every 10 ms
  until the process exits (shared-memory pages the process touched count too); processes are
  reaped with ``os.wait4``;
- fan-out: 1..8 subscribers on one publisher, stock against demo (allocate).

Output: a markdown report on stdout and in ``DIR/benchmark.md``, and ``DIR/benchmark.png``
(latency against payload size; publisher CPU per message against subscriber count). The target
checks are printed as computed ratios: a benchmark reports, it asserts nothing about time.
"""
import argparse
import contextlib
import dataclasses
import datetime
import importlib.metadata
import importlib.util
import os
import platform
import re
import secrets
import shutil
import statistics
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy

from launch_free_demos.bench.measured import (
    MeasuredNode, MeasuredRun, StealMeter, claim_domain_id)
from launch_free_demos.bench.stats import percentiles
from launch_free_demos.runner import lock_free, remove_fastdds_leftovers

# label, width, height, encoding
PAYLOADS = [
    ('1 KiB', 1024, 1, 'mono8'),
    ('1 MiB', 1024, 1024, 'mono8'),
    ('640x480 rgb8', 640, 480, 'rgb8'),
    ('1920x1080 rgb8', 1920, 1080, 'rgb8'),
    ('3840x2160 rgb8', 3840, 2160, 'rgb8'),
]
PAYLOAD = {p[0]: p for p in PAYLOADS}
BYTES_PER_PIXEL = {'mono8': 1, 'rgb8': 3}


def payload_bytes(payload: str) -> int:
    _, width, height, encoding = PAYLOAD[payload]
    return width * height * BYTES_PER_PIXEL[encoding]


@dataclass(frozen=True)
class Transport:
    label: str
    publisher: str
    subscriber: str
    backend: Optional[str] = None  # None: a legacy node, no rosidl_buffer_py parameters
    fill: str = 'allocate'
    accept: Optional[str] = None
    #: a peer transport (launch_free_demos/bench/peers): the Python module it needs and its pip name
    peer_module: Optional[str] = None
    pip_name: Optional[str] = None


STOCK, CPU, DEMO_FROM_CPU, DEMO_ALLOCATE = (
    'stock rclpy', 'rosidl_buffer_py cpu', 'demo from_cpu', 'demo allocate')
MEMCPY = 'one memcpy (in-process)'
MEMCPY_IDLE = 'one memcpy after idle'
TRANSPORTS = [
    Transport(STOCK, 'legacy_image_publisher', 'legacy_image_subscriber'),
    Transport(CPU, 'image_publisher', 'image_subscriber', 'cpu', 'allocate', 'cpu'),
    Transport(DEMO_FROM_CPU, 'image_publisher', 'image_subscriber', 'demo', 'from_cpu', 'demo'),
    Transport(DEMO_ALLOCATE, 'image_publisher', 'image_subscriber', 'demo', 'allocate', 'demo'),
]
ICEORYX2, ZENOH = 'iceoryx2', 'zenoh shm'
#: What a user would pick instead of this package, measured the same way (the peers table):
#: optional, benchmark-only dependencies (requirements-bench.txt), skipped when absent.
PEERS = [
    Transport(ICEORYX2, 'iceoryx2_peer', 'iceoryx2_peer', peer_module='iceoryx2',
              pip_name='iceoryx2'),
    Transport(ZENOH, 'zenoh_peer', 'zenoh_peer', peer_module='zenoh', pip_name='eclipse-zenoh'),
]
TRANSPORT = {t.label: t for t in TRANSPORTS + PEERS}
ALL_ROWS = [t.label for t in TRANSPORTS] + [MEMCPY, MEMCPY_IDLE]
#: Rows of the peers table: stock rclpy, this package (CPU path, demo backend filled in
#: place), the peers, the in-process copy.
PEER_TABLE_OURS = [STOCK, CPU, DEMO_ALLOCATE]
#: Measured together, frames interleaved, in ``Mode.latency_rounds`` rounds (their ratio is a
#: target near 1).
PAIRED = (STOCK, CPU)
FANOUT_TRANSPORTS = [STOCK, DEMO_ALLOCATE]
#: PAIRED runs go side by side only up to this payload: a stock frame of 1920x1080 takes 50 to
#: 100 ms, and frames half a period (100 ms) apart would overlap and slow each other down.
PAIR_MAX_BYTES = 1024 * 1024
BIG, SMALL = '3840x2160 rgb8', '1 KiB'


@dataclass
class Mode:
    name: str
    payloads: List[str]          # latency / CPU / memory table
    frames: int                  # frames per latency run (and per fan-out run)
    rate: float                  # Hz of latency and fan-out runs (low: no queueing)
    rate_payloads: List[str]     # where the maximum sustained rate is searched
    rates: List[float]
    rate_seconds: float          # each rate runs rate x this many frames (at least 20)
    fanout_payloads: List[str]
    fanout_subscribers: List[int]
    memcpy_repeat: int
    latency_rounds: int = 1      # rounds of the PAIRED transports' latency runs
    #: payloads of the mixed-graph table (launch_free_demos.bench.mixed): what a legacy
    #: listener costs the buffer-aware subscriber beside it and the publisher
    mixed_payloads: List[str] = field(default_factory=list)
    #: payloads of the mixed-graph latency table (a demo subscriber alone, beside a plain one,
    #: and the same graph of stock endpoints) at MIXED_LATENCY_RATE, and its frames per run
    mixed_latency_payloads: List[str] = field(default_factory=list)
    mixed_latency_frames: int = 300
    #: seconds of the churn benchmark (launch_free_demos.bench.churn) at 1080p; 0: not run
    churn_seconds: float = 0.0
    #: payloads of the peers table; those not in ``payloads`` get their own stock and
    #: rosidl_buffer_py runs, only when a peer is installed
    peer_payloads: List[str] = field(default_factory=list)


PEER_PAYLOADS = ['1 KiB', '1 MiB', '1920x1080 rgb8', BIG]
MODES = {
    'full': Mode('full', [p[0] for p in PAYLOADS], 30, 5.0, [p[0] for p in PAYLOADS],
                 [10.0, 30.0, 60.0, 120.0, 240.0], 2.0, ['1920x1080 rgb8', BIG], [1, 2, 4, 8],
                 50, latency_rounds=5, mixed_payloads=['1920x1080 rgb8', BIG],
                 mixed_latency_payloads=['640x480 rgb8', '1920x1080 rgb8', BIG],
                 churn_seconds=20.0, peer_payloads=PEER_PAYLOADS),
    'quick': Mode('quick', [SMALL, '1920x1080 rgb8', BIG], 8, 5.0, [BIG], [30.0, 60.0], 1.0,
                  [BIG], [1, 4], 20, mixed_latency_payloads=['640x480 rgb8'],
                  mixed_latency_frames=90, peer_payloads=PEER_PAYLOADS),
    'smoke': Mode('smoke', [SMALL, '640x480 rgb8'], 5, 5.0, ['640x480 rgb8'], [30.0], 1.0,
                  ['640x480 rgb8'], [1, 2], 10, mixed_latency_payloads=['640x480 rgb8'],
                  mixed_latency_frames=15, peer_payloads=[SMALL, '640x480 rgb8']),
}

#: Hz of the mixed-graph latency runs (a camera's rate: issue #19's target graph)
MIXED_LATENCY_RATE = 30.0
#: graphs of the mixed-graph latency table (see launch_free_demos.bench.mixed)
MIXED_LATENCY_GRAPHS = ['pure', 'mixed', 'stock mixed']

SAMPLE_PERIOD = 0.01
LOG_PERIOD = 0.05       # subscribers' progress log (the CPU window's marks), latency runs
RATE_LOG_PERIOD = 0.02  # finer for rate runs: the receive rate is fitted from these marks
DRAIN_SEC = 3.0         # after the publisher exited, subscribers get this long to finish


# --- peers: what they need, and the files they leave ---------------------------------------

def peer_version(transport: Transport) -> Optional[str]:
    """The installed version of a peer's Python package, or None when it cannot be imported."""
    if importlib.util.find_spec(transport.peer_module) is None:
        return None
    try:
        return importlib.metadata.version(transport.pip_name)
    except importlib.metadata.PackageNotFoundError:
        return 'installed'


def skipped_note(transport: Transport) -> str:
    return (f'{transport.pip_name} not installed (pip install -r requirements-bench.txt): '
            f'skipped')


#: A zenoh shared-memory segment: zenoh holds a flock on each one while it uses it, and
#: leaves some behind when its session closes.
_ZENOH_SEGMENT = re.compile(r'^\d+\.zenoh$')


def peer_shm_leftovers(prefix: str, since: float) -> List[str]:
    """Files in /dev/shm that a peer run left: those named with the run's iceoryx2 prefix
    (iceoryx2 keeps a management segment after its nodes exit; a killed node leaves all of
    them), and zenoh segments made at or after ``since`` that no process holds any more."""
    left = []
    for name in sorted(os.listdir('/dev/shm')):
        path = os.path.join('/dev/shm', name)
        if name.startswith(prefix):
            left.append(name)
        elif _ZENOH_SEGMENT.match(name):
            try:
                recent = os.stat(path).st_mtime >= since
            except FileNotFoundError:
                continue
            if recent and lock_free(path):
                left.append(name)
    return left


@contextlib.contextmanager
def peer_scratch(transport: Transport):
    """Parameters that give one peer run files of its own (a directory; for iceoryx2 also a
    file prefix in /dev/shm); on exit, after the run's processes are reaped, whatever of them
    is left is removed."""
    root = tempfile.mkdtemp(prefix='rbpy_bench_peer_')
    prefix = f'rbpy_iox2_{os.getpid()}_{secrets.token_hex(4)}_'  # rbpy_<owner pid>_: ours
    since = time.time() - 1.0
    try:
        yield {'root_path': root, **({'shm_prefix': prefix} if transport.label == ICEORYX2
                                    else {})}
    finally:
        shutil.rmtree(root, ignore_errors=True)
        for name in peer_shm_leftovers(prefix, since):
            try:
                os.remove(os.path.join('/dev/shm', name))
            except FileNotFoundError:
                pass


# --- one measurement ------------------------------------------------------------------------

@dataclass
class Result:
    transport: str
    payload: str
    subscribers: int
    count: int
    rate: float
    complete: bool = False
    distinct: List[int] = field(default_factory=list)
    latency: Dict[str, float] = field(default_factory=dict)  # median over subscribers
    view: Dict[str, float] = field(default_factory=dict)     # time to a numpy view, ditto
    pub_cpu_ms: Optional[float] = None                     # see cpu_per_message
    sub_cpu_ms: Optional[float] = None                     # mean over subscribers
    pub_rss_mib: Optional[float] = None
    sub_rss_mib: Optional[float] = None                    # max over subscribers
    receive_rate: Optional[float] = None                   # min over subscribers
    backends: Dict[str, int] = field(default_factory=dict)
    problem: str = ''
    setup_retries: int = 0


_topic_counter = 0


def next_topic(kind: str) -> str:
    global _topic_counter
    _topic_counter += 1
    return f'/benchmark_{os.getpid()}/{kind}_{_topic_counter}'


SETUP_ATTEMPTS = 3  # a run whose publisher gave up before any frame was sent is started again
SETUP_FAILURES: List[str] = []  # such runs, for the report


def measure(transport_label: str, payload: str, subscribers: int, count: int, rate: float,
            log_period: float = LOG_PERIOD, linger: float = 20.0) -> Result:
    """Run one publisher and ``subscribers`` subscribers; measure from outside.

    If the publisher gave up waiting for its subscribers (or their channels) and nothing was
    delivered, the run is repeated on a new topic, up to SETUP_ATTEMPTS times; the retries are
    counted in the result.
    """
    return _measure_with_retries([Leg(transport_label)], payload, subscribers, count, rate,
                                 log_period, linger)[0]


def measure_paired(payload: str, count: int, rate: float, round_index: int) -> Dict[str, Result]:
    """Latency runs of the PAIRED transports at the same time, their frames interleaved.

    Each transport has its own publisher, subscriber and topic; the publishers send on one
    wall-clock grid, half a period apart (which one goes first alternates by round), so at
    every moment at most one frame is in flight and both meet the same machine: a shared
    machine's load (CPU steal) changes within seconds, by more than the difference measured.
    """
    half = 0.5 / rate
    phases = (0.0, half) if round_index % 2 == 0 else (half, 0.0)
    legs = [Leg(label, phase) for label, phase in zip(PAIRED, phases)]
    results = _measure_with_retries(legs, payload, 1, count, rate, LOG_PERIOD, 20.0)
    return {leg.transport: result for leg, result in zip(legs, results)}


@dataclass(frozen=True)
class Leg:
    """One transport's publisher and subscribers within a run."""

    transport: str
    phase: Optional[float] = None  # the publisher's phase_sec (None: first frame at once)


def _measure_with_retries(legs: List[Leg], payload: str, subscribers: int, count: int,
                          rate: float, log_period: float, linger: float) -> List[Result]:
    for attempt in range(SETUP_ATTEMPTS):
        results = _measure_once(legs, payload, subscribers, count, rate, log_period, linger)
        failed = [r for r in results if r.problem and max(r.distinct, default=0) == 0]
        for result in results:
            result.setup_retries = attempt
        if not failed:
            break
        for result in failed:
            SETUP_FAILURES.append(f'{result.transport}, {payload}, {subscribers} '
                                  f'subscriber(s), {rate:g} Hz: {result.problem}')
        print(f'    setup failed, attempt {attempt + 1} of {SETUP_ATTEMPTS}', file=sys.stderr)
    return results


@dataclass
class _LegRun:
    """The nodes of one leg in a run, and what was measured of them."""

    subs: List[MeasuredNode]
    pub: MeasuredNode
    result: Result
    samples: List['Sample'] = field(default_factory=list)  # taken while all its nodes live
    pub_exited: Optional[float] = None


def _measure_once(legs: List[Leg], payload: str, subscribers: int, count: int, rate: float,
                  log_period: float, linger: float) -> List[Result]:
    _, width, height, encoding = PAYLOAD[payload]
    expected_sec = count / rate
    runs: List[_LegRun] = []
    with contextlib.ExitStack() as scratch, MeasuredRun() as run:  # run reaped, then scratch
        started = []
        for n, leg in enumerate(legs):
            t = TRANSPORT[leg.transport]
            topic = next_topic(f'{leg.transport.split()[0]}_{width}x{height}_{subscribers}s')
            if t.peer_module is not None:
                topic = topic.lstrip('/')  # a zenoh key expression has no leading /
            sub_params = dict(topic=topic, expected_count=count,
                              timeout_sec=expected_sec + 120.0, report_period_sec=log_period)
            pub_params = dict(topic=topic, count=count, rate_hz=rate,
                              wait_for_subscribers=subscribers,
                              wait_timeout_sec=20.0 + 5.0 * subscribers, linger_sec=linger,
                              width=width, height=height, encoding=encoding)
            if leg.phase is not None:
                pub_params['phase_sec'] = leg.phase
            if t.backend is not None:
                sub_params['acceptable_buffer_backends'] = t.accept
                pub_params.update(backend=t.backend, fill=t.fill,
                                  wait_for_buffer_peers=subscribers)
            if t.peer_module is not None:  # files of its own, removed after the run
                own = scratch.enter_context(peer_scratch(t))
                sub_params.update(own, role='subscriber', width=width, height=height,
                                  encoding=encoding, wait_for_subscribers=subscribers)
                pub_params.update(own, role='publisher')
            subs = [run.start(f'bench{n}_sub{i}', t.subscriber, **sub_params)
                    for i in range(subscribers)]
            started.append((leg, subs, t.publisher, pub_params))
        for n, (leg, subs, publisher, pub_params) in enumerate(started):
            pub = run.start(f'bench{n}_pub', publisher, **pub_params)
            runs.append(_LegRun(subs, pub, Result(leg.transport, payload, subscribers, count,
                                                  rate)))
        deadline = time.monotonic() + expected_sec + 180.0
        while True:
            now = time.monotonic()
            for leg_run in runs:
                _sample_leg(leg_run, now, deadline)
            if all(leg_run.result.problem or all(node.reaped for node in
                                                 leg_run.subs + [leg_run.pub])
                   for leg_run in runs):
                break
            time.sleep(SAMPLE_PERIOD)
        run.stop_all()  # SIGINT (the nodes print their report), then SIGKILL; reaps all
        for leg_run in runs:
            for sub in leg_run.subs:
                sub.read_log()
        diagnostics = run.diagnostics()
    return [_leg_result(leg_run, count, diagnostics) for leg_run in runs]


def _sample_leg(leg_run: _LegRun, now: float, deadline: float) -> None:
    """One sampling pass over a leg's nodes: logs, CPU clocks, peak RSS, exits."""
    if leg_run.result.problem:
        return
    subs, pub = leg_run.subs, leg_run.pub
    nodes = subs + [pub]
    for sub in subs:
        sub.read_log()
    cpus = [node.cpu() for node in nodes]
    for node in nodes:
        node.read_peak_rss()
    if None not in cpus:
        leg_run.samples.append(Sample(time.time(), cpus[-1], cpus[:-1],
                                      [sub.marks[-1] if sub.marks else (0.0, 0)
                                       for sub in subs]))
    if all([node.try_reap() for node in nodes]):
        return
    if pub.reaped and leg_run.pub_exited is None:
        leg_run.pub_exited = now
    if (leg_run.pub_exited is not None and now - leg_run.pub_exited > DRAIN_SEC) or \
            now > deadline:
        leg_run.result.problem = 'timed out' if now > deadline else (
            f'publisher exited ({pub.process.returncode}) before every frame arrived')


def _leg_result(leg_run: _LegRun, count: int, diagnostics: str) -> Result:
    result, subs, pub, samples = leg_run.result, leg_run.subs, leg_run.pub, leg_run.samples
    transport_label, payload, subscribers, rate = (result.transport, result.payload,
                                                   result.subscribers, result.rate)
    reports = [sub.report for sub in subs]
    if any(r is None for r in reports):
        result.problem = result.problem or 'no report'
        print(f'    {transport_label} {payload} x{subscribers}: missing report\n{diagnostics}',
              file=sys.stderr)
        return result
    result.distinct = [r['distinct'] for r in reports]
    result.complete = all(r['distinct'] == count and r['gaps'] == 0 and
                          not r['checksum_failures'] and not r['timed_out'] for r in reports)
    for r in reports:
        for backend, n in r['backends'].items():
            result.backends[backend] = result.backends.get(backend, 0) + n
    result.latency = {q: statistics.median(r['latency_ms'][q] for r in reports)
                      for q in ('p50', 'p90', 'p99', 'max')}
    if all(r.get('view_ms') for r in reports):
        result.view = {q: statistics.median(r['view_ms'][q] for r in reports)
                       for q in ('p50', 'p90', 'p99', 'max')}
    result.pub_rss_mib = pub.peak_rss_mib
    rss = [s.peak_rss_mib for s in subs if s.peak_rss_mib is not None]
    result.sub_rss_mib = max(rss) if rss else None

    # CPU per message, per process: see cpu_per_message. The publisher's frames are counted by
    # the first subscriber (every subscriber gets the same frames).
    per_sub = [cpu_per_message(samples, i, lambda s, i=i: s.subs[i])
               for i in range(subscribers)]
    if per_sub and None not in per_sub:
        result.sub_cpu_ms = statistics.mean(per_sub)
    result.pub_cpu_ms = cpu_per_message(samples, 0, lambda s: s.pub)
    rates = [receive_rate(sub.marks, count) for sub in subs]
    if None not in rates:
        result.receive_rate = min(rates)
    if not result.complete:
        print(f'    {transport_label} {payload} x{subscribers} at {rate:g} Hz: incomplete '
              f'(distinct {result.distinct} of {count}, {result.problem or "lost frames"})',
              file=sys.stderr)
        if pub.process.returncode != 0:  # the publisher failed (e.g. gave up waiting)
            print(diagnostics, file=sys.stderr)
    return result


@dataclass
class Sample:
    wall: float                     # time.time() when taken
    pub: float                      # CPU seconds of the publisher
    subs: List[float]               # CPU seconds of each subscriber
    marks: List[Tuple[float, int]]  # each subscriber's last progress line: (wall time, distinct)


FRESH_SEC = 0.02  # a sample counts frames only if it follows a progress line this closely


def cpu_per_message(samples: List[Sample], sub_index: int, cpu) -> Optional[float]:
    """CPU ms per frame of one process: the CPU time of a window / the frames received in it.

    The window runs between the first and the last sample taken right after a progress line of
    subscriber ``sub_index`` (so its frame count is current), from that subscriber's second
    frame on (the first one comes in the tail of discovery). The node's idle spinning between
    frames is included.
    """
    fresh = [s for s in samples if s.marks[sub_index][1] >= 2 and
             0 <= s.wall - s.marks[sub_index][0] <= FRESH_SEC]
    if len(fresh) < 2:
        return None
    first, last = fresh[0], fresh[-1]
    frames = last.marks[sub_index][1] - first.marks[sub_index][1]
    return (cpu(last) - cpu(first)) * 1e3 / frames if frames >= 2 else None


#: A fan-out series is implausible when the publisher's CPU per message with more subscribers is
#: below this fraction of a value with fewer (more work cannot cost less: a measurement error,
#: such as a window caught in discovery, not a result).
FANOUT_DROP_LIMIT = 0.7


def fanout_implausibility(points: List[Tuple[int, float]]) -> Optional[str]:
    """Why a (subscribers, publisher CPU ms per message) series cannot be right, or None.

    Each added subscriber adds work for the publisher (at least its share of matching and
    delivery), so its CPU per message must not fall markedly as subscribers are added.
    """
    points = sorted(points)
    for i, (n_few, few) in enumerate(points):
        for n_more, more in points[i + 1:]:
            if few > 0 and more < FANOUT_DROP_LIMIT * few:
                return (f'CPU per message fell from {few:.1f} to {more:.1f} ms from {n_few} to '
                        f'{n_more} subscribers: a measurement error, not plotted')
    return None


def receive_rate(marks: List[Tuple[float, int]], count: int) -> Optional[float]:
    """Frames per second between the first and the last progress line inside the run."""
    inside = [(t, n) for t, n in marks if 0 < n < count]
    if len(inside) < 2 or inside[-1][0] - inside[0][0] < 0.2 or inside[-1][1] == inside[0][1]:
        return None
    return (inside[-1][1] - inside[0][1]) / (inside[-1][0] - inside[0][0])


def latency_run(label: str, payload: str, mode: Mode, progress, round_name: str = '') -> Result:
    """One latency run of one transport (one subscriber, ``mode.frames`` at ``mode.rate``),
    logged with the CPU steal it met."""
    steal = StealMeter()
    r = measure(label, payload, 1, mode.frames, mode.rate)
    progress(f'latency {label:<22} {payload:>15}{round_name}: p50 {_fmt(r.latency.get("p50"))} '
             f'ms, pub CPU {_fmt(r.pub_cpu_ms)} ms/msg, view {_fmt(r.view.get("p50"), 3)} ms, '
             f'backends {r.backends}, CPU steal {_pct(steal.fraction())}')
    return r


def max_sustained_rate(transport: str, payload: str, mode: Mode) -> Tuple[Optional[float], str]:
    """The highest rate of ``mode.rates`` that is sustained, and how the search ended."""
    best = None
    for rate in mode.rates:
        count = max(20, round(rate * mode.rate_seconds))
        result = measure(transport, payload, 1, count, rate, log_period=RATE_LOG_PERIOD,
                         linger=2.0)
        achieved = result.receive_rate
        ok = result.complete and (achieved is None or achieved >= 0.9 * rate)
        print(f'    rate {transport:<22} {payload:>15} {rate:6g} Hz: '
              f'{"sustained" if ok else "NOT sustained"} (distinct {result.distinct} of '
              f'{count}, receive rate {_fmt(achieved, 1)} Hz)', file=sys.stderr, flush=True)
        if not ok:
            return best, f'< {rate:g}' if best is None else f'{best:g}'
        best = rate
    return best, f'>= {best:g}'


def measure_memcpy(payload: str, repeat: int, idle: float) -> Dict[str, Dict[str, float]]:
    """numpy.copyto of the payload (the physical reference), back to back (``warm``) and each
    after ``idle`` seconds of sleep (``idle``), and zlib.crc32 (what the nodes add on every
    frame, ``crc32``); ms percentiles."""
    nbytes = payload_bytes(payload)
    source = numpy.random.default_rng(0).integers(0, 256, size=nbytes, dtype=numpy.uint8)
    target = numpy.empty_like(source)

    def timed(func, count, pause=0.0):
        func()
        times = []
        for _ in range(count):
            if pause:
                time.sleep(pause)
            start = time.perf_counter()
            func()
            times.append((time.perf_counter() - start) * 1e3)
        return percentiles(times)

    def copy():
        numpy.copyto(target, source)

    return {'warm': timed(copy, repeat), 'idle': timed(copy, min(repeat, 10), idle),
            'crc32': timed(lambda: zlib.crc32(source), repeat)}


def _pct(fraction: Optional[float]) -> str:
    return '—' if fraction is None else f'{100 * fraction:.0f} %'


# --- report ---------------------------------------------------------------------------------

def _fmt(value: Optional[float], digits: int = 2) -> str:
    return '—' if value is None else f'{value:.{digits}f}'


PEER_QUANTILES = ('p50', 'p90', 'max')


def _lat(latency: Dict[str, float], quantiles=('p50', 'p90', 'p99'), fine: bool = False) -> str:
    """Latency quantiles in ms; ``fine``: three decimals below 1 ms (the peers table)."""
    if not latency:
        return '—'
    return ' / '.join(_fmt(latency[q], 3 if fine and latency[q] < 1 else
                           2 if latency[q] < 100 else 0) for q in quantiles)


def _ratio(a: Optional[float], b: Optional[float]) -> Optional[float]:
    return None if a is None or b is None or b == 0 else a / b


def slope(points: List[Tuple[int, float]]) -> Optional[float]:
    """Least-squares growth of y per added x."""
    points = [(x, y) for x, y in points if y is not None]
    if len(points) < 2:
        return None
    xs, ys = numpy.array(points, dtype=float).T
    return float(numpy.polyfit(xs, ys, 1)[0])


def median_run(runs: List['Result']) -> 'Result':
    """The run with the median latency p50 (the lower middle one of an even count), complete
    runs first: the run a table row shows when a transport was measured in rounds."""
    pool = [r for r in runs if r.complete and r.latency] or [r for r in runs if r.latency] or runs
    if not pool[0].latency:
        return pool[0]
    ordered = sorted(pool, key=lambda r: r.latency['p50'])
    return ordered[(len(ordered) - 1) // 2]


def paired_ratios(rounds: Dict, payload: str, value) -> List[float]:
    """CPU path / stock of ``value(result)`` in each round in which both were measured."""
    ratios = []
    for cpu_path, stock in zip(rounds.get((CPU, payload), []), rounds.get((STOCK, payload), [])):
        ratio = _ratio(value(cpu_path), value(stock))
        if ratio is not None:
            ratios.append(ratio)
    return ratios


def target_checks(mode: Mode, lat: Dict, rates: Dict, fanout: Dict, memcpy: Dict,
                  rounds: Dict) -> List[Tuple]:
    """(check, computed value, target, met) rows; value None when not measured in this mode."""
    def p50(transport, payload):
        result = lat.get((transport, payload))
        return result.latency.get('p50') if result and result.latency else None

    checks = []
    for demo in (DEMO_FROM_CPU, DEMO_ALLOCATE):
        value = _ratio(p50(demo, BIG), p50(demo, SMALL))
        checks.append((f'{demo}: latency 3840x2160 / 1 KiB', value, '<= 2',
                       None if value is None else value <= 2))
    for demo in (DEMO_FROM_CPU, DEMO_ALLOCATE):
        value = _ratio(p50(STOCK, BIG), p50(demo, BIG))
        checks.append((f'latency stock / {demo} at 3840x2160', value, '>= 30',
                       None if value is None else value >= 30))
    from_cpu, allocate = p50(DEMO_FROM_CPU, BIG), p50(DEMO_ALLOCATE, BIG)
    if from_cpu is not None and allocate is not None and BIG in memcpy:
        checks.append(('(demo from_cpu - demo allocate) latency at 3840x2160 / one memcpy after '
                       'idle', _ratio(from_cpu - allocate, memcpy[BIG]['idle']['p50']),
                       'about 1: the one copy from_cpu asks for', None))
    for label, value in (('latency', lambda r: r.latency.get('p50')),
                         ('publisher CPU per message', lambda r: r.pub_cpu_ms)):
        for payload in mode.payloads:
            ratios = paired_ratios(rounds, payload, value)
            shown = statistics.median(ratios) if ratios else None
            how = (f' (median of {len(ratios)} paired rounds: '
                   f'{", ".join(f"{r:.2f}" for r in ratios)})' if len(ratios) > 1 else '')
            checks.append((f'{label} CPU path / stock at {payload}{how}', shown, '<= 1.1',
                           None if shown is None else shown <= 1.1))
    for demo in (DEMO_FROM_CPU, DEMO_ALLOCATE):
        name = (f'{demo}: sustained rate at 3840x2160, Hz (tried '
                f'{", ".join(f"{r:g}" for r in mode.rates)})')
        if (demo, BIG) in rates:
            best, shown = rates[(demo, BIG)]
            checks.append((name, shown, '>= 60', (best or 0) >= 60))
        else:
            checks.append((name, None, '>= 60', None))
    for payload in mode.fanout_payloads:
        used = {t: [n for n in mode.fanout_subscribers
                    if (t, payload, n) in fanout and fanout[(t, payload, n)].complete]
                for t in FANOUT_TRANSPORTS}  # runs that lost frames are left out of the fit
        series = {t: [(n, fanout[(t, payload, n)].pub_cpu_ms) for n in used[t]
                      if fanout[(t, payload, n)].pub_cpu_ms is not None]
                  for t in FANOUT_TRANSPORTS}
        wrong = {t: fanout_implausibility(series[t]) for t in FANOUT_TRANSPORTS}
        growth = {t: None if wrong[t] else slope(series[t]) for t in FANOUT_TRANSPORTS}
        for t in FANOUT_TRANSPORTS:
            checks.append((f'{t}: publisher CPU per message at {payload} does not fall as '
                           'subscribers are added', wrong[t] or 'it does not', 'plausible',
                           wrong[t] is None))
        for t in FANOUT_TRANSPORTS:
            checks.append((f'{t}: publisher CPU growth per added subscriber at {payload}, '
                           f'ms/msg (fit over {", ".join(map(str, used[t])) or "no"} complete '
                           f'runs)', growth[t], 'demo << stock', None))
        value = _ratio(growth[DEMO_ALLOCATE], growth[STOCK])
        checks.append((f'fan-out growth demo / stock at {payload}', value, '<< 1 (no fixed target)',
                       None))
    return checks


def mixed_latency_checks(latencies: Dict[str, Dict[str, List[Dict[str, dict]]]]) -> List[Tuple]:
    """Issue #19's timing targets per payload, as (check, value, target, met) rows: beside a
    plain subscriber, the demo subscriber's p99 is at most twice its p99 alone, and never
    above the plain subscriber's p99 (medians over the runs)."""
    checks = []
    for payload, runs in latencies.items():
        def p99s(graph, label):
            return [run[label]['p99'] for run in runs.get(graph, []) if run.get(label)]
        pure, mixed, plain = (p99s('pure', 'demo_sub'), p99s('mixed', 'demo_sub'),
                              p99s('mixed', 'plain_sub'))
        if not (pure and mixed and plain):
            continue
        pure, mixed, plain = (statistics.median(v) for v in (pure, mixed, plain))
        checks.append((f'mixed graph at {payload}: demo p99 beside a plain subscriber / alone',
                       mixed / pure, '<= 2', mixed / pure <= 2))
        checks.append((f'mixed graph at {payload}: demo p99 / the plain subscriber\'s p99 '
                       'beside it', mixed / plain, '<= 1', mixed <= plain))
    return checks


def markdown(mode: Mode, lat: Dict, memcpy: Dict, rates: Dict, fanout: Dict,
             checks: List[Tuple], header: str) -> str:
    out = [header, '']
    out.append(f'## Per payload and transport\n\nLatency: publish -> callback in ms, p50 / p90 / '
               f'p99 of {mode.frames} frames at {mode.rate:g} Hz, one subscriber. Max rate: '
               f'highest of {", ".join(f"{r:g}" for r in mode.rates)} Hz with every frame '
               f'delivered once ({mode.rate_seconds:g} s of frames each, RELIABLE depth 10); '
               f'"—" where not searched in this mode. CPU: ms of process CPU time (all threads) '
               f'per message in the latency run, from the second frame on; it includes the '
               f'nodes\' idle time between frames (the subscriber\'s progress log every '
               f'{LOG_PERIOD * 1e3:g} ms, timers), the floor the 1 KiB rows show. Peak RSS: MiB '
               f'(VmHWM, last read before exit). Frames: distinct frames received '
               f'of those sent. The memcpy rows are one numpy.copyto of the payload in one '
               f'process (the latency column is the copy time), back to back and after '
               f'{1 / mode.rate:g} s of sleep (the latency runs\' frame period). '
               f'{" and ".join(PAIRED)} run at the same time up to {PAIR_MAX_BYTES // 1024} '
               f'KiB, each with its own publisher, subscriber and topic, their frames '
               f'interleaved half a period apart (larger frames would overlap: there they run '
               f'one after the other, in alternating order)'
               + (f'; each row is the median of {mode.latency_rounds} such rounds (by latency '
                  f'p50).' if mode.latency_rounds > 1 else '.') + '\n')
    out.append('| payload | transport | latency p50 / p90 / p99 ms | max rate Hz | '
               'pub CPU ms/msg | sub CPU ms/msg | pub peak RSS MiB | sub peak RSS MiB | frames |')
    out.append('|---|---|---|---|---|---|---|---|---|')
    for payload in mode.payloads:
        for t in TRANSPORTS:
            r = lat[(t.label, payload)]
            rate = rates[(t.label, payload)][1] if (t.label, payload) in rates else '—'
            frames = f'{min(r.distinct) if r.distinct else 0}/{r.count}' + (
                '' if r.complete else ' !')
            out.append(f'| {payload} | {t.label} | {_lat(r.latency)} | {rate} | '
                       f'{_fmt(r.pub_cpu_ms)} | {_fmt(r.sub_cpu_ms)} | '
                       f'{_fmt(r.pub_rss_mib, 0)} '
                       f'| {_fmt(r.sub_rss_mib, 0)} | {frames} |')
        for label, key in ((MEMCPY, 'warm'), (MEMCPY_IDLE, 'idle')):
            m = memcpy[payload][key]
            out.append(f'| {payload} | {label} | {_lat(m)} | — | '
                       f'{_fmt(m["p50"], 3)} | — | — | — | — |')
    out.append('\nCRC32 of the payload, which every publisher and subscriber node computes on '
               'every frame (included in their CPU above), ms: ' +
               ', '.join(f'{p} {memcpy[p]["crc32"]["p50"]:.3f}' for p in mode.payloads) + '.')
    out.append(f'\n## Fan-out\n\nOne publisher, N subscriber processes, {mode.frames} frames at '
               f'{mode.rate:g} Hz. CPU per message as above; sub columns: mean (CPU) and median '
               f'(latency p50) over the subscribers.\n')
    out.append('| payload | transport | subscribers | pub CPU ms/msg | sub CPU ms/msg | '
               'latency p50 ms | pub peak RSS MiB | frames (min) |')
    out.append('|---|---|---|---|---|---|---|---|')
    for payload in mode.fanout_payloads:
        for t in FANOUT_TRANSPORTS:
            for n in mode.fanout_subscribers:
                r = fanout[(t, payload, n)]
                frames = f'{min(r.distinct) if r.distinct else 0}/{r.count}' + (
                    '' if r.complete else ' !')
                out.append(f'| {payload} | {t} | {n} | {_fmt(r.pub_cpu_ms)} | '
                           f'{_fmt(r.sub_cpu_ms)} | '
                           f'{_fmt(r.latency.get("p50"))} | '
                           f'{_fmt(r.pub_rss_mib, 0)} | {frames} |')
    out.append('\n## Target checks (computed, not asserted)\n')
    out.append('| check | value | target | met |')
    out.append('|---|---|---|---|')
    for name, value, target, met in checks:
        shown = ('not measured in this mode' if value is None else
                 value if isinstance(value, str) else f'{value:.2f}')
        out.append(f'| {name} | {shown} | {target} | '
                   f'{"—" if met is None else ("yes" if met else "NO")} |')
    out.append('\n"!" marks a run that lost frames or did not finish; its numbers are shown '
               'as measured.')
    if SETUP_FAILURES:
        out.append(f'\nRuns started again because nothing was delivered (the publisher gave up '
                   f'waiting for its subscribers or channels): {len(SETUP_FAILURES)}.')
        out.extend(f'- {failure}' for failure in SETUP_FAILURES)
    return '\n'.join(out) + '\n'


def peers_markdown(mode: Mode, payloads: List[str], lat: Dict, memcpy: Dict,
                   versions: Dict[str, Optional[str]], argv: Optional[List[str]]) -> str:
    """The peers table: this package beside what a user would pick instead, same method."""
    command = ' '.join(['./dev bench', *(sys.argv[1:] if argv is None else argv)])
    rounds = (f', the median run (by latency p50) of {mode.latency_rounds} rounds for the '
              f'peers, {" and ".join(PAIRED)}' if mode.latency_rounds > 1 else '')
    out = [f'## Peers side by side\n\nProduced by `{command}`. Every transport runs the same '
           f'frames the same way: publisher and subscriber in separate processes, the frame '
           f'written into the transport\'s memory before it is sent (in place, except '
           f'zenoh: its shared-memory buffer takes only bytes, so the frame is copied in from a '
           f'bytearray), CRC32 on both sides, {mode.frames} frames at {mode.rate:g} Hz, one '
           f'subscriber{rounds}. Latency: ms from a stamp taken just before publish to the '
           f'start of the subscriber\'s callback, p50 / p90 / max. CPU: ms of process CPU time '
           f'per frame, as in the table above. View: ms from the callback\'s start to a '
           f'readable numpy array over the payload, p50 (rosidl_buffer_py.image.from_input_msg '
           f'with clone=False for stock rclpy and this package, a numpy array over the loaned '
           f'sample for iceoryx2, payload.to_bytes() for zenoh, which has no buffer protocol: '
           f'a full copy). The memcpy rows are one numpy.copyto of the payload in one process '
           f'(the latency column is the copy time).\n']
    out.append('Peers: ' + '; '.join(
        f'{t.label} ({t.pip_name} {versions[t.label]})' if versions.get(t.label) else
        skipped_note(t) for t in PEERS) + '.\n')
    out.append('| payload | transport | latency p50 / p90 / max ms | pub CPU ms/frame | '
               'sub CPU ms/frame | view ms | frames |')
    out.append('|---|---|---|---|---|---|---|')
    for payload in payloads:
        for label in PEER_TABLE_OURS + [t.label for t in PEERS]:
            r = lat.get((label, payload))
            if r is None:  # a peer that is not installed
                continue
            frames = f'{min(r.distinct) if r.distinct else 0}/{r.count}' + (
                '' if r.complete else ' !')
            out.append(f'| {payload} | {label} | {_lat(r.latency, PEER_QUANTILES, fine=True)} | '
                       f'{_fmt(r.pub_cpu_ms)} | {_fmt(r.sub_cpu_ms)} | '
                       f'{_fmt(r.view.get("p50"), 3)} | {frames} |')
        for label, key in ((MEMCPY, 'warm'), (MEMCPY_IDLE, 'idle')):
            copy = _lat(memcpy[payload][key], PEER_QUANTILES, fine=True)
            out.append(f'| {payload} | {label} | {copy} | — | — | — | — |')
    skipped = [skipped_note(t) for t in PEERS if not versions.get(t.label)]
    if skipped:
        out.append('\n' + '. '.join(skipped) + '.')
    missing = [p for p in mode.peer_payloads if p not in payloads]
    if missing:
        out.append(f'\n{", ".join(missing)}: measured only when a peer is installed.')
    return '\n'.join(out) + '\n'


def plot(path: str, mode: Mode, lat: Dict, memcpy: Dict, fanout: Dict,
         peers: List[str] = ()) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5.2))
    sizes = {p: payload_bytes(p) for p in mode.payloads}
    for label in ALL_ROWS + list(peers):
        points = []
        for payload in mode.payloads:
            run = lat.get((label, payload))  # a peer runs only at the peers table's payloads
            latency = memcpy[payload]['warm'] if label == MEMCPY else \
                memcpy[payload]['idle'] if label == MEMCPY_IDLE else run.latency if run else None
            if latency:
                points.append((sizes[payload], latency['p50'], latency['p90']))
        if points:
            xs, p50, p90 = zip(*points)
            line, = left.plot(xs, p50, marker='o', label=label,
                              linestyle=':' if label == MEMCPY_IDLE else
                              '--' if label == MEMCPY else '-')
            left.fill_between(xs, p50, p90, color=line.get_color(), alpha=0.12)
    left.set_xscale('log')
    left.set_yscale('log')
    left.set_xlabel('payload bytes')
    left.set_ylabel('latency publish -> callback, ms (p50; band to p90)')
    left.set_title('Latency against payload size')
    left.grid(True, which='both', alpha=0.3)
    left.legend(fontsize=8)

    for payload in mode.fanout_payloads:
        for t in FANOUT_TRANSPORTS:
            points = [(n, fanout[(t, payload, n)].pub_cpu_ms) for n in mode.fanout_subscribers
                      if fanout[(t, payload, n)].pub_cpu_ms is not None]
            wrong = fanout_implausibility(points)
            if wrong:  # said in the checks table; a wrong figure is not drawn as a result
                right.plot([], [], linestyle='none', label=f'{t}, {payload}: {wrong}')
            elif points:
                xs, ys = zip(*points)
                right.plot(xs, ys, marker='o', label=f'{t}, {payload}')
    right.set_xlabel('subscribers')
    right.set_ylabel('publisher CPU per message, ms')
    right.set_yscale('log')
    right.set_xticks(mode.fanout_subscribers)
    right.set_title('Publisher CPU against fan-out')
    right.grid(True, which='both', alpha=0.3)
    right.legend(fontsize=8)
    fig.suptitle(f'rosidl_buffer_py benchmark ({mode.name} mode, {os.cpu_count()} cores)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- main -----------------------------------------------------------------------------------

def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--quick', action='store_true',
                       help='fewer frames, payloads, rates and fan-outs (under two minutes)')
    group.add_argument('--smoke', action='store_true',
                       help='the smallest run that still fills every table row (for tests)')
    parser.add_argument('--rounds', type=int, default=None,
                        help='rounds of the paired stock and CPU-path latency runs '
                             '(default: 5 in the full mode, 1 otherwise)')
    parser.add_argument('--out', default='benchmark_out',
                        help='directory for benchmark.md and benchmark.png (default: %(default)s)')
    args = parser.parse_args(argv)
    mode = MODES['smoke' if args.smoke else 'quick' if args.quick else 'full']
    if args.rounds is not None:
        if args.rounds < 1:
            parser.error(f'--rounds must be at least 1, got {args.rounds}')
        mode = dataclasses.replace(mode, latency_rounds=args.rounds)
    os.makedirs(args.out, exist_ok=True)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    own_domain = claim_domain_id()
    began, load_before, steal = time.monotonic(), os.getloadavg(), StealMeter()
    started_at = time.time() - 1.0  # for the Fast DDS files of nodes it had to SIGKILL

    def progress(text: str) -> None:
        print(f'[{time.monotonic() - began:6.1f} s] {text}', file=sys.stderr, flush=True)

    memcpy = {p: measure_memcpy(p, mode.memcpy_repeat, 1.0 / mode.rate) for p in mode.payloads}
    peer_versions = {t.label: peer_version(t) for t in PEERS}
    installed_peers = [label for label, version in peer_versions.items() if version]
    for t in PEERS:
        if not peer_versions[t.label]:
            progress(skipped_note(t))
    # payloads the peers table adds to the latency table's are measured only with a peer
    peer_payloads = [p for p in mode.peer_payloads if p in mode.payloads or installed_peers]
    lat: Dict[Tuple[str, str], Result] = {}
    rounds: Dict[Tuple[str, str], List[Result]] = {}
    for payload in mode.payloads:
        for index in range(mode.latency_rounds):
            steal = StealMeter()
            if payload_bytes(payload) <= PAIR_MAX_BYTES:
                paired = measure_paired(payload, mode.frames, mode.rate, index)
            else:  # frames would overlap: one after the other, in alternating order
                order = PAIRED if index % 2 == 0 else PAIRED[::-1]
                paired = {label: measure(label, payload, 1, mode.frames, mode.rate)
                          for label in order}
            for label, r in paired.items():
                rounds.setdefault((label, payload), []).append(r)
                progress(f'latency {label:<22} {payload:>15} round {index + 1}: p50 '
                         f'{_fmt(r.latency.get("p50"))} ms, pub CPU {_fmt(r.pub_cpu_ms)} ms/msg,'
                         f' backends {r.backends}, CPU steal {_pct(steal.fraction())}')
        for t in TRANSPORTS:
            if t.label not in PAIRED:
                rounds[(t.label, payload)] = [latency_run(t.label, payload, mode, progress)]
        if payload in peer_payloads:  # in the same rounds' conditions as ours
            for index in range(mode.latency_rounds):
                for label in installed_peers:
                    rounds.setdefault((label, payload), []).append(latency_run(
                        label, payload, mode, progress, f' round {index + 1}'))
        for label in [t.label for t in TRANSPORTS] + installed_peers:
            if (label, payload) in rounds:
                lat[(label, payload)] = median_run(rounds[(label, payload)])
    for payload in peer_payloads:
        if payload in mode.payloads:
            continue
        # a payload only the peers table has: its own runs of ours, once, and of the peers
        memcpy[payload] = measure_memcpy(payload, mode.memcpy_repeat, 1.0 / mode.rate)
        for label in PEER_TABLE_OURS:
            lat[(label, payload)] = latency_run(label, payload, mode, progress)
        for label in installed_peers:
            lat[(label, payload)] = median_run([
                latency_run(label, payload, mode, progress, f' round {index + 1}')
                for index in range(mode.latency_rounds)])
    rates: Dict[Tuple[str, str], Tuple[Optional[float], str]] = {}
    for payload in mode.rate_payloads:
        for t in TRANSPORTS:
            rates[(t.label, payload)] = max_sustained_rate(t.label, payload, mode)
            progress(f'max rate {t.label:<22} {payload:>15}: {rates[(t.label, payload)][1]} Hz')
    fanout: Dict[Tuple[str, str, int], Result] = {}
    for payload in mode.fanout_payloads:
        for t in FANOUT_TRANSPORTS:
            for n in mode.fanout_subscribers:
                if n == 1 and (t, payload) in lat:  # the same run as the latency table's
                    fanout[(t, payload, n)] = lat[(t, payload)]
                    continue
                r = fanout[(t, payload, n)] = measure(t, payload, n, mode.frames, mode.rate)
                progress(f'fan-out {t:<22} {payload:>15} x{n}: pub CPU '
                         f'{_fmt(r.pub_cpu_ms)} ms/msg, sub CPU {_fmt(r.sub_cpu_ms)} ms/msg')

    from launch_free_demos.bench import mixed as bench_mixed
    mixed = []
    for payload in mode.mixed_payloads:
        _, width, height, _ = PAYLOAD[payload]
        graphs = list(bench_mixed.GRAPHS)
        try:
            per_frame = bench_mixed.measure(width, height, 10.0, 10, 40, 2, graphs)
        except RuntimeError as exc:  # a graph lost frames: say so, keep the rest of the report
            mixed.append(f'{payload}: not measured, {str(exc)[:300]}')
            progress(f'mixed graph {payload}: not measured ({str(exc)[:300]})')
            continue
        mixed.append(bench_mixed.table(per_frame, graphs, payload.split()[0], 10.0, 10, 40, 2))
        progress(f'mixed graph {payload}: ' + ', '.join(
            f'{graph} {label} {statistics.median(v):.2f} ms'
            for (graph, label), v in per_frame.items()))

    latencies: Dict[str, Dict[str, List[Dict[str, dict]]]] = {}
    latency_tables = []
    for payload in mode.mixed_latency_payloads:
        _, width, height, _ = PAYLOAD[payload]
        results = latencies[payload] = {}
        for graph in MIXED_LATENCY_GRAPHS:
            try:
                run = bench_mixed.run_latency(
                    graph, width, height, mode.mixed_latency_frames, MIXED_LATENCY_RATE, 10,
                    next_topic('mixed_latency'))
            except RuntimeError as exc:
                progress(f'mixed latency {graph} {payload}: not measured ({str(exc)[:300]})')
                continue
            results.setdefault(graph, []).append(run)
            progress(f'mixed latency {graph:<12} {payload:>15}: ' + ', '.join(
                f'{label} p99 {r["p99"]:.1f} ms' for label, r in run.items()))
        latency_tables.append(bench_mixed.latency_table(
            results, MIXED_LATENCY_GRAPHS, payload.split()[0], MIXED_LATENCY_RATE,
            mode.mixed_latency_frames, 10))
    churn_table = None
    if mode.churn_seconds:
        from launch_free_demos.bench import churn as bench_churn
        rows = [(graph, bench_churn.run_graph(graph == 'ours', mode.churn_seconds, 1920, 1080,
                                              30.0, 2.0, 3.0)) for graph in ('stock', 'ours')]
        churn_table = bench_churn.table(rows, '1920x1080', 30.0, mode.churn_seconds, 2.0, 3.0, 0)
        progress('churn: ' + '; '.join(f'{graph} {row}' for graph, row in rows))

    checks = target_checks(mode, lat, rates, fanout, memcpy, rounds)
    checks += mixed_latency_checks(latencies)
    if own_domain:  # a domain of our own: what its dead participants left
        remove_fastdds_leftovers(started_at, int(os.environ['ROS_DOMAIN_ID']))
    load_after = os.getloadavg()
    header = (f'# rosidl_buffer_py benchmark: zero-copy images against stock rclpy\n\n'
              f'{mode.name} mode, {datetime.datetime.now().isoformat(timespec="seconds")}, '
              f'{platform.node()}, {os.cpu_count()} cores, load average '
              f'{load_before[0]:.2f} before / {load_after[0]:.2f} after, CPU steal '
              f'{_pct(steal.fraction())} of the run, '
              f'{os.environ["RMW_IMPLEMENTATION"]}, ROS_DOMAIN_ID {os.environ["ROS_DOMAIN_ID"]}'
              f', {time.monotonic() - began:.0f} s. Publisher and subscribers in separate '
              f'processes on this machine; a shared machine makes every number noisy.')
    text = markdown(mode, lat, memcpy, rates, fanout, checks, header)
    text += '\n' + peers_markdown(mode, peer_payloads, lat, memcpy, peer_versions, argv)
    if mixed:
        text += ('\n\n## Mixed graph: a legacy listener beside a buffer-aware subscriber\n\n'
                 + '\n\n'.join(mixed) + '\n')
    if latency_tables:
        text += ('\n\n## Mixed graph latency: a zero-copy subscriber alone, beside a plain '
                 'one, and the same graph of stock endpoints\n\n'
                 + '\n\n'.join(latency_tables) + '\n')
    if churn_table:
        text += '\n\n## Subscriber churn, ours against stock\n\n' + churn_table + '\n'
    png = os.path.join(args.out, 'benchmark.png')
    plot(png, mode, lat, memcpy, fanout, installed_peers)
    with open(os.path.join(args.out, 'benchmark.md'), 'w') as f:
        f.write(text + '\n![benchmark plot](benchmark.png)\n')
    print(text)
    print(f'Wrote {os.path.join(args.out, "benchmark.md")} and {png}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
