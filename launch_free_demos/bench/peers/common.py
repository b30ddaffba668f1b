"""What the benchmark's peer nodes share: parameters, frames, the progress line, the report.

A peer node (``iceoryx2_peer``, ``zenoh_peer``) is one process, publisher or subscriber, that
behaves towards the benchmark as image_publisher / image_subscriber do, without rclpy:

- it takes the same parameter names (as ``--name=value``, see :data:`PARAMETERS`);
- the publisher writes each frame into the transport's memory (the same pseudo-random pixels,
  its counter in the first 8 bytes), takes the CRC32 of the payload, stamps the wall-clock time
  (nanoseconds) just before it publishes, and sends counter, CRC32 and stamp along;
- the subscriber takes the latency at the start of its callback, then makes a readable numpy
  array over the payload (timed: "time to a numpy view"), checks the CRC32 and the counter,
  logs ``received N (M distinct)`` on stderr every ``report_period_sec`` (the benchmark's CPU
  window marks) and prints a JSON report line at exit, with the keys image_subscriber's report
  has that the benchmark reads.

No rclpy is imported: a peer costs what its own library costs.
"""
import argparse
import json
import signal
import struct
import sys
import time
import zlib
from dataclasses import dataclass, field
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy

from launch_free_demos.bench.stats import percentiles

#: The report line of rosidl_buffer_py.report (the benchmark reads a peer's as a node's),
#: written out here: importing that package would import rclpy, which a peer must not pay.
REPORT_PREFIX = 'REPORT '

BYTES_PER_PIXEL = {'mono8': 1, 'rgb8': 3, 'bgr8': 3, 'rgba8': 4}
#: stamp (ns since the epoch), counter, CRC32 of the payload: sent beside each frame.
FRAME_HEADER = struct.Struct('<QQI')
_COUNTER = struct.Struct('<Q')


def parse_parameters(program: str, argv: Optional[List[str]] = None,
                     extra: Sequence[Tuple[str, str]] = ()) -> argparse.Namespace:
    """The parameters image_publisher and image_subscriber take that a peer needs, plus
    ``role`` and the peer's own required ``extra`` (option, help) string options."""
    parser = argparse.ArgumentParser(prog=program, description=__doc__.splitlines()[0])
    add = parser.add_argument
    add('--role', choices=('publisher', 'subscriber'), required=True)
    add('--topic', required=True, help='the run\'s own name (service name / key expression)')
    add('--width', type=int, default=640)
    add('--height', type=int, default=480)
    add('--encoding', default='rgb8', choices=sorted(BYTES_PER_PIXEL))
    add('--count', type=int, default=10, help='publisher: frames to send')
    add('--rate_hz', type=float, default=10.0)
    add('--phase_sec', type=float, default=-1.0,
        help='send at wall-clock times t with t mod (1 / rate_hz) == phase_sec; -1 = off')
    add('--wait_for_subscribers', type=int, default=1)
    add('--wait_timeout_sec', type=float, default=30.0)
    add('--settle_sec', type=float, default=0.5)
    add('--linger_sec', type=float, default=2.0)
    add('--expected_count', type=int, default=0, help='subscriber: exit after this many')
    add('--timeout_sec', type=float, default=60.0)
    add('--report_period_sec', type=float, default=1.0)
    add('--label', default=program, help='the name in the progress lines')
    for option, text in extra:
        add(option, required=True, help=text)
    args = parser.parse_args(argv)
    if args.width < 1 or args.height < 1:
        parser.error(f'width and height must be at least 1, got {args.width}x{args.height}')
    if args.rate_hz <= 0:
        parser.error(f'rate_hz must be > 0, got {args.rate_hz}')
    return args


def payload_shape(args: argparse.Namespace):
    """(height, width[, channels]) of the image a subscriber lays over the payload."""
    channels = BYTES_PER_PIXEL[args.encoding]
    return (args.height, args.width) if channels == 1 else (args.height, args.width, channels)


def payload_size(args: argparse.Namespace) -> int:
    return args.width * args.height * BYTES_PER_PIXEL[args.encoding]


def pixels(nbytes: int) -> numpy.ndarray:
    """The frame's pixels (the same bytes as image_publisher's, seed 7)."""
    return numpy.random.default_rng(7).integers(0, 256, size=nbytes, dtype=numpy.uint8)


def write_frame(target: numpy.ndarray, source: numpy.ndarray, counter: int) -> int:
    """Write the frame into ``target`` (the transport's memory, flat uint8), its counter in the
    first 8 bytes; return the CRC32 of what was written."""
    target[...] = source
    if target.nbytes >= _COUNTER.size:
        target[:_COUNTER.size] = numpy.frombuffer(_COUNTER.pack(counter), dtype=numpy.uint8)
    return zlib.crc32(target)


def frame_header(counter: int, crc: int) -> bytes:
    """The header of a frame, stamped now: take it just before publishing."""
    return FRAME_HEADER.pack(time.time_ns(), counter, crc)


class FrameCheck(NamedTuple):
    counter: int
    ok: bool


