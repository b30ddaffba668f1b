"""image_publisher: publish verifiable sensor_msgs/Image frames (cpu or a buffer backend).

Each frame carries its counter in its first bytes and a CRC32 in ``header.frame_id``
(``frames.py``); image_subscriber checks both. The parameters are listed in :data:`PARAMETERS`
(``image_publisher --help`` prints them).
"""
import time
import zlib

import numpy
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import Image

import rosidl_buffer_py
from rosidl_buffer_py.backend import BufferBackend
from rosidl_buffer_py.image import allocate_image_msg, encoding_info, supported_encodings
from rosidl_buffer_py.nodes.common import (
    QOS_PARAMETERS, Param, ParameterError, backend_stats, bad_parameter, declare_parameters,
    qos_profile, run_node, with_default)
from rosidl_buffer_py.nodes.frames import pattern, stamp_frame
from rosidl_buffer_py.report import print_report

SUMMARY = ('Publish verifiable sensor_msgs/Image frames (a counter and a CRC32 in each) from '
           'CPU memory or a buffer backend; image_subscriber checks them.')

#: Every ROS parameter of image_publisher (legacy_image_publisher: legacy defaults to true).
PARAMETERS = (
    Param('topic', 'image', 'topic to publish on'),
    Param('backend', 'cpu', 'where frames live: cpu (array.array, as stock rclpy) or a buffer '
          'backend', accepts='cpu or an installed backend that can allocate'),
    Param('fill', 'allocate', 'allocate: fill the backend memory in place; from_cpu: copy a '
          'CPU frame into it at publish time', choices=('allocate', 'from_cpu')),
    Param('width', 640, 'image width in pixels', minimum=1),
    Param('height', 480, 'image height in rows', minimum=1),
    Param('encoding', 'rgb8', 'sensor_msgs image encoding', accepts='mono8, rgb8, bgr8, rgba8, '
          'mono16, yuv422, bayer_*8/16, 8UC1 .. 64FC4, ...'),
    Param('rate_hz', 30.0, 'frames per second; 0 = as fast as possible', minimum=0),
    Param('count', 0, 'frames to publish; 0 = until stopped', minimum=0),
    *QOS_PARAMETERS,
    Param('wait_for_subscribers', 0, 'start publishing once this many subscriptions are '
          'matched', minimum=0),
    Param('wait_for_buffer_peers', 0, 'also wait until this many buffer-aware subscriptions '
          'are served by a descriptor channel', minimum=0),
    Param('wait_timeout_sec', 30.0, 'give up waiting for subscribers after this long '
          '(error, exit 1)', minimum=0),
    Param('settle_sec', 0.5, 'after the wait, spin this long before the first frame (a DDS '
          'volatile reader that matches after the writer may miss the first samples)',
          minimum=0),
    Param('linger_sec', 5.0, 'after the last frame, stay until subscribers leave or this long',
          minimum=0),
    Param('first_frame', 0, 'counter of the first frame', minimum=0),
    Param('phase_sec', -1.0, 'when >= 0: send frames at wall-clock times t with t mod '
          '(1 / rate_hz) == phase_sec; -1 = off'),
    Param('legacy', False, 'publish with a plain rclpy publisher (no rosidl_buffer_py); only '
          'backend cpu'),
    Param('report_period_sec', 5.0, 'log a summary line this often while publishing; 0 = '
          'never', minimum=0),
    Param('scratch_bytes', 0, 'before each frame, fill this many bytes of other memory and '
          "checksum them, as a frame's own fill does (benchmarks: a small frame on caches a "
          'big one would leave)', minimum=0),
)


def _can_allocate(backend: BufferBackend) -> bool:
    return type(backend).allocate is not BufferBackend.allocate


