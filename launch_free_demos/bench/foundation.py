"""Benchmark of the foundation pieces: wire codec and demo shared-memory backend.

Prints a markdown table of median (and p90) times next to one memcpy of the same bytes, the
physical reference, and the minor page faults of 100 whole publish/take cycles in the demo
backend (from_cpu, describe, take, nothing kept: 0 once the pool is warm). Run with
``./dev bench foundation`` (or ``python -m launch_free_demos.bench.foundation``).
A benchmark, not a test: it asserts nothing about time.
"""
import argparse
import resource
import time
from typing import Callable, Dict, List

import numpy

from rosidl_buffer_py import EndpointInfo, EndpointKind, codec
from rosidl_buffer_py.image import allocate_image_msg, from_output_msg
from sensor_msgs.msg import Image

from demo_buffer_backend import DemoBackend, DemoBuffer
from launch_free_demos.bench.stats import QUANTILES, percentiles

PAYLOADS = [  # (label, height, width, encoding)
    ('1 KiB', 1, 1024, 'mono8'),
    ('1 MiB', 1024, 1024, 'mono8'),
    ('1920x1080 rgb8', 1080, 1920, 'rgb8'),
    ('3840x2160 rgb8', 2160, 3840, 'rgb8'),
]


def measure(func: Callable[[], object], repeat: int) -> List[float]:
    """Run ``func`` ``repeat`` times after a warm-up; return the times in milliseconds."""
    func()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        times.append((time.perf_counter() - start) * 1e3)
    return times


def summarize(times: List[float]) -> str:
    quantiles = percentiles(times, QUANTILES[:2])
    return f"{quantiles['p50']:.3f} / {quantiles['p90']:.3f}"


def peer(kind: EndpointKind) -> EndpointInfo:
    return EndpointInfo(gid=bytes(range(16)), topic_name='/bench', endpoint_kind=kind,
                        node_name='bench')


def bench_payload(label: str, height: int, width: int, encoding: str,
                  repeat: int) -> Dict[str, str]:
    msg = allocate_image_msg(height, width, encoding)
    from_output_msg(msg)[...] = numpy.random.default_rng(0).integers(
        0, 255, size=from_output_msg(msg).shape, dtype=numpy.uint8)
    nbytes = len(msg.data)
    source = numpy.frombuffer(msg.data, dtype=numpy.uint8)
    target = numpy.empty_like(source)
    wire = codec.encode(msg)

    backend = DemoBackend()
    subscriber = peer(EndpointKind.SUBSCRIPTION)
    publisher = peer(EndpointKind.PUBLISHER)
    backend.on_discovering_endpoint(subscriber, [], {'cpu': '',
                                                     'demo': backend.get_backend_metadata()})
    demo = DemoBuffer.from_cpu(source)
    descriptor = backend.create_descriptor_with_endpoint(demo, subscriber)

    def allocate_and_fill():
        buf = DemoBuffer.allocate(nbytes)
        numpy.asarray(buf)[...] = source  # the producer writing its frame in place
        return buf

    def from_descriptor():
        return backend.from_descriptor_with_endpoint(descriptor, publisher)

    def cycle():  # one frame published and taken, nothing kept
        backend.from_descriptor_with_endpoint(backend.create_descriptor_with_endpoint(
            DemoBuffer.from_cpu(source), subscriber), publisher)

    row = {
        'payload': label,
        'bytes': f'{nbytes:,}',
        'memcpy': summarize(measure(lambda: numpy.copyto(target, source), repeat)),
        'codec encode (cpu)': summarize(measure(lambda: codec.encode(msg), repeat)),
        'codec decode (cpu)': summarize(measure(lambda: codec.decode(wire, Image), repeat)),
        'demo from_cpu': summarize(measure(lambda: DemoBuffer.from_cpu(source), repeat)),
        'demo allocate': summarize(measure(lambda: DemoBuffer.allocate(nbytes), repeat)),
        'demo allocate+fill': summarize(measure(allocate_and_fill, repeat)),
        'demo create_descriptor': summarize(measure(
            lambda: backend.create_descriptor_with_endpoint(demo, subscriber), repeat)),
        'demo from_descriptor': summarize(measure(from_descriptor, repeat)),
        'demo page faults / 100 cycles': str(page_faults(cycle, 100)),
    }
    return row


def page_faults(func: Callable[[], object], count: int) -> int:
    """Minor page faults of ``count`` calls of ``func`` after a warm-up."""
    func()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(count):
        func()
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeat', type=int, default=30, help='timed runs per cell')
    args = parser.parse_args(argv)
    rows = [bench_payload(*payload, repeat=args.repeat) for payload in PAYLOADS]
    columns = list(rows[0])
    print(f'Times in ms, median / p90 of {args.repeat} runs (one process, this machine).\n')
    print('| ' + ' | '.join(columns) + ' |')
    print('|' + '|'.join('---' for _ in columns) + '|')
    for row in rows:
        print('| ' + ' | '.join(row[c] for c in columns) + ' |')


if __name__ == '__main__':
    main()
