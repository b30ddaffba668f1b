"""Quick timings of the demo backend (not collected by pytest): medians, steady state (warm pool).

    python test/demo_backend_bench.py [--repeat N]

For each size: one memcpy of the bytes (numpy.copyto into a preallocated array) as the yardstick,
DemoBuffer.from_cpu, allocate alone, allocate + fill (a copy of the source into the slot),
create_descriptor_with_endpoint and from_descriptor_with_endpoint (this process's own subscriber
mapping: the same syscalls as another process), plus the minor page faults of 100 whole
publish/take cycles after warm-up.
"""
import argparse
import gc
import resource
import statistics
import time

import numpy

from rosidl_buffer_py import EndpointInfo, EndpointKind

import demo_buffer_backend
from demo_buffer_backend import DemoBackend, DemoBuffer

SIZES = [('1 KiB', 1024), ('1 MiB', 1 << 20), ('1920x1080x3', 1920 * 1080 * 3),
         ('3840x2160x3', 3840 * 2160 * 3)]


def median_us(func, repeat):
    samples = []
    for _ in range(repeat):
        t0 = time.perf_counter_ns()
        func()
        samples.append(time.perf_counter_ns() - t0)
    return statistics.median(samples) / 1000.0


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument('--repeat', type=int, default=0, help='samples per timing')
    args = parser.parse_args()
    backend = DemoBackend()
    ep = EndpointInfo(b'\x42' * 16, '/bench', EndpointKind.SUBSCRIPTION)
    backend.on_discovering_endpoint(ep, [], {'demo': backend.get_backend_metadata()})
    gc.disable()
    rows = []
    for label, n in SIZES:
        repeat = args.repeat or (2000 if n < 65536 else 100 if n < (8 << 20) else 40)
        src = numpy.random.default_rng(0).integers(0, 256, n, dtype=numpy.uint8)
        dst = numpy.empty_like(src)
        dst[:] = src  # fault in

        def memcpy():
            numpy.copyto(dst, src)

        def from_cpu():
            DemoBuffer.from_cpu(src)

        def allocate():
            DemoBuffer.allocate(n)

        def allocate_fill():
            numpy.copyto(numpy.asarray(DemoBuffer.allocate(n)), src)

        buf = DemoBuffer.from_cpu(src)

        def create_descriptor():
            backend.create_descriptor_with_endpoint(buf, ep)

        desc = backend.create_descriptor_with_endpoint(buf, ep)

        def from_descriptor():
            backend.from_descriptor_with_endpoint(desc, ep)

        for f in (memcpy, from_cpu, allocate_fill):  # warm-up: the pool has its slots
            f()
            f()
        row = [label]
        for f in (memcpy, from_cpu, allocate, allocate_fill, create_descriptor, from_descriptor):
            row.append(median_us(f, repeat))

        def frame():  # a whole publish/take cycle, nothing kept
            backend.from_descriptor_with_endpoint(
                backend.create_descriptor_with_endpoint(DemoBuffer.from_cpu(src), ep), ep)
        frame()
        faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(100):
            frame()
        row.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0)
        del buf
        rows.append(row)
    header = ['size', 'memcpy', 'from_cpu', 'allocate', 'alloc+fill', 'create_desc',
              'from_desc', 'faults/100']
    print('median microseconds per call')
    print(''.join(f'{h:>13}' for h in header))
    for row in rows:
        print(f'{row[0]:>13}' + ''.join(f'{v:13.1f}' for v in row[1:-1]) + f'{row[-1]:13d}')
    print('faults/100: minor page faults of 100 whole from_cpu/describe/take cycles')
    print('stats:', {k: v for k, v in demo_buffer_backend.stats().items()
                     if k in ('slots', 'bytes', 'segments_created', 'fallbacks',
                              'descriptors_created', 'taken')})


if __name__ == '__main__':
    main()
