"""GPU frames between two processes: the cuda backend against the paths a Python node has today.

For each size (4K and 1080p rgb8 at ``--rate`` Hz), a publisher process fills each frame on the
GPU and a subscriber process checks it on the GPU (one reduction, read back), publish -> frame
usable on the subscriber's GPU:

- ``(a) stock``: device-to-host copy, stock rclpy, host-to-device copy;
- ``(b) demo``: device-to-host copy into the demo backend's shared memory, host-to-device copy;
- ``(c) raw IPC floor``: no middleware: four VMM slots handed over once as file descriptors, an
  interprocess event recorded per frame, the slot number sent over a Unix socket (measured here,
  in the same run);
- ``cuda``: this package's cuda backend, zero-copy;
- ``(d) small``, once, not per size: a 1 KiB mono8 message from a stock rclpy publisher to a
  stock rclpy subscription, filled and checked on the host: what any message costs in ROS itself,
  for reading the gap between the cuda backend and the floor.

Prints a markdown table (p50 / p99 latency, CPU per frame of each process) and the targets:
4K p50 at most 1.5 ms and at most 1.5x the floor, at least 40x faster than (a). Needs a CUDA GPU
and torch. ``./dev bench cuda``. A benchmark: it prints, it asserts nothing.
"""
import argparse
import json
import os
import resource
import socket
import subprocess
import sys
import tempfile
import time
from typing import Dict, List

SIZES = [('3840x2160 rgb8', 3840, 2160), ('1920x1080 rgb8', 1920, 1080)]
TRANSPORTS = [('(a) stock: D2H + stock rclpy + H2D', 'stock'),
              ('(b) demo backend + H2D', 'demo'),
              ('(c) raw CUDA IPC floor', 'floor'),
              ('cuda backend, zero-copy', 'cuda')]
SMALL = ('1 KiB mono8 (32x32), CPU', '(d) stock rclpy, a 1 KiB message', 'small', 32, 32)


def _peer(role: str, mode: str, width: int, height: int, frames: int, rate: float,
          topic: str, report: str, extra: List[str]) -> subprocess.Popen:
    cmd = [sys.executable, '-m', 'launch_free_demos.cuda_peer', role, '--mode', mode,
           '--width', str(width), '--height', str(height), '--frames', str(frames),
           '--rate', str(rate), '--topic', topic, '--report', report, *extra]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL)


def run_ros(mode: str, width: int, height: int, frames: int, rate: float) -> Dict:
    with tempfile.TemporaryDirectory() as tmp:
        sub_report, pub_report = os.path.join(tmp, 'sub'), os.path.join(tmp, 'pub')
        ready = os.path.join(tmp, 'ready')
        sub = _peer('sub', mode, width, height, frames, rate, '/bench/gpu', sub_report,
                    ['--ready-file', ready, '--timeout', str(frames / rate + 60)])
        deadline = time.monotonic() + 60
        while not os.path.exists(ready) and time.monotonic() < deadline:
            time.sleep(0.05)
        pub = _peer('pub', mode, width, height, frames, rate, '/bench/gpu', pub_report,
                    ['--wait-buffer-peers', '1' if mode in ('cuda', 'demo') else '0'])
        try:
            sub.wait(timeout=frames / rate + 120)
        finally:
            for p in (pub, sub):
                if p.poll() is None:
                    p.wait(timeout=30) if p is pub else p.kill()
        reports = [json.loads(line) for path in (sub_report, pub_report)
                   if os.path.exists(path) for line in open(path)]
    sub_r = next((r for r in reports if r['role'] == 'sub'), None)
    pub_r = next((r for r in reports if r['role'] == 'pub'), None)
    if sub_r is None or pub_r is None:
        raise RuntimeError(f'{mode} {width}x{height}: no report ({reports})')
    return {'p50': sub_r.get('latency_p50_ms'), 'p99': sub_r.get('latency_p99_ms'),
            'pub_cpu': pub_r['cpu_ms_per_frame'], 'sub_cpu': sub_r.get('cpu_ms_per_frame'),
            'frames': sub_r['frames'], 'failures': len(sub_r['failures']),
            'types': sub_r['types'], 'on_lane': pub_r.get('published_on_lane'),
            'delivered_steady': sub_r.get('delivered_steady')}


