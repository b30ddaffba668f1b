"""image_publisher: publish verifiable sensor_msgs/Image frames (cpu or a buffer backend).

Parameters: topic, backend (cpu | demo | any installed backend that can allocate), fill
(allocate: fill the backend's memory in place | from_cpu: copy a CPU frame into it), width,
height, encoding, rate_hz (0 = as fast as possible), count (0 = until stopped), reliability,
depth, wait_for_subscribers (start once this many are matched), wait_timeout_sec,
linger_sec (after the last frame, stay until subscribers leave or this long), first_frame
(counter of the first frame), wait_for_buffer_peers (also wait until this many buffer-aware
subscriptions are served by a channel), settle_sec (then wait this long: a DDS volatile reader
that matches after the writer may miss the first samples), phase_sec (when >= 0: send frames at
wall-clock times t with t mod (1 / rate_hz) == phase_sec), legacy (plain rclpy publisher).
"""
import time

import numpy
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import Image

import rosidl_buffer_py
from rosidl_buffer_py.image import allocate_image_msg
from rosidl_buffer_py.nodes.common import declare_qos_parameters, print_report, run_node
from rosidl_buffer_py.nodes.frames import pattern, stamp_frame


class ImagePublisher(Node):

    def __init__(self, legacy: bool = False) -> None:
        super().__init__('legacy_image_publisher' if legacy else 'image_publisher')
        p = {name: self.declare_parameter(name, default).value for name, default in [
            ('topic', 'image'), ('backend', 'cpu'), ('fill', 'allocate'), ('width', 640),
            ('height', 480), ('encoding', 'rgb8'), ('rate_hz', 30.0), ('count', 0),
            ('wait_for_subscribers', 0), ('wait_timeout_sec', 30.0), ('linger_sec', 5.0),
            ('first_frame', 0), ('wait_for_buffer_peers', 0), ('settle_sec', 0.5),
            ('phase_sec', -1.0), ('legacy', legacy)]}
        self.params = p
        qos = declare_qos_parameters(self)
        if p['fill'] not in ('allocate', 'from_cpu'):
            raise ValueError(f"fill must be 'allocate' or 'from_cpu', got {p['fill']!r}")
        if p['legacy'] and p['backend'] != 'cpu':
            raise ValueError('a legacy publisher can only publish backend cpu')
        self.publisher = self.create_publisher(Image, p['topic'], qos) if p['legacy'] else \
            rosidl_buffer_py.create_publisher(self, Image, p['topic'], qos)
        template = allocate_image_msg(p['height'], p['width'], p['encoding'])
        self.pixels = pattern(len(template.data))
        self.published = 0

    def make_frame(self, counter: int) -> Image:
        p = self.params
        if p['backend'] != 'cpu' and p['fill'] == 'from_cpu':
            # a camera frame in ordinary memory, copied into the backend at publish time; the
            # message gets no CPU payload of its own (freeing one after the stamp costs
            # milliseconds at 4K and is not part of publishing)
            msg = allocate_image_msg(0, p['width'], p['encoding'])  # metadata, no rows
            msg.height = p['height']
            frame = self.pixels.copy()
            stamp_frame(msg, counter, frame)
            msg.data = _from_cpu(p['backend'], frame)
            return msg
        msg = allocate_image_msg(p['height'], p['width'], p['encoding'], backend=p['backend'])
        flat = numpy.frombuffer(memoryview(msg.data), dtype=numpy.uint8)  # writable view
        flat[...] = self.pixels  # the camera writing its frame in place
        stamp_frame(msg, counter, flat)
        return msg

    def served_buffer_peers(self) -> int:
        if not hasattr(self.publisher, 'buffer_peers'):
            return 0
        return sum(1 for peer in self.publisher.buffer_peers() if peer['channel_serving'])

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
        linger_until = time.monotonic() + p['linger_sec']
        while self.publisher.get_subscription_count() > 0 and time.monotonic() < linger_until:
            rclpy.spin_once(self, timeout_sec=0.05)

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
            report['statistics'] = self.publisher.statistics()
        print_report(report)


def _from_cpu(backend: str, frame: numpy.ndarray):
    if backend == 'demo':
        from demo_buffer_backend import DemoBuffer
        return DemoBuffer.from_cpu(frame)
    raise ValueError(f"fill 'from_cpu' is implemented for the demo backend, not {backend!r}")


def main(args=None) -> int:
    return run_node(lambda: ImagePublisher(), lambda node: node.run())


def legacy_main(args=None) -> int:
    return run_node(lambda: ImagePublisher(legacy=True), lambda node: node.run())


if __name__ == '__main__':
    raise SystemExit(main())
