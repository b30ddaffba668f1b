"""Recording benchmark: buffer_record against a stock rclpy recorder, and the disk against dd.

One run, three phases on the same file system (``--dir``, default the system temp directory):

1. ``buffer_record`` records a demo-backed ``image_publisher`` (3840x2160 rgb8 at 30 Hz for
   20 s, frames filled in place in shared memory: ``fill allocate``);
2. a stock recorder records the same publisher: a plain rclpy ``raw=True`` subscription
   writing each serialized message with the mcap library's ``Writer.add_message`` into the same
   MCAP layout (unchunked, ``ros2`` profile, same schema and channel metadata);
3. ``dd`` writes as many bytes as phase 1 did through the page cache, then ``--dd-mib`` (2 GiB)
   with ``conv=fdatasync`` (what the disk sustains) and with ``oflag=direct bs=24M`` (how
   ``buffer_record`` writes large shared-memory frames: O_DIRECT, see
   :mod:`rosidl_buffer_py.tools.bag`).

Per recorder: frames published and written, frames lost, the recorder's CPU time per written
frame (its process CPU clock from the moment it is subscribed to the moment it is stopped),
its write throughput, and the publisher's CPU per frame. A second table times one 4K frame
through the writers in this process (chunked ``add_message``, unchunked ``add_message``,
``BagWriter.write`` of the codec's parts). Bags are deleted after each phase.

Run: ``./dev bench record [--seconds 20] [--rate 30] [--width 3840 --height 2160] [--dir D]``.
"""
import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional

from launch_free_demos.bench.measured import (
    StealMeter, claim_domain_id, cpu_clock_of, cpu_seconds)
from launch_free_demos.runner import Run, remove_fastdds_leftovers
from rosidl_buffer_py.report import last_report, print_report
from rosidl_buffer_py.tools.bag import BagError, BagReader

TOPIC = '/bench/record'


def _report(lines: List[str]) -> dict:
    return last_report(lines) or {}


# --- the stock recorder (a plain rclpy node) -----------------------------------------------------

def stock_recorder(topic: str, directory: str) -> int:
    """Record ``topic`` as a stock rclpy node would: raw subscription, mcap Writer."""
    import rclpy
    from mcap.writer import CompressionType, Writer
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Image

    from rosidl_buffer_py.tools.bag import SERIALIZATION_FORMAT, Topic
    from rosidl_buffer_py.tools.message_definition import full_definition

    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('stock_recorder')
    Path(directory).mkdir(parents=True)
    stream = open(Path(directory) / f'{Path(directory).name}_0.mcap', 'wb')
    writer = Writer(stream, compression=CompressionType.NONE, use_chunking=False)
    writer.start(profile='ros2', library='stock rclpy recorder')
    definition = full_definition('sensor_msgs/msg/Image')
    schema = writer.register_schema('sensor_msgs/msg/Image', definition.encoding,
                                    definition.text.encode())
    offered = [info.qos_profile for info in node.get_publishers_info_by_topic(topic)]
    channel = writer.register_channel(topic, SERIALIZATION_FORMAT, schema, Topic(
        topic, 'sensor_msgs/msg/Image', definition, offered).channel_metadata())
    counts = {'written': 0, 'bytes': 0}

    def on_message(data: bytes, info) -> None:
        writer.add_message(channel, time.time_ns(), data, info['source_timestamp'])
        counts['written'] += 1
        counts['bytes'] += len(data)

    node.create_subscription(Image, topic, on_message,
                             QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
                             raw=True)
    print(f'stock_recorder: recording {topic}', flush=True)
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.1)
    writer.finish()
    stream.close()
    print_report(counts)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


# --- phases --------------------------------------------------------------------------------------

class Recorder:
    """A recorder process: started, waited for until subscribed, CPU sampled, stopped."""

    def __init__(self, command: List[str]) -> None:
        self.process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            start_new_session=True, env=dict(os.environ, PYTHONUNBUFFERED='1'))
        self.clock = cpu_clock_of(self.process.pid)
        self.lines: List[str] = []
        self.subscribed = threading.Event()
        self.pump = threading.Thread(target=self._pump, daemon=True)
        self.pump.start()

    def _pump(self) -> None:
        for line in self.process.stdout:
            self.lines.append(line.rstrip('\n'))
            if ': recording ' in line:
                self.subscribed.set()

    def wait_subscribed(self, timeout: float = 90.0) -> None:
        """Until it says it subscribed (the publisher exists: the topic is there)."""
        if not self.subscribed.wait(timeout):
            raise RuntimeError(f'the recorder did not subscribe within {timeout} s: '
                               f'{self.lines[-5:]}')

    def cpu(self) -> float:
        return cpu_seconds(self.process.pid, self.clock) or 0.0

    def stop(self) -> dict:
        self.process.send_signal(signal.SIGINT)
        try:
            self.process.wait(timeout=300)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.pump.join(10)
        err = self.process.stderr.read()
        if self.process.returncode:
            print(f'recorder exited {self.process.returncode}: {err[-2000:]}', file=sys.stderr)
        return _report(self.lines)