def check_parameters(p: dict) -> None:
    """Reject combinations and values :func:`declare_parameters` cannot check alone.

    :raises ParameterError: Naming the parameter, its value and what is accepted.
    """
    if p['backend'] != 'cpu':
        installed = rosidl_buffer_py.get_installed_backends()
        usable = ['cpu'] + sorted(n for n, b in installed.items()
                                 if n != 'cpu' and _can_allocate(b))
        if p['backend'] not in usable:
            raise bad_parameter('backend', p['backend'], 'one of ' + ', '.join(usable) + (
                ' (installed, cannot allocate: ' + ', '.join(sorted(set(installed) - set(usable)))
                + ')' if set(installed) - set(usable) else ''))
    try:
        encoding_info(p['encoding'])
    except ValueError:
        raise bad_parameter('encoding', p['encoding'], supported_encodings()) from None
    if p['legacy'] and p['backend'] != 'cpu':
        raise bad_parameter('backend', p['backend'], 'cpu for a legacy publisher')
    if p['phase_sec'] != -1.0 and not (p['phase_sec'] >= 0 and (
            p['rate_hz'] == 0 or p['phase_sec'] < 1.0 / p['rate_hz'])):
        raise bad_parameter('phase_sec', p['phase_sec'],
                            '-1 (off) or 0 <= phase_sec < 1 / rate_hz')


