"""One process of a GPU frame exchange: ``python -m launch_free_demos.cuda_peer pub|sub ...``.

Used by ``./dev bench cuda`` and by the GPU tests (test/test_cuda_gpu.py), in real processes over
real Fast DDS. Frame ``i`` has every byte equal to ``value(i)``; a subscriber checks every frame
on the GPU (or the host) and reports, as one JSON line on stdout (and in ``--report``), what it
saw: counts, payload types, failures, latencies (publish -> frame usable where the consumer wants
it), CPU time per frame.

Publisher modes (``--mode``):

- ``cuda``: frames filled in place in a CudaBuffer (``allocate_image_msg(..., backend='cuda')``,
  written through ``torch.from_dlpack``), published by a buffer-aware publisher;
- ``stock``: frames filled on the GPU, copied to the host into the message (device-to-host), and
  published by a plain rclpy publisher;
- ``demo``: the same device-to-host copy, into a ``demo`` shared-memory buffer;
- ``small``: no GPU: a 1 KiB mono8 frame (``--width`` x ``--height``) filled on the host and
  published by a plain rclpy publisher, what a small message costs in ROS itself.

Subscriber modes: ``cuda`` (accepts the cuda backend: zero-copy), ``cpu`` (a buffer-aware
subscription that accepts CPU bytes only), ``legacy`` (a plain rclpy subscription), ``stock`` and
``demo`` (CPU bytes or a demo buffer, copied host-to-device), ``small`` (a plain rclpy subscription
checking on the host). ``--consumer torch|cupy`` picks the GPU library; ``--own-stream`` reads on
a stream of its own. A GPU subscriber makes its CUDA context and the check's kernels ready before
it says it is ready, as a perception node has its model loaded before frames come: the first
frame's latency is not torch's start-up.
"""
import argparse
import collections
import json
import os
import resource
import signal
import sys
import threading
import time
from typing import Any, Dict, List, Optional


def value(i: int) -> int:
    """The byte every position of frame ``i`` holds (never 0: a zeroed slot fails the check)."""
    return i % 251 + 1


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _set_stamp(msg, ns: int) -> None:
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)


class _Gpu:
    """The consumer library's few operations: fill, check, copies, streams."""

    def __init__(self, name: str, own_stream: bool) -> None:
        self.name = name
        if name == 'torch':
            import torch
            self.torch = torch
            self.stream = torch.cuda.Stream() if own_stream else None
        else:
            import cupy
            self.cupy = cupy
            self.stream = cupy.cuda.Stream(non_blocking=True) if own_stream else None

    def context(self):
        if self.stream is None:
            return _Null()
        return (self.torch.cuda.stream(self.stream) if self.name == 'torch' else self.stream)

    def from_dlpack(self, obj):
        return (self.torch.from_dlpack(obj) if self.name == 'torch'
                else self.cupy.from_dlpack(obj))

    def check(self, array, expected: int) -> bool:
        """Every byte equals ``expected`` (one reduction, read back)."""
        if self.name == 'torch':
            lo, hi = self.torch.aminmax(array)
            return (int(lo), int(hi)) == (expected, expected)
        return (int(array.min()), int(array.max())) == (expected, expected)

    def warm_up(self) -> None:
        """Make the CUDA context and the check's kernels ready (a first use costs ~0.2 s)."""
        with self.context():
            if self.name == 'torch':
                self.check(self.torch.ones(16, dtype=self.torch.uint8, device='cuda'), 1)
            else:
                self.check(self.cupy.ones(16, dtype=self.cupy.uint8), 1)
        self.synchronize()

    def synchronize(self) -> None:
        if self.name == 'torch':
            (self.stream or self.torch.cuda.current_stream()).synchronize()
        else:
            (self.stream or self.cupy.cuda.get_current_stream()).synchronize()

    def upload(self, host) -> Any:
        """A device copy of a host uint8 array (host-to-device)."""
        if self.name == 'torch':
            import numpy
            return self.torch.from_numpy(numpy.asarray(host)).to('cuda')
        return self.cupy.asarray(host)