def _publisher_params(args, buffer_peers: int) -> dict:
    return dict(topic=TOPIC, backend='demo', fill='allocate', width=args.width,
                height=args.height, rate_hz=float(args.rate),
                count=int(args.seconds * args.rate), wait_for_subscribers=1,
                wait_for_buffer_peers=buffer_peers, wait_timeout_sec=60.0, linger_sec=1.0,
                settle_sec=0.5, depth=10)


def _bytes_on_disk(directory: Path) -> int:
    return sum(p.stat().st_size for p in directory.glob('*.mcap')) if directory.exists() else 0


def run_phase(name: str, command: List[str], bag: Path, args, buffer_peers: int) -> dict:
    """The publisher first (it waits for the recorder), then the recorder; the recorder's CPU
    is counted from its subscription (at least the publisher's settle time before the first
    frame) to its stop."""
    with Run() as run:
        publisher = run.start('camera', 'image_publisher', **_publisher_params(args, buffer_peers))
        pub_clock = cpu_clock_of(publisher.process.pid)
        recorder = Recorder(command)
        try:
            recorder.wait_subscribed()
            steal = StealMeter()
            cpu_start = recorder.cpu()
            pub_cpu_start = cpu_seconds(publisher.process.pid, pub_clock) or 0.0
            started = time.monotonic()
            pub_cpu = pub_cpu_start
            while publisher.process.poll() is None:
                pub_cpu = cpu_seconds(publisher.process.pid, pub_clock) or pub_cpu
                if time.monotonic() - started > args.seconds * 3 + 120:
                    break
                time.sleep(0.05)
            elapsed = time.monotonic() - started
            cpu = recorder.cpu() - cpu_start
            report = recorder.stop()
        finally:
            if recorder.process.poll() is None:
                recorder.process.kill()
                recorder.process.wait()
        run.stop_all()
        published = (publisher.report or {}).get('published', 0)
        if not published:
            print(run.diagnostics(), file=sys.stderr)
    written = report.get('written') if 'written' in report else \
        sum(t['written'] for t in report.get('topics', {}).values())
    dropped = sum(t.get('dropped', 0) for t in report.get('topics', {}).values())
    try:
        first, last = BagReader(bag).time_range()
    except BagError as exc:
        print(f'{name}: {exc}', file=sys.stderr)
        first = last = 0
    return {'name': name, 'published': published, 'written': written or 0,
            'dropped_in_recorder': dropped, 'recorder_cpu_s': cpu, 'seconds': elapsed,
            'bytes': _bytes_on_disk(bag), 'log_span_s': (last - first) / 1e9,
            'publisher_cpu_s': pub_cpu - pub_cpu_start, 'steal': steal.fraction()}


def dd(directory: Path, nbytes: int, flag: str = '', block_mib: int = 1) -> Optional[float]:
    """dd's own throughput figure in MB/s (10^6 bytes, as dd prints it)."""
    target = directory / 'dd.bin'
    count = max(1, nbytes // (block_mib * 1024 * 1024))
    command = ['dd', 'if=/dev/zero', f'of={target}', f'bs={block_mib}M', f'count={count}']
    if flag:
        command.append(flag)
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=900)
    finally:
        target.unlink(missing_ok=True)
        os.sync()
    match = re.search(r'copied, ([\d.]+) s', result.stderr)
    return count * block_mib * 1024 * 1024 / float(match.group(1)) / 1e6 if match else None


def writer_costs(directory: Path, width: int, height: int, frames: int = 10) -> Dict[str, float]:
    """CPU ms per frame of one 4K frame through each writer, in this process."""
    from mcap.writer import CompressionType, Writer
    from sensor_msgs.msg import Image

    import rosidl_buffer_py  # noqa: F401
    from demo_buffer_backend import DemoBuffer
    from rosidl_buffer_py import codec
    from rosidl_buffer_py.tools.bag import BagWriter, Topic
    from rosidl_buffer_py.tools.message_definition import full_definition

    msg = Image(height=height, width=width, encoding='rgb8', step=width * 3)
    msg.data = DemoBuffer.allocate(width * height * 3)
    data = bytes(codec.encode(msg))
    results = {}
    for label, chunking in (('mcap Writer.add_message, chunked (library default)', True),
                            ('mcap Writer.add_message, unchunked', False)):
        path = directory / 'writer.mcap'
        with open(path, 'wb') as stream:
            writer = Writer(stream, compression=CompressionType.NONE, use_chunking=chunking)
            writer.start()
            channel = writer.register_channel('/x', 'cdr', 0)
            begin = time.process_time()
            for i in range(frames):
                writer.add_message(channel, i, data, i)
            writer.finish()
            results[label] = (time.process_time() - begin) / frames * 1e3
        path.unlink()
        os.sync()
    definition = full_definition('sensor_msgs/msg/Image')
    bag = BagWriter(directory / 'writer_bag')
    bag.add_topic(Topic('/x', 'sensor_msgs/msg/Image', definition))
    begin = time.process_time()
    for i in range(frames):
        bag.write('/x', i, i, codec.encode_parts(msg))
    bag.close()
    results['buffer_record: encode_parts, then O_DIRECT (or writev) from shared memory'] = \
        (time.process_time() - begin) / frames * 1e3
    shutil.rmtree(directory / 'writer_bag')
    os.sync()
    return results