def check_frame(header: bytes, view: numpy.ndarray) -> FrameCheck:
    """CRC32 and embedded counter of a received frame against its header."""
    _, counter, crc = FRAME_HEADER.unpack(header)
    flat = view.reshape(-1)
    ok = zlib.crc32(flat) == crc and (
        flat.nbytes < _COUNTER.size or _COUNTER.unpack(flat[:_COUNTER.size].tobytes())[0]
        == counter)
    return FrameCheck(counter, ok)


def latency_ms(header: bytes) -> float:
    return (time.time_ns() - FRAME_HEADER.unpack_from(header)[0]) / 1e6


class Ticker:
    """The publisher's send times: ``rate_hz``, optionally on image_publisher's wall-clock
    grid (``phase_sec``)."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.period = 1.0 / args.rate_hz
        self.next = time.monotonic()
        if args.phase_sec >= 0:
            self.next += (args.phase_sec - time.time()) % self.period

    def wait(self) -> None:
        """Sleep until the next send time, then advance it by one period."""
        delay = self.next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self.next += self.period


def publish_frames(args: argparse.Namespace, stop: 'Stop', matched: Callable[[], int],
                   send: Callable[[int], None]) -> int:
    """A peer publisher's life, as image_publisher's: wait until ``matched()`` counts
    ``wait_for_subscribers``, settle, ``send(counter)`` ``count`` frames at ``rate_hz``, linger
    until the subscribers leave, print the report. Returns the exit status."""
    deadline = time.monotonic() + args.wait_timeout_sec
    while matched() < args.wait_for_subscribers:
        if time.monotonic() > deadline or stop.requested:
            print(f'{args.label}: {matched()} of {args.wait_for_subscribers} subscribers after '
                  f'{args.wait_timeout_sec} s', file=sys.stderr)
            return 1
        time.sleep(0.01)
    time.sleep(args.settle_sec)
    ticker, published = Ticker(args), 0
    while published < args.count and not stop.requested:
        ticker.wait()
        send(published)
        published += 1
    linger_until = time.monotonic() + args.linger_sec
    while matched() > 0 and time.monotonic() < linger_until and not stop.requested:
        time.sleep(0.05)
    print_report({'role': 'publisher', 'node': args.label, 'published': published,
                  'params': vars(args)})
    return 0


@dataclass
class Received:
    """What a peer subscriber saw; :meth:`report` in image_subscriber's terms."""

    args: argparse.Namespace
    backends: Dict[str, int] = field(default_factory=dict)
    latencies: List[float] = field(default_factory=list)
    view_ms: List[float] = field(default_factory=list)
    seen: set = field(default_factory=set)
    received: int = 0
    duplicates: int = 0
    checksum_failures: int = 0
    started: float = field(default_factory=time.monotonic)

    def frame(self, header: bytes, latency: float, view_ns: int, view: numpy.ndarray,
              backend: str) -> None:
        """Note a frame: its ``latency`` (ms, taken at the callback's start), the ns from then
        to its readable ``view``, and how it came (``backend``: shared memory or not)."""
        self.view_ms.append(view_ns / 1e6)
        self.latencies.append(latency)
        self.backends[backend] = self.backends.get(backend, 0) + 1
        self.received += 1
        check = check_frame(header, view)
        if check.counter in self.seen:
            self.duplicates += 1
        self.seen.add(check.counter)
        if not check.ok:
            self.checksum_failures += 1

    def done(self) -> bool:
        a = self.args
        return (bool(a.expected_count) and len(self.seen) >= a.expected_count) or (
            bool(a.timeout_sec) and time.monotonic() - self.started > a.timeout_sec)

    def log_progress(self) -> None:
        """The progress line the benchmark's CPU window is marked by (rclpy's log format)."""
        print(f'[INFO] [{time.time():.9f}] [{self.args.label}]: received {self.received} '
              f'({len(self.seen)} distinct)', file=sys.stderr, flush=True)

    def report(self) -> dict:
        expected = self.args.expected_count
        span = expected or (max(self.seen) + 1 if self.seen else 0)
        missing = sorted(set(range(span)) - self.seen)
        return {
            'role': 'subscriber', 'node': self.args.label, 'params': vars(self.args),
            'received': self.received, 'distinct': len(self.seen),
            'duplicates': self.duplicates, 'gaps': len(missing), 'missing': missing[:20],
            'checksum_failures': self.checksum_failures,
            'backends': self.backends,
            'latency_ms': percentiles(self.latencies or [0.0], digits=3),
            'view_ms': percentiles(self.view_ms or [0.0], digits=3),
            'timed_out': bool(expected) and len(self.seen) < expected,
        }


class Stop:
    """SIGINT / SIGTERM set a flag that the peer's loops look at (then it reports and exits
    cleanly, removing its shared-memory files)."""

    def __init__(self) -> None:
        self.requested = False
        signal.signal(signal.SIGINT, self._set)
        signal.signal(signal.SIGTERM, self._set)

    def _set(self, *_) -> None:
        self.requested = True


def print_report(report: dict) -> None:
    """Print the peer's report line (see :data:`REPORT_PREFIX`)."""
    print(REPORT_PREFIX + json.dumps(report, sort_keys=True), flush=True)