class _Null:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def publish(args) -> Dict[str, Any]:
    import numpy
    import rclpy
    from sensor_msgs.msg import Image

    import rosidl_buffer_py
    from rosidl_buffer_py.image import allocate_image_msg

    rclpy.init()
    node = rclpy.create_node(f'cuda_pub_{os.getpid()}')
    if args.mode in ('stock', 'small'):
        pub = node.create_publisher(Image, args.topic, args.depth)
    else:
        pub = rosidl_buffer_py.create_publisher(node, Image, args.topic, args.depth)
    deadline = time.monotonic() + args.wait_timeout
    while pub.get_subscription_count() < args.wait_subscribers and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    if args.wait_buffer_peers and args.mode != 'stock':
        pub.wait_for_buffer_peers(args.wait_buffer_peers,
                                  timeout_sec=max(0.1, deadline - time.monotonic()))
    on_gpu = args.mode != 'small'
    stream = source = None
    if on_gpu:
        import torch
        stream = torch.cuda.Stream()
        source = torch.empty(args.height * args.width * 3, dtype=torch.uint8, device='cuda')
    cpu0 = _cpu_seconds()
    period = 1.0 / args.rate
    next_at = time.monotonic()
    addresses = set()
    for i in range(args.frames):
        next_at += period
        if on_gpu:
            msg = _gpu_frame(args, i, stream, source, addresses)
        else:
            msg = allocate_image_msg(args.height, args.width, 'mono8')
            numpy.frombuffer(msg.data, numpy.uint8)[:] = value(i)
        msg.header.frame_id = str(i)
        _set_stamp(msg, time.time_ns())
        pub.publish(msg)
        del msg
        rclpy.spin_once(node, timeout_sec=max(0.0, next_at - time.monotonic()))
    cpu = _cpu_seconds() - cpu0
    report = {'role': 'pub', 'mode': args.mode, 'frames': args.frames,
              'cpu_ms_per_frame': 1000 * cpu / max(1, args.frames),
              'slot_addresses': len(addresses)}
    if args.mode not in ('stock', 'small'):  # frames written through the steady lane
        report['published_on_lane'] = pub.statistics().published_on_lane
    if args.mode == 'cuda':
        from rosidl_buffer_py.registry import get_backend
        report['stats'] = get_backend('cuda').stats()
    _emit(args, report)
    if args.hang:
        signal.pause()  # until the test kills it
    end = time.monotonic() + args.linger
    while time.monotonic() < end and pub.get_subscription_count() > 0:
        rclpy.spin_once(node, timeout_sec=0.05)
    node.destroy_node()
    rclpy.shutdown()
    return report