class ImagePublisher(Node):

    def __init__(self, legacy: bool = False) -> None:
        super().__init__('legacy_image_publisher' if legacy else 'image_publisher')
        try:
            p = declare_parameters(self, with_default(PARAMETERS, 'legacy', legacy))
            check_parameters(p)
        except ParameterError:
            self.destroy_node()
            raise
        self.params = p
        qos = qos_profile(p)
        self.publisher = self.create_publisher(Image, p['topic'], qos) if p['legacy'] else \
            rosidl_buffer_py.create_publisher(self, Image, p['topic'], qos)
        template = allocate_image_msg(p['height'], p['width'], p['encoding'])
        self.pixels = pattern(len(template.data))
        #: ``scratch_bytes``: its pattern and the memory filled from it before each frame
        scratch = p['scratch_bytes']
        self.scratch = (pattern(scratch), numpy.empty(scratch, numpy.uint8)) if scratch else None
        #: the backend of ``fill`` from_cpu, found as any backend is (None for cpu)
        self.backend = None if p['backend'] == 'cpu' else rosidl_buffer_py.get_backend(
            p['backend'])
        self.published = 0
        self.get_logger().info(self.start_line())

    def make_frame(self, counter: int) -> Image:
        p = self.params
        if self.scratch is not None:  # what a big frame's fill and checksum do to the caches
            source, memory = self.scratch
            memory[...] = source
            zlib.crc32(memory)
        if p['backend'] != 'cpu' and p['fill'] == 'from_cpu':
            # a camera frame in ordinary memory, copied into the backend at publish time; the
            # message gets no CPU payload of its own (freeing one after the stamp costs
            # milliseconds at 4K and is not part of publishing)
            msg = allocate_image_msg(0, p['width'], p['encoding'])  # metadata, no rows
            msg.height = p['height']
            frame = self.pixels.copy()
            stamp_frame(msg, counter, frame)
            msg.data = _from_cpu(self.backend, frame)
            return msg
        msg = allocate_image_msg(p['height'], p['width'], p['encoding'], backend=p['backend'])
        flat = numpy.frombuffer(memoryview(msg.data), dtype=numpy.uint8)  # writable view
        flat[...] = self.pixels  # the camera writing its frame in place
        stamp_frame(msg, counter, flat)
        return msg

    def start_line(self) -> str:
        """What this publisher sends, where, and what it waits for, said once at start."""
        p = self.params
        how = 'a plain rclpy publisher' if p['legacy'] else f"backend {p['backend']}" + (
            f" ({p['fill']})" if p['backend'] != 'cpu' else '')
        rate = f"{p['rate_hz']:g} Hz" if p['rate_hz'] > 0 else 'as fast as possible'
        count = f"{p['count']} frames" if p['count'] else 'frames until stopped'
        waits = [f"{p['wait_for_subscribers']} subscriptions"] if p['wait_for_subscribers'] \
            else []
        if p['wait_for_buffer_peers']:
            waits.append(f"{p['wait_for_buffer_peers']} served on descriptor channels")
        waiting = (f"; waiting up to {p['wait_timeout_sec']:g} s for " + ' and '.join(waits)
                   if waits else '')
        return (f"publishing {count} of {p['width']}x{p['height']} {p['encoding']} on "
                f"{self.publisher.topic_name} at {rate} with {how}{waiting}")

    def log_summary(self) -> None:
        """Cheap on purpose (no statistics query): frames so far and who is matched."""
        self.get_logger().info(
            f'published {self.published} frames; {self.publisher.get_subscription_count()} '
            f'subscriptions matched, {self.served_buffer_peers()} served on descriptor channels')

    def served_buffer_peers(self) -> int:
        if not hasattr(self.publisher, 'buffer_peers'):
            return 0
        return sum(1 for peer in self.publisher.buffer_peers() if peer.channel_serving)

    def run(self) -> None:
        p = self.params
        deadline = time.monotonic() + p['wait_timeout_sec']
        while (self.publisher.get_subscription_count() < p['wait_for_subscribers'] or
               self.served_buffer_peers() < p['wait_for_buffer_peers']):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.publisher.get_subscription_count()} of "
                                   f"{p['wait_for_subscribers']} subscribers and "
                                   f"{self.served_buffer_peers()} of "
                                   f"{p['wait_for_buffer_peers']} channels after "
                                   f"{p['wait_timeout_sec']} s; peers: "
                                   f"{getattr(self.publisher, 'buffer_peers', list)()}")
            rclpy.spin_once(self, timeout_sec=0.05)
        if p['report_period_sec'] > 0:
            self.log_summary()  # what it waited for is there: frames start
            self.create_timer(p['report_period_sec'], self.log_summary)
        settle_until = time.monotonic() + p['settle_sec']
        while time.monotonic() < settle_until:
            rclpy.spin_once(self, timeout_sec=0.05)
        period = 1.0 / p['rate_hz'] if p['rate_hz'] > 0 else 0.0
        next_time = time.monotonic()
        if p['phase_sec'] >= 0 and period:
            # frames on a wall-clock grid: two publishers given phases half a period apart
            # send alternately (the benchmark measures two transports under the same load)
            next_time += (p['phase_sec'] - time.time()) % period
            self.spin_until(next_time)
        while p['count'] == 0 or self.published < p['count']:
            self.publisher.publish(self.make_frame(p['first_frame'] + self.published))
            self.published += 1
            next_time += period
            self.spin_until(next_time)
        if p['report_period_sec'] > 0:
            self.log_summary()
        linger_until = time.monotonic() + p['linger_sec']
        while self.subscribers_left() and time.monotonic() < linger_until:
            rclpy.spin_once(self, timeout_sec=0.05)

    def subscribers_left(self) -> bool:
        """Whether some subscription is still matched, or still a buffer peer of ours: DDS
        unmatches a dead process's reader when its lease ends, and the publisher drops its
        channel when discovery says so, on a later callback (either may come first)."""
        peers = getattr(self.publisher, 'buffer_peers', None)
        return self.publisher.get_subscription_count() > 0 or bool(peers and peers())

    def spin_until(self, deadline: float) -> None:
        """Serve the node's callbacks until ``time.monotonic()`` reaches ``deadline``.

        The executor blocks until the deadline or a callback: between frames the node sleeps
        (polling would cost the publisher about 5 % of a core at any rate).
        """
        while (remaining := deadline - time.monotonic()) > 0:
            rclpy.spin_once(self, timeout_sec=remaining)

    def finish(self) -> None:
        report = {'role': 'publisher', 'node': self.get_name(), 'published': self.published,
                  'params': self.params}
        if hasattr(self.publisher, 'statistics'):
            report['statistics'] = self.publisher.statistics().as_dict()
            report['backend_stats'] = backend_stats([self.params['backend']])
        print_report(report)


def _from_cpu(backend: BufferBackend, frame: numpy.ndarray) -> rosidl_buffer_py.Buffer:
    """A copy of ``frame`` in ``backend``'s memory: one allocation, one memcpy."""
    buffer = backend.allocate(frame.nbytes)
    memoryview(buffer).cast('B')[:] = memoryview(frame).cast('B')
    return buffer


def main(args=None) -> int:
    return run_node(lambda: ImagePublisher(), lambda node: node.run(),
                    program='image_publisher', summary=SUMMARY, parameters=PARAMETERS)


def legacy_main(args=None) -> int:
    return run_node(lambda: ImagePublisher(legacy=True), lambda node: node.run(),
                    program='legacy_image_publisher',
                    summary=SUMMARY.replace('from CPU memory or a buffer backend',
                                            'with plain rclpy only'),
                    parameters=with_default(PARAMETERS, 'legacy', True))


if __name__ == '__main__':
    raise SystemExit(main())
