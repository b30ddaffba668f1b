"""image_subscriber: receive and verify the frames of image_publisher, then report.

Parameters: topic, acceptable_buffer_backends (``__default__``: do not pass the option, as
upstream's test nodes do), expected_backend (optional: count frames of any other backend as
wrong), expected_count (exit once that many distinct frames arrived; 0 = until stopped),
timeout_sec (give up after this long; 0 = never), reliability, depth, legacy (a plain rclpy
subscription), raw (legacy only: take serialized bytes and check they are canonical CDR),
report_period_sec (log a summary this often, default 5 s; 0 = never).
The report (a JSON line at exit): received, distinct, duplicates, gaps (and the first 20 missing
frames), checksum failures, backends seen, wrong-backend frames and latency percentiles.
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
from rosidl_buffer_py.nodes.common import declare_qos_parameters, print_report, run_node
from rosidl_buffer_py.nodes.frames import check_frame, latency_ms

DEFAULT_SENTINEL = '__default__'


class ImageSubscriber(Node):

    def __init__(self, legacy: bool = False) -> None:
        super().__init__('legacy_image_subscriber' if legacy else 'image_subscriber')
        p = {name: self.declare_parameter(name, default).value for name, default in [
            ('topic', 'image'), ('acceptable_buffer_backends', DEFAULT_SENTINEL),
            ('expected_backend', ''), ('expected_count', 0), ('timeout_sec', 60.0),
            ('legacy', legacy), ('raw', False), ('report_period_sec', 5.0)]}
        self.params = p
        qos = declare_qos_parameters(self)
        self.latencies = []
        self.counters = collections.Counter()
        self.backends = collections.Counter()
        self.problems = []
        self.seen = set()
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

    def on_raw(self, raw: bytes) -> None:
        msg = deserialize_message(raw, Image)
        if codec.encode(msg) != raw:  # legacy CDR, as serialize_message gives (padding zeroed)
            self.problem('raw bytes are not the canonical CPU encoding')
        self.on_image(msg)

    def on_image(self, msg: Image) -> None:
        self.latencies.append(latency_ms(msg))
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
            self.seen.add(check.counter)

    def problem(self, text: str) -> None:
        if len(self.problems) < 20:
            self.problems.append(text)

    def done(self) -> bool:
        p = self.params
        if p['expected_count'] and len(self.seen) >= p['expected_count']:
            return True
        return bool(p['timeout_sec']) and time.monotonic() - self.start > p['timeout_sec']

    def run(self) -> None:
        # spin_once returns after each callback: the last frame ends the loop at once; the
        # timeout only bounds how late timeout_sec is noticed (each idle wake-up of rclpy's
        # executor costs about half a millisecond of CPU)
        while not self.done():
            rclpy.spin_once(self, timeout_sec=0.25)

    def report(self) -> dict:
        p = self.params
        lat = numpy.array(self.latencies) if self.latencies else numpy.zeros(1)
        missing = []
        if self.seen:
            span = p['expected_count'] or (max(self.seen) + 1)
            missing = sorted(set(range(span)) - self.seen)
        report = {
            'role': 'subscriber', 'node': self.get_name(), 'params': p,
            'received': self.counters['received'], 'distinct': len(self.seen),
            'duplicates': self.counters['duplicates'], 'gaps': len(missing),
            'missing': missing[:20],
            'checksum_failures': self.counters['checksum_failures'],
            'wrong_backend': self.counters['wrong_backend'],
            'backends': dict(self.backends), 'problems': self.problems,
            'latency_ms': {name: round(float(numpy.percentile(lat, q)), 3) for name, q in
                           (('p50', 50), ('p90', 90), ('p99', 99), ('max', 100))},
            'timed_out': bool(p['expected_count']) and len(self.seen) < p['expected_count'],
        }
        if hasattr(self.subscription, 'statistics'):
            report['statistics'] = self.subscription.statistics()
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


def main(args=None) -> int:
    return run_node(lambda: ImageSubscriber(), lambda node: node.run())


def legacy_main(args=None) -> int:
    return run_node(lambda: ImageSubscriber(legacy=True), lambda node: node.run())


if __name__ == '__main__':
    raise SystemExit(main())
