"""image_subscriber: receive and verify the frames of image_publisher, then report.

The report (a JSON line at exit): received, distinct, duplicates, gaps (and the first 20 missing
frames), the most publishers matched at once (``publishers``), the first and last frame seen,
checksum failures, backends seen, wrong-backend frames, latency percentiles and the time from
the callback's start to a readable numpy array over the image (``view_ms``). The parameters are
listed in :data:`PARAMETERS` (``image_subscriber --help`` prints them).
"""
import collections
import time

import numpy
import rclpy
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image

import rosidl_buffer_py
from rosidl_buffer_py import codec
from rosidl_buffer_py.image import from_input_msg
from rosidl_buffer_py.nodes.common import (
    QOS_PARAMETERS, Param, ParameterError, backend_stats, bad_parameter, declare_parameters,
    qos_profile, run_node, with_default)
from rosidl_buffer_py.registry import parse_acceptable_buffer_backends
from rosidl_buffer_py.nodes.frames import check_frame, latency_ms
from rosidl_buffer_py.report import print_report

DEFAULT_SENTINEL = '__default__'

SUMMARY = ('Receive the frames of image_publisher, verify each (counter, CRC32), log a summary '
           'periodically and print a JSON report at exit.')

#: Every ROS parameter of image_subscriber (legacy_image_subscriber: legacy defaults to true).
PARAMETERS = (
    Param('topic', 'image', 'topic to subscribe to'),
    Param('acceptable_buffer_backends', DEFAULT_SENTINEL,
          "the subscription option: which backends' descriptors to take (cpu, any, or names "
          f'such as demo); {DEFAULT_SENTINEL} = do not pass the option (default cpu)'),
    Param('expected_backend', '', 'count frames of any other backend as wrong_backend in the '
          "report; '' = no expectation", accepts="'', cpu or an installed backend"),
    Param('expected_count', 0, 'exit once this many distinct frames arrived; 0 = until stopped',
          minimum=0),
    Param('timeout_sec', 60.0, 'exit after this long; 0 = never', minimum=0),
    *QOS_PARAMETERS,
    Param('legacy', False, 'a plain rclpy subscription (no rosidl_buffer_py)'),
    Param('raw', False, 'legacy only: take serialized bytes and check they are canonical CDR'),
    Param('report_period_sec', 5.0, 'log a summary line this often; 0 = never', minimum=0),
    Param('work_sec', 0.0, 'seconds each callback spends after checking its frame (a slow '
          'subscriber, for fault tests); 0 = none', minimum=0),
)


def check_parameters(p: dict) -> None:
    """:raises ParameterError: A value :func:`declare_parameters` cannot check alone."""
    if p['expected_backend']:
        known = sorted({'cpu', *rosidl_buffer_py.get_installed_backends()})
        if p['expected_backend'] not in known:
            raise bad_parameter('expected_backend', p['expected_backend'],
                                "'' or one of " + ', '.join(known))
    if p['raw'] and not p['legacy']:
        raise bad_parameter('raw', True, 'false unless legacy is true')


def same_cdr(raw: bytes, canonical: bytes) -> bool:
    """Whether ``raw`` is the CDR ``canonical`` (legacy CDR, as ``serialize_message`` gives it),
    but for alignment padding: rmw's serialization, stock rclpy's too, skips padding bytes, so
    they keep whatever the reused DDS payload buffer held (checked: a stock publisher's frames
    differ from serialize_message's there). Bytes that differ must be zero in ``canonical``.
    """
    if len(raw) != len(canonical):
        return False
    if raw == canonical:
        return True
    ours = numpy.frombuffer(canonical, dtype=numpy.uint8)
    return not ours[numpy.frombuffer(raw, dtype=numpy.uint8) != ours].any()