def _ms(seconds: float, frames: int) -> str:
    return f'{seconds / frames * 1e3:.2f}' if frames else '—'


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--rate', type=float, default=30.0)
    parser.add_argument('--width', type=int, default=3840)
    parser.add_argument('--height', type=int, default=2160)
    parser.add_argument('--dir', default=tempfile.gettempdir(),
                        help='file system to record to (bags are deleted afterwards)')
    parser.add_argument('--dd-mib', type=int, default=2048,
                        help='MiB that dd writes with conv=fdatasync (default 2048)')
    parser.add_argument('--stock-recorder', nargs=2, metavar=('TOPIC', 'DIR'),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.stock_recorder:
        return stock_recorder(*args.stock_recorder)
    claim_domain_id()
    began = time.time()
    work = Path(tempfile.mkdtemp(prefix='bench_record_', dir=args.dir))
    frame_mb = args.width * args.height * 3 / 1e6
    print(f'recording {args.width}x{args.height} rgb8 ({frame_mb:.1f} MB) at {args.rate:g} Hz '
          f'for {args.seconds:g} s into {work} (ROS_DOMAIN_ID {os.environ["ROS_DOMAIN_ID"]}, '
          f'load {os.getloadavg()[0]:.2f})', flush=True)
    rows = []
    try:
        ours = work / 'buffer_record'
        rows.append(run_phase('buffer_record (demo backend, zero-copy)',
                              [sys.executable, '-m', 'rosidl_buffer_py.tools.record', TOPIC,
                               '-o', str(ours)], ours, args, buffer_peers=1))
        print(f'  {rows[-1]}', flush=True)
        shutil.rmtree(ours, ignore_errors=True)
        os.sync()
        stock = work / 'stock'
        rows.append(run_phase('stock rclpy raw subscription + mcap Writer',
                              [sys.executable, '-m', 'launch_free_demos.bench.record',
                               '--stock-recorder', TOPIC, str(stock)], stock, args,
                              buffer_peers=0))
        print(f'  {rows[-1]}', flush=True)
        shutil.rmtree(stock, ignore_errors=True)
        os.sync()
        dd_buffered = dd(work, rows[0]['bytes'])
        dd_synced = dd(work, args.dd_mib * 1024 ** 2, 'conv=fdatasync')
        dd_direct = dd(work, args.dd_mib * 1024 ** 2, 'oflag=direct', block_mib=24)
        costs = writer_costs(work, args.width, args.height)
    finally:
        shutil.rmtree(work, ignore_errors=True)
        remove_fastdds_leftovers(began, int(os.environ['ROS_DOMAIN_ID']))

    print()
    print('| recorder | frames published | frames written | frames lost | recorder CPU per '
          'frame, ms | recorder CPU, % of a core | write MB/s (first to last message) | '
          'publisher CPU per frame, ms | CPU steal |')
    print('|---|---|---|---|---|---|---|---|---|')
    for row in rows:
        lost = row['published'] - row['written']
        steal = '—' if row['steal'] is None else f'{100 * row["steal"]:.0f} %'
        print(f'| {row["name"]} | {row["published"]} | {row["written"]} | {lost} '
              f'({row["dropped_in_recorder"]} dropped in the recorder\'s queue) | '
              f'{_ms(row["recorder_cpu_s"], row["written"])} | '
              f'{100 * row["recorder_cpu_s"] / row["seconds"]:.0f} % | '
              f'{row["bytes"] / max(row["log_span_s"], 1e-9) / 1e6:.0f} | '
              f'{_ms(row["publisher_cpu_s"], row["published"])} | {steal} |')
    ours, stock = rows
    if ours['written'] and stock['written']:
        ratio = (ours['recorder_cpu_s'] / ours['written']) / \
            (stock['recorder_cpu_s'] / stock['written'])
        print(f'\nbuffer_record CPU per frame = {100 * ratio:.1f} % of the stock recorder\'s')
    print(f'dd to the same file system: {dd_buffered or 0:.0f} MB/s through the page cache '
          f'({rows[0]["bytes"] / 1e9:.1f} GB, as the recorders write), {dd_synced or 0:.0f} '
          f'MB/s with conv=fdatasync ({args.dd_mib} MiB: what the disk sustains), '
          f'{dd_direct or 0:.0f} MB/s with oflag=direct bs=24M (as buffer_record writes frames)')
    print(f'needed for {args.rate:g} Hz: {frame_mb * args.rate:.0f} MB/s')
    print('\n| writer, one frame in this process | CPU ms per frame |\n|---|---|')
    for label, ms in costs.items():
        print(f'| {label} | {ms:.2f} |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