class _SlotView:
    """The first ``nbytes`` of a slot's device memory, for torch's ``from_dlpack``."""

    def __init__(self, slot, nbytes: int) -> None:
        self.slot = slot
        self.nbytes = nbytes

    def __dlpack__(self, stream=None, **_):
        from rosidl_buffer_py._native import dlpack_capsule
        return dlpack_capsule(self.slot.data.address, self.nbytes, 2, self.slot.device, self)

    def __dlpack_device__(self):
        return (2, self.slot.device)


# --- the raw IPC floor ---------------------------------------------------------------------------

SLOTS = 4


def run_floor(width: int, height: int, frames: int, rate: float) -> Dict:
    """Producer here, consumer in a child process: the least any IPC of GPU frames costs."""
    import torch

    from cuda_buffer_backend import driver as cuda
    from cuda_buffer_backend.memory import DeviceSegment

    nbytes = width * height * 3
    drv = cuda.load()
    uuid = drv.uuid(0)
    with drv.on(0):
        granularity = drv.granularity(0)
    capacity = -(-nbytes // granularity) * granularity
    slots = [DeviceSegment(capacity, 0, uuid, granularity) for _ in range(SLOTS)]
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    child = subprocess.Popen([sys.executable, '-m', 'launch_free_demos.bench.cuda',
                              '--floor-consumer', str(theirs.fileno()), str(capacity),
                              str(nbytes), str(frames)], pass_fds=[theirs.fileno()])
    theirs.close()
    for slot in slots:
        fds = slot.reader_fds()
        socket.send_fds(ours, [b'slot'], fds)
        for fd in fds:
            os.close(fd)
    ours.recv(16)  # the consumer mapped them

    tensors = [torch.from_dlpack(_SlotView(s, nbytes)) for s in slots]
    stream = torch.cuda.Stream()
    cpu0 = _cpu()
    period = 1.0 / rate
    next_at = time.monotonic()
    for i in range(frames):
        next_at += period
        k = i % SLOTS
        if i >= SLOTS:
            ours.recv(16)  # the consumer is done with slot k's previous frame
        t0 = time.time_ns()
        with torch.cuda.stream(stream):
            tensors[k].fill_(i % 251 + 1)
        slot = slots[k]
        slot.record(stream.cuda_stream)
        ours.send(f'{k} {i} {t0}'.encode())
        time.sleep(max(0.0, next_at - time.monotonic()))
    pub_cpu = 1000 * (_cpu() - cpu0) / frames
    for _ in range(min(SLOTS, frames)):
        ours.recv(16)  # the consumer's last acknowledgements
    report = json.loads(ours.recv(1 << 20).decode())
    child.wait(timeout=30)
    for slot in slots:
        slot.close()
    report['pub_cpu'] = pub_cpu
    return report


def floor_consumer(fd: int, capacity: int, nbytes: int, frames: int) -> None:
    import torch

    from cuda_buffer_backend import driver as cuda
    from cuda_buffer_backend.memory import DeviceReceived

    sock = socket.socket(fileno=fd)
    drv = cuda.load()
    devices = {drv.uuid(d): d for d in range(drv.device_count())}
    with drv.on(0):
        granularity = drv.granularity(0)
    slots = []
    for _ in range(SLOTS):
        _, fds, _, _ = socket.recv_fds(sock, 16, 2)
        slots.append(DeviceReceived(fds, capacity, devices, granularity))

    tensors = [torch.from_dlpack(_SlotView(s, nbytes)) for s in slots]
    stream = torch.cuda.Stream()
    with torch.cuda.stream(stream):  # the check's kernels ready, as the ROS subscribers' are
        torch.aminmax(torch.ones(16, dtype=torch.uint8, device='cuda'))
    stream.synchronize()
    sock.send(b'ready')
    latencies, failures = [], 0
    cpu0 = _cpu()
    for _ in range(frames):
        k, i, t0 = (int(x) for x in sock.recv(64).split())
        with drv.on(0):
            drv.stream_wait(stream.cuda_stream, slots[k].data.event)
        with torch.cuda.stream(stream):
            lo, hi = torch.aminmax(tensors[k])
            ok = (int(lo), int(hi)) == (i % 251 + 1,) * 2
        latencies.append((time.time_ns() - t0) / 1e6)
        failures += not ok
        sock.send(b'done')
    sub_cpu = 1000 * (_cpu() - cpu0) / frames
    latencies.sort()
    sock.send(json.dumps({'p50': latencies[len(latencies) // 2],
                          'p99': latencies[min(len(latencies) - 1, int(len(latencies) * .99))],
                          'sub_cpu': sub_cpu, 'frames': frames, 'failures': failures,
                          'types': {'raw': frames}}).encode())
    for slot in slots:
        slot.close()


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=90)
    parser.add_argument('--rate', type=float, default=30.0)
    parser.add_argument('--sizes', default='4k,1080p', help='comma-separated: 4k, 1080p')
    parser.add_argument('--paths', default='stock,demo,floor,cuda,small',
                        help='comma-separated: stock, demo, floor, cuda, small')
    parser.add_argument('--json', help='also write the results here')
    parser.add_argument('--floor-consumer', nargs=4, type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.floor_consumer:
        floor_consumer(*args.floor_consumer)
        return 0
    from cuda_buffer_backend import unavailable_reason
    why = unavailable_reason()
    if why:
        print(f'bench cuda: needs a CUDA GPU: {why}', file=sys.stderr)
        return 2
    wanted = {'4k': '3840x2160 rgb8', '1080p': '1920x1080 rgb8'}
    sizes = [s for s in SIZES if s[0] in {wanted[w] for w in args.sizes.split(',')}]
    results: Dict[str, Dict[str, Dict]] = {}
    for label, width, height in sizes:
        for name, mode in TRANSPORTS:
            if mode not in args.paths.split(','):
                continue
            frames = args.frames if mode != 'stock' else min(args.frames, 45)
            try:
                r = (run_floor(width, height, frames, args.rate) if mode == 'floor'
                     else run_ros(mode, width, height, frames, args.rate))
            except Exception as exc:  # a failed transport is reported, the others still run
                r = {'error': f'{type(exc).__name__}: {exc}'}
            results.setdefault(label, {})[name] = r
            print(f'{label} {name}: {json.dumps(r)}', file=sys.stderr, flush=True)
    if 'small' in args.paths.split(','):
        label, name, mode, width, height = SMALL
        try:
            r = run_ros(mode, width, height, args.frames, args.rate)
        except Exception as exc:
            r = {'error': f'{type(exc).__name__}: {exc}'}
        results[label] = {name: r}
        print(f'{label} {name}: {json.dumps(r)}', file=sys.stderr, flush=True)
    print(table(results))
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(results, f, indent=1)
    return 0


def _fmt(x) -> str:
    return '-' if x is None else f'{x:.2f}'


def table(results: Dict[str, Dict[str, Dict]]) -> str:
    lines = ['| size | path | p50 ms | p99 ms | pub CPU ms/frame | sub CPU ms/frame | frames '
             '(failures) |', '|---|---|---|---|---|---|---|']
    verdicts = []
    for label, rows in results.items():
        for name, r in rows.items():
            if 'error' in r:
                lines.append(f'| {label} | {name} | error: {r["error"]} | | | | |')
                continue
            lines.append(f'| {label} | {name} | {_fmt(r["p50"])} | {_fmt(r["p99"])} | '
                         f'{_fmt(r["pub_cpu"])} | {_fmt(r["sub_cpu"])} | {r["frames"]} '
                         f'({r["failures"]}) |')
        ours = rows.get('cuda backend, zero-copy', {})
        floor = rows.get('(c) raw CUDA IPC floor', {})
        stock = rows.get('(a) stock: D2H + stock rclpy + H2D', {})
        if ours.get('p50') and floor.get('p50'):
            faster = (f', {stock["p50"] / ours["p50"]:.0f}x faster than (a)'
                      if stock.get('p50') else '')
            verdicts.append(
                f'{label}: cuda p50 {ours["p50"]:.2f} ms = {ours["p50"] / floor["p50"]:.2f}x the '
                f'floor (+{ours["p50"] - floor["p50"]:.2f} ms){faster}')
    small = results.get(SMALL[0], {}).get(SMALL[1], {})
    if verdicts and small.get('p50'):
        verdicts.append(f'a 1 KiB stock rclpy message: p50 {small["p50"]:.2f} ms')
    if verdicts:
        lines += ['', 'Targets (4K): p50 <= 1.5 ms, <= 1.5x the floor, >= 40x faster than (a).']
        lines += verdicts
    return '\n'.join(lines)


if __name__ == '__main__':
    sys.exit(main())