def _gpu_frame(args, i: int, stream, source, addresses: set):
    """Frame ``i`` written on the GPU on ``stream``: in place in a CudaBuffer (``cuda``), or into
    ``source`` then copied to the host message (``stock``, ``demo``)."""
    import numpy
    import torch

    from rosidl_buffer_py.image import allocate_image_msg
    with torch.cuda.stream(stream):
        if args.mode == 'cuda':
            msg = allocate_image_msg(args.height, args.width, 'rgb8', backend='cuda')
            target = torch.from_dlpack(msg.data)  # the consumer's stream: ours
            addresses.add(msg.data.address)
        else:
            if args.mode == 'stock':
                msg = allocate_image_msg(args.height, args.width, 'rgb8')
                host = torch.from_numpy(numpy.frombuffer(msg.data, numpy.uint8))
            else:
                msg = allocate_image_msg(args.height, args.width, 'rgb8', backend='demo')
                host = torch.from_numpy(numpy.asarray(msg.data))
            target = source
        if args.slow:  # a frame written chunk by chunk by slow kernels: never seen torn
            chunks = 16
            step = -(-target.numel() // chunks)
            for c in range(chunks):
                torch.cuda._sleep(args.slow)
                target[c * step:(c + 1) * step].fill_(value(i))
        else:
            target.fill_(value(i))
        if args.mode != 'cuda':
            host.copy_(target)  # device-to-host, synchronous: the bytes are on the host
    return msg


def subscribe(args) -> Dict[str, Any]:
    import hashlib

    import numpy
    import rclpy
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image

    import rosidl_buffer_py

    gpu = _Gpu(args.consumer, args.own_stream) if args.mode in ('cuda', 'stock', 'demo') \
        else None
    if gpu is not None:
        gpu.warm_up()
    rclpy.init()
    node = rclpy.create_node(f'cuda_sub_{os.getpid()}')
    got: Dict[str, Any] = {'role': 'sub', 'mode': args.mode, 'frames': 0, 'failures': [],
                           'types': collections.Counter(), 'latency_ms': [], 'hashes': {},
                           'pointer_matches': 0, 'addresses': set(), 'cpu_frames': []}
    held = collections.deque(maxlen=args.hold or None)
    done = threading.Event()

    def check_frame(i: int, data, msg_bytes: Optional[bytes]) -> None:
        got['types'][type(data).__name__] += 1
        if args.mode == 'cuda' and type(data).__name__ != 'CudaBuffer':
            got['cpu_frames'].append(i)
        if msg_bytes is not None and args.hash:
            got['hashes'][str(i)] = hashlib.sha1(msg_bytes).hexdigest()
        if gpu is not None:
            with gpu.context():
                if type(data).__name__ == 'CudaBuffer':
                    array = gpu.from_dlpack(data)
                    pointer = (array.data_ptr() if gpu.name == 'torch' else array.data.ptr)
                    got['pointer_matches'] += pointer == getattr(data, 'address', None)
                    got['addresses'].add(getattr(data, 'address', None))
                else:
                    host = numpy.frombuffer(data, numpy.uint8) if not hasattr(data, 'to_bytes') \
                        else numpy.asarray(data)
                    array = gpu.upload(host)  # host-to-device
                ok = gpu.check(array, value(i))
                if args.hold:
                    held.append((i, data, array))
        else:
            view = numpy.frombuffer(data, numpy.uint8)
            ok = bool(view.size) and int(view.min()) == int(view.max()) == value(i)
        if not ok:
            got['failures'].append(i)

    def on_image(msg) -> None:
        if args.mode == 'legacy':  # raw: the CDR bytes, as a stock node gets them
            msg = deserialize_message(msg, Image)
        i = int(msg.header.frame_id)
        check_frame(i, msg.data, _content(msg) if args.hash else None)
        stamp = _stamp_ns(msg)
        now_ns = time.time_ns()
        got['latency_ms'].append((now_ns - stamp) / 1e6)
        got['frames'] += 1
        if got['frames'] >= args.frames:
            done.set()

    aware = None  # the buffer-aware subscription
    if args.mode == 'legacy':
        node.create_subscription(Image, args.topic, on_image, args.depth, raw=True)
    elif args.mode in ('stock', 'small'):
        node.create_subscription(Image, args.topic, on_image, args.depth)
    else:
        accept = {'cuda': 'cuda', 'cpu': 'cpu', 'demo': 'demo'}[args.mode]
        aware = rosidl_buffer_py.create_subscription(node, Image, args.topic, on_image,
                                                     args.depth,
                                                     acceptable_buffer_backends=accept)
    if args.ready_file:
        open(args.ready_file, 'w').close()
    cpu0 = None
    deadline = time.monotonic() + args.timeout
    last = (0, time.monotonic())  # frames so far, when the last one came
    while not done.is_set() and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
        now = time.monotonic()
        if got['frames'] != last[0]:
            last = (got['frames'], now)
        elif got['frames'] and now - last[1] > args.idle:
            break  # the rest was lost (a transport that drops frames is measured as it is)
        if cpu0 is None and got['frames']:
            cpu0 = (_cpu_seconds(), got['frames'])
    if cpu0 is not None and got['frames'] > cpu0[1]:
        got['cpu_ms_per_frame'] = 1000 * (_cpu_seconds() - cpu0[0]) / (got['frames'] - cpu0[1])
    if args.hold:
        got['held'] = len(held)
        if args.recheck_after:  # e.g. after its publisher was killed: still valid?
            _emit(args, {'role': 'sub', 'phase': 'holding', 'frames': got['frames']})
            time.sleep(args.recheck_after)
        with gpu.context():
            got['held_failures'] = [i for i, _, array in held if not gpu.check(array, value(i))]
    got['types'] = dict(got['types'])
    if aware is not None:  # frames its steady step delivered, opened by the steady opener
        got['delivered_steady'] = aware.statistics().delivered_steady
    got['addresses'] = len(got['addresses'])
    lat = sorted(got.pop('latency_ms'))
    if lat:
        got['latency_p50_ms'] = lat[len(lat) // 2]
        got['latency_p99_ms'] = lat[min(len(lat) - 1, int(len(lat) * 0.99))]
        got['latencies_ms'] = lat
    _emit(args, got)
    node.destroy_node()
    rclpy.shutdown()
    return got


def _content(msg) -> bytes:
    """What a subscriber received, field by field (not the CDR bytes: stock's
    ``serialize_message`` leaves its alignment padding uninitialized, so two serializations of
    one message differ there)."""
    data = msg.data
    payload = data.to_bytes() if hasattr(data, 'to_bytes') else bytes(data)
    head = (f'{msg.header.stamp.sec}.{msg.header.stamp.nanosec}|{msg.header.frame_id}|'
            f'{msg.height}|{msg.width}|{msg.encoding}|{msg.is_bigendian}|{msg.step}|')
    return head.encode() + payload


def _emit(args, report: Dict[str, Any]) -> None:
    line = json.dumps(report, sort_keys=True)
    print(line, flush=True)
    if args.report:
        with open(args.report, 'a') as f:
            f.write(line + '\n')


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('role', choices=('pub', 'sub'))
    parser.add_argument('--mode', default='cuda',
                        choices=('cuda', 'stock', 'demo', 'small', 'cpu', 'legacy'))
    parser.add_argument('--topic', default='/cuda/image')
    parser.add_argument('--frames', type=int, default=60)
    parser.add_argument('--rate', type=float, default=30.0)
    parser.add_argument('--width', type=int, default=640)
    parser.add_argument('--height', type=int, default=480)
    parser.add_argument('--depth', type=int, default=10)
    parser.add_argument('--consumer', default='torch', choices=('torch', 'cupy'))
    parser.add_argument('--own-stream', action='store_true')
    parser.add_argument('--slow', type=int, default=0,
                        help='GPU cycles each of 16 chunk writes of a frame waits first')
    parser.add_argument('--hold', type=int, default=0, help='keep the last N frames and '
                        'check them again at the end')
    parser.add_argument('--recheck-after', type=float, default=0.0)
    parser.add_argument('--hash', action='store_true', help='report the SHA-1 of what each frame '
                        'holds, field by field')
    parser.add_argument('--wait-subscribers', type=int, default=1)
    parser.add_argument('--wait-buffer-peers', type=int, default=0)
    parser.add_argument('--wait-timeout', type=float, default=30.0)
    parser.add_argument('--timeout', type=float, default=60.0)
    parser.add_argument('--idle', type=float, default=5.0, help='stop after this many seconds '
                        'without a frame, once one came')
    parser.add_argument('--linger', type=float, default=5.0)
    parser.add_argument('--hang', action='store_true', help='after publishing, wait to be '
                        'killed')
    parser.add_argument('--ready-file')
    parser.add_argument('--report')
    args = parser.parse_args(argv)
    (publish if args.role == 'pub' else subscribe)(args)
    return 0


if __name__ == '__main__':
    sys.exit(main())