class ImageSubscriber(Node):

    def __init__(self, legacy: bool = False) -> None:
        super().__init__('legacy_image_subscriber' if legacy else 'image_subscriber')
        try:
            p = declare_parameters(self, with_default(PARAMETERS, 'legacy', legacy))
            check_parameters(p)
        except ParameterError:
            self.destroy_node()
            raise
        self.params = p
        qos = qos_profile(p)
        self.latencies = []
        self.view_ms = []
        self.counters = collections.Counter()
        self.backends = collections.Counter()
        self.problems = []
        self.seen = set()
        self.last_counter = None
        self.last_size = 'none yet'
        self.start = time.monotonic()
        if p['legacy']:
            self.subscription = self.create_subscription(
                Image, p['topic'], self.on_raw if p['raw'] else self.on_image, qos,
                raw=p['raw'])
        else:
            kwargs = {}
            if p['acceptable_buffer_backends'] != DEFAULT_SENTINEL:
                kwargs['acceptable_buffer_backends'] = p['acceptable_buffer_backends']
            self.subscription = rosidl_buffer_py.create_subscription(
                self, Image, p['topic'], self.on_image, qos, **kwargs)
        if p['report_period_sec'] > 0:
            self.create_timer(p['report_period_sec'], self.log_summary)
        #: why run() ended: 'expected_count', 'timeout_sec', or None (a signal, or not yet)
        self.stopped_by = None
        #: the most publishers matched at once: frames of two publishers share counters
        self.most_publishers = 0
        self.get_logger().info(self.start_line())

    def start_line(self) -> str:
        """What this subscriber takes and when it stops, said once at start: a user who sees
        CPU copies learns here how to get zero-copy."""
        p = self.params
        if p['legacy']:
            takes = 'a plain rclpy subscription: every frame arrives as CPU bytes'
        else:
            chosen = p['acceptable_buffer_backends']
            accepted = 'cpu' if chosen == DEFAULT_SENTINEL else chosen
            installed = ', '.join(sorted(set(rosidl_buffer_py.get_installed_backends()) -
                                         {'cpu'})) or 'none'
            takes = f'accepting backends: {accepted}'
            if accepted.strip() == 'cpu':
                takes += (' (the default): frames arrive as CPU copies; for zero-copy pass '
                          '-p acceptable_buffer_backends:=any, or one of the installed '
                          f'backends ({installed})')
        stops = []
        if p['expected_count']:
            stops.append(f"after {p['expected_count']} distinct frames")
        if p['timeout_sec']:
            stops.append(f"after {p['timeout_sec']:g} s (timeout_sec; 0 = never)")
        return (f"subscribed to {p['topic']}, {takes}; stops "
                f"{' or '.join(stops) if stops else 'on Ctrl-C only'}")

    def on_raw(self, raw: bytes) -> None:
        msg = deserialize_message(raw, Image)
        if not same_cdr(raw, bytes(codec.encode(msg))):
            self.problem('raw bytes are not the canonical CPU encoding')
        self.on_image(msg)

    def on_image(self, msg: Image) -> None:
        started = time.perf_counter_ns()
        self.latencies.append(latency_ms(msg))
        self.time_view(msg, started)
        self.last_size = f'{msg.width}x{msg.height} {msg.encoding}, {len(msg.data):,} bytes'
        self.counters['received'] += 1
        data = msg.data
        backend = data.backend_type if isinstance(data, rosidl_buffer_py.Buffer) else (
            'cpu' if type(data).__name__ == 'array' else type(data).__name__)
        self.backends[backend] += 1
        expected = self.params['expected_backend']
        if expected and backend != expected:
            self.counters['wrong_backend'] += 1
        check = check_frame(msg)
        if not check.ok:
            self.counters['checksum_failures'] += 1
            self.problem(f'frame {check.counter}: {check.reason}')
        if check.counter is not None:
            if check.counter in self.seen:
                self.counters['duplicates'] += 1
            if self.last_counter is not None and check.counter < self.last_counter:
                self.counters['out_of_order'] += 1  # (one publisher: its counters increase)
            self.last_counter = check.counter
            self.seen.add(check.counter)
        if self.params['work_sec']:
            time.sleep(self.params['work_sec'])

    def time_view(self, msg: Image, started_ns: int) -> None:
        """Note how long after ``started_ns`` (the callback's start) a readable numpy array over
        the image exists: what a user's callback does first (the benchmark's "time to a numpy
        view"). No copy: ``from_input_msg(msg, clone=False)``."""
        try:
            from_input_msg(msg, clone=False)
        except (TypeError, ValueError):  # metadata no image follows: check_frame judges it
            return
        self.view_ms.append((time.perf_counter_ns() - started_ns) / 1e6)

    def problem(self, text: str) -> None:
        if len(self.problems) < 20:
            self.problems.append(text)

    def done(self) -> bool:
        p = self.params
        self.most_publishers = max(self.most_publishers,
                                   self.subscription.get_publisher_count())
        if p['expected_count'] and len(self.seen) >= p['expected_count']:
            self.stopped_by = 'expected_count'
        elif p['timeout_sec'] and time.monotonic() - self.start > p['timeout_sec']:
            self.stopped_by = 'timeout_sec'
        return self.stopped_by is not None

    def run(self) -> None:
        # spin_once returns after each callback: the last frame ends the loop at once; the
        # timeout only bounds how late timeout_sec is noticed (each idle wake-up of rclpy's
        # executor costs about half a millisecond of CPU)
        while not self.done():
            rclpy.spin_once(self, timeout_sec=0.25)

    def report(self) -> dict:
        p = self.params
        missing = []
        if self.seen:
            span = p['expected_count'] or (max(self.seen) + 1)
            missing = sorted(set(range(span)) - self.seen)
        report = {
            'role': 'subscriber', 'node': self.get_name(), 'params': p,
            'received': self.counters['received'], 'distinct': len(self.seen),
            'duplicates': self.counters['duplicates'], 'gaps': len(missing),
            'publishers': self.most_publishers,
            'out_of_order': self.counters['out_of_order'],
            'missing': missing[:20],
            'first_frame': min(self.seen) if self.seen else None,
            'last_frame': max(self.seen) if self.seen else None,
            'checksum_failures': self.counters['checksum_failures'],
            'wrong_backend': self.counters['wrong_backend'],
            'backends': dict(self.backends), 'problems': self.problems,
            'latency_ms': _percentiles(self.latencies), 'view_ms': _percentiles(self.view_ms),
            'late_over_200ms': sum(1 for value in self.latencies if value > 200.0),
            # it stopped because timeout_sec passed (with or without an expected_count)
            'timed_out': self.stopped_by == 'timeout_sec',
            'stopped_by': self.stopped_by or 'signal',
        }
        if hasattr(self.subscription, 'statistics'):
            report['statistics'] = self.subscription.statistics().as_dict()
            accepted = p['acceptable_buffer_backends']
            report['backend_stats'] = backend_stats(parse_acceptable_buffer_backends(
                None if accepted == DEFAULT_SENTINEL else accepted))
        return report

    def log_summary(self) -> None:
        # Cheap on purpose (the benchmark logs every 50 ms): not report(), whose subscription
        # statistics query the ROS graph.
        p50 = round(float(numpy.median(self.latencies)), 3) if self.latencies else 0.0
        self.get_logger().info(
            f"received {self.counters['received']} ({len(self.seen)} distinct), last "
            f"{self.last_size}, backends {dict(self.backends)}, latency p50 {p50} ms, checksum "
            f"failures {self.counters['checksum_failures']}")

    def finish(self) -> None:
        print_report(self.report())


def _percentiles(values) -> dict:
    """p50 / p90 / p99 / max of ``values`` in ms, rounded to the microsecond (0 when empty)."""
    data = numpy.array(values) if values else numpy.zeros(1)
    return {name: round(float(numpy.percentile(data, q)), 3) for name, q in
            (('p50', 50), ('p90', 90), ('p99', 99), ('max', 100))}


def main(args=None) -> int:
    return run_node(lambda: ImageSubscriber(), lambda node: node.run(),
                    program='image_subscriber', summary=SUMMARY, parameters=PARAMETERS)


def legacy_main(args=None) -> int:
    return run_node(lambda: ImageSubscriber(legacy=True), lambda node: node.run(),
                    program='legacy_image_subscriber',
                    summary=SUMMARY.replace('Receive', 'With plain rclpy only, receive'),
                    parameters=with_default(PARAMETERS, 'legacy', True))


if __name__ == '__main__':
    raise SystemExit(main())
