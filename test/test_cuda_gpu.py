"""The cuda backend on a GPU, in real processes over real Fast DDS (launch_free_demos.cuda_peer).

Every test here needs a CUDA device and torch; elsewhere they are reported skipped with the
reason. Frame ``i`` holds ``value(i)`` in every byte; subscribers check every frame.
"""
import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

import cuda_buffer_backend

WHY = cuda_buffer_backend.unavailable_reason()
HAVE_TORCH = importlib.util.find_spec('torch') is not None
pytestmark = [
    pytest.mark.skipif(bool(WHY), reason=f'needs a CUDA GPU: {WHY}'),
    pytest.mark.skipif(not HAVE_TORCH, reason='needs torch (the GPU producer and consumer)'),
]


def _have(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


class Peers:
    """Peer processes of one test, reaped at the end."""

    def __init__(self, tmp_path, topic: str) -> None:
        self.tmp = tmp_path
        self.topic = topic
        self.procs = {}

    def start(self, name: str, role: str, *args: str) -> subprocess.Popen:
        report = self.tmp / f'{name}.jsonl'
        cmd = [sys.executable, '-m', 'launch_free_demos.cuda_peer', role, '--topic', self.topic,
               '--report', str(report), *args]
        if role == 'sub':
            ready = self.tmp / f'{name}.ready'
            cmd += ['--ready-file', str(ready)]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=open(
            self.tmp / f'{name}.err', 'w'))
        self.procs[name] = proc
        if role == 'sub':
            deadline = time.monotonic() + 60
            while not ready.exists() and time.monotonic() < deadline and proc.poll() is None:
                time.sleep(0.05)
        return proc

    def reports(self, name: str):
        path = self.tmp / f'{name}.jsonl'
        return [json.loads(line) for line in path.read_text().splitlines()] \
            if path.exists() else []

    def final(self, name: str, timeout: float = 120.0):
        proc = self.procs[name]
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        reports = self.reports(name)
        assert reports, (f'{name} reported nothing; stderr:\n'
                         + (self.tmp / f'{name}.err').read_text()[-3000:])
        return reports[-1]

    def reap(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.fixture
def peers(tmp_path, request):
    p = Peers(tmp_path, '/gpu/' + re.sub(r'[^A-Za-z0-9_]', '_', request.node.name))
    yield p
    p.reap()


def test_gpu_frames_zero_copy_beside_legacy_and_cpu_subscribers_that_get_identical_bytes(peers):
    frames = ['--frames', '40', '--rate', '20', '--width', '320', '--height', '240']
    peers.start('gpu', 'sub', '--mode', 'cuda', '--hash', *frames)
    peers.start('cpu', 'sub', '--mode', 'cpu', '--hash', *frames)
    peers.start('legacy', 'sub', '--mode', 'legacy', '--hash', *frames)
    peers.start('pub', 'pub', '--mode', 'cuda', '--wait-subscribers', '3',
                '--wait-buffer-peers', '2', *frames)
    gpu, cpu, legacy = (peers.final(n) for n in ('gpu', 'cpu', 'legacy'))
    pub = peers.final('pub')
    assert gpu['frames'] == cpu['frames'] == legacy['frames'] == 40
    assert gpu['failures'] == cpu['failures'] == legacy['failures'] == []
    assert gpu['types'] == {'CudaBuffer': 40}  # every frame zero-copy on the GPU
    assert gpu['pointer_matches'] == 40  # the consumer's tensor is the mapped memory itself
    assert gpu['addresses'] <= pub['stats']['cuda:0']['slots']
    assert cpu['types'] == {'array': 40}
    # the CPU peers got the bytes stock would have sent, as the GPU one would serialize them
    assert cpu['hashes'] == legacy['hashes'] == gpu['hashes']


@pytest.mark.parametrize('consumer', ['torch', 'cupy'])
def test_a_consumer_on_its_own_stream_never_sees_a_half_written_frame(peers, consumer):
    if not _have(consumer):
        pytest.skip(f'{consumer} is not installed')
    frames = ['--frames', '30', '--rate', '30', '--width', '1920', '--height', '1080']
    # each frame is written in 16 chunks, each after a ~1 ms GPU sleep, and published at once:
    # only the stream wait keeps the subscriber from reading it before it is complete
    peers.start('sub', 'sub', '--mode', 'cuda', '--consumer', consumer, '--own-stream',
                '--hold', '4', *frames)
    peers.start('pub', 'pub', '--mode', 'cuda', '--slow', '2000000', '--wait-buffer-peers',
                '1', *frames)
    sub = peers.final('sub')
    assert sub['frames'] == 30 and sub['types'] == {'CudaBuffer': 30}
    assert sub['failures'] == []
    # the 4 frames still held at the end were never overwritten by a reused slot
    assert sub['held'] == 4 and sub['held_failures'] == []


def test_a_steady_cuda_publisher_writes_through_its_lane_and_frames_stay_whole(peers):
    """Once the routes are steady the publisher writes through its lane (the backend's steady
    describer records the slot's event, then describes) and the subscription delivers through
    its steady step (the backend's steady opener): every frame zero-copy, none torn though
    each is written by slow kernels and published at once."""
    frames = ['--frames', '90', '--rate', '30', '--width', '640', '--height', '480']
    peers.start('sub', 'sub', '--mode', 'cuda', '--own-stream', *frames)
    peers.start('pub', 'pub', '--mode', 'cuda', '--slow', '300000', '--wait-buffer-peers',
                '1', *frames)
    sub, pub = peers.final('sub'), peers.final('pub')
    assert sub['frames'] == 90 and sub['types'] == {'CudaBuffer': 90}
    assert sub['failures'] == [] and sub['pointer_matches'] == 90
    assert pub['published_on_lane'] > 0, pub
    assert sub['delivered_steady'] > 0, sub


def test_frames_a_subscriber_holds_stay_valid_after_its_publisher_is_sigkilled(peers):
    frames = ['--frames', '10', '--rate', '20', '--width', '640', '--height', '480']
    sub = peers.start('sub', 'sub', '--mode', 'cuda', '--hold', '5', '--recheck-after', '3',
                      *frames)
    pub = peers.start('pub', 'pub', '--mode', 'cuda', '--wait-buffer-peers', '1', '--hang',
                      *frames)
    deadline = time.monotonic() + 60
    while not any(r.get('phase') == 'holding' for r in peers.reports('sub')) and \
            time.monotonic() < deadline and sub.poll() is None:
        time.sleep(0.05)
    pub.send_signal(signal.SIGKILL)
    pub.wait()
    result = peers.final('sub')
    assert result['frames'] == 10 and result['types'] == {'CudaBuffer': 10}
    assert result['held'] == 5 and result['held_failures'] == []


def test_a_subscriber_sigkilled_while_holding_frames_gives_the_publisher_its_slots_back(
        peers, tmp_path):
    env_frames = ['--width', '640', '--height', '480', '--rate', '20']
    # the holder keeps 3 frames, then is killed; the steady subscriber must keep getting every
    # frame zero-copy from a pool of 6 slots
    os.environ['RBPY_DEMO_MAX_SLOTS'] = '6'
    try:
        holder = peers.start('holder', 'sub', '--mode', 'cuda', '--hold', '3',
                             '--recheck-after', '60', '--frames', '5', *env_frames)
        peers.start('steady', 'sub', '--mode', 'cuda', '--frames', '80', *env_frames)
        peers.start('pub', 'pub', '--mode', 'cuda', '--frames', '80', '--wait-subscribers',
                    '2', '--wait-buffer-peers', '2', *env_frames)
    finally:
        del os.environ['RBPY_DEMO_MAX_SLOTS']
    deadline = time.monotonic() + 60
    while not any(r.get('phase') == 'holding' for r in peers.reports('holder')) and \
            time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    killed_at = time.monotonic()
    steady = peers.final('steady')
    pub = peers.final('pub')
    assert steady['frames'] == 80 and steady['failures'] == []
    # while the holder lived, the steady one may have got some frames as CPU bytes (the pool
    # was short); once it is killed its slots come back: the last half are all zero-copy
    assert all(i < 40 for i in steady['cpu_frames']), (steady['cpu_frames'], killed_at)
    assert pub['stats']['cuda:0']['slots'] <= 6


def test_the_recorder_writes_a_cuda_topics_frames_as_the_bytes_stock_would_serialize(
        peers, tmp_path):
    """buffer_record takes a cuda publisher's frames (a buffer-aware subscription accepting
    every backend: zero-copy on this GPU) and writes each as its legacy CDR, the bytes copied
    from the device: what ``serialize_message`` of the CPU frame gives, padding zeroed."""
    from mcap.reader import make_reader
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image

    from launch_free_demos.cuda_peer import value
    from rosidl_buffer_py import codec
    from rosidl_buffer_py.report import last_report
    count, width, height = 20, 320, 240
    bag = tmp_path / 'bag'
    recorder = subprocess.Popen(
        [sys.executable, '-m', 'rosidl_buffer_py.tools.record', peers.topic, '-o', str(bag),
         '--qos-depth', '100'], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, env=dict(os.environ, PYTHONUNBUFFERED='1'))
    try:
        peers.start('pub', 'pub', '--mode', 'cuda', '--frames', str(count), '--rate', '20',
                    '--width', str(width), '--height', str(height), '--depth', '100',
                    '--wait-buffer-peers', '1', '--linger', '1')
        pub = peers.final('pub')
        time.sleep(1.0)  # the last frames reach the recorder's queue
        recorder.send_signal(signal.SIGINT)
        out, err = recorder.communicate(timeout=60)
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.communicate()
    assert recorder.returncode == 0 and 'Traceback' not in err, err[-3000:]
    topic = last_report(out.splitlines())['topics'][peers.topic]
    assert topic['written'] == count and topic['backends'] == {'cuda': count}, topic
    assert pub['stats']['cuda:0']['slots'] >= 1
    raws = []
    for path in sorted(bag.glob('*.mcap')):
        with open(path, 'rb') as stream:
            raws += [message.data for _, _, message in make_reader(stream).iter_messages()]
    assert len(raws) == count
    for i, raw in enumerate(raws):
        decoded = deserialize_message(raw, Image)
        assert decoded.header.frame_id == str(i)
        expected = Image(height=height, width=width, encoding='rgb8', step=width * 3,
                         header=decoded.header)
        expected.data = bytes([value(i)]) * (width * height * 3)
        assert raw == bytes(codec.encode(expected)), i


def test_allocating_more_than_the_device_has_is_a_clear_memory_error():
    from cuda_buffer_backend import CudaBuffer
    with pytest.raises(MemoryError, match='cuda:0'):
        CudaBuffer.allocate(1 << 50)


def test_from_dlpack_copies_a_torch_tensor_and_torch_reads_it_back():
    import torch

    from cuda_buffer_backend import CudaBuffer
    source = torch.arange(1000, dtype=torch.int32, device='cuda')
    buf = CudaBuffer.from_dlpack(source)
    assert len(buf) == 4000 and buf.__dlpack_device__() == (2, 0)
    back = torch.from_dlpack(buf).view(torch.int32)
    assert torch.equal(back, source)
    assert back.data_ptr() == buf.address
    assert bytes(buf.to_bytes()) == source.cpu().numpy().tobytes()
    with pytest.raises(TypeError, match='GPU memory'):
        import numpy
        numpy.asarray(buf)


def _endpoint(gid: bytes):
    from rosidl_buffer_py import EndpointInfo, EndpointKind
    return EndpointInfo(gid, '/cuda_gpu_test', EndpointKind.SUBSCRIPTION)


def test_renew_waits_for_the_subscribers_reads_then_gives_a_new_frame_in_the_same_memory():
    """A camera that keeps its device buffers: renew() returns once the descriptor was taken and
    the view dropped; the slot keeps its address (a CUDA graph may keep writing there), and the
    old descriptor is refused as stale."""
    import gc

    import torch

    from cuda_buffer_backend import CudaBuffer
    from cuda_buffer_backend.backend import CudaBackend
    be = CudaBackend()
    ep = _endpoint(b'\x22' * 16)  # this process's own endpoint: descriptors and views are real
    assert be.on_discovering_endpoint(ep, [], {'cuda': be.get_backend_metadata(), 'cpu': ''}) \
        == (True, [])
    buf = CudaBuffer.allocate(1 << 16)
    address, generation = buf.address, buf.generation
    torch.from_dlpack(buf).fill_(1)
    first = be.create_descriptor_with_endpoint(buf, ep)
    assert first is not None
    assert not buf.renew(timeout=0.05)  # sent, not taken yet
    got = be.from_descriptor_with_endpoint(first, ep)
    assert not buf.renew(timeout=0.05)  # taken, a view of it held
    assert int(torch.from_dlpack(got)[0]) == 1
    del got
    gc.collect()
    assert buf.renew(timeout=5.0)
    assert (buf.address, buf.generation) == (address, generation + 1)
    with pytest.raises(ValueError, match='stale'):
        be.from_descriptor_with_endpoint(first, ep)
    torch.from_dlpack(buf).fill_(2)  # the new frame, in the same memory
    again = be.from_descriptor_with_endpoint(be.create_descriptor_with_endpoint(buf, ep), ep)
    view = torch.from_dlpack(again)  # the subscriber's mapping of the same device memory
    assert int(view.min()) == int(view.max()) == 2
    assert not again.renew()  # a received buffer is not the subscriber's to renew


def test_an_in_process_cuda_subscription_gets_the_publishers_frames_zero_copy(context):
    """Publisher and subscriptions in one process: the cuda one gets every frame in the
    publisher's pooled device memory (mapped a second time, read-only), a plain rclpy one beside
    it the same bytes."""
    import rclpy
    import torch
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    import rosidl_buffer_py
    from cuda_buffer_backend import CudaBuffer
    from harness.in_process import spin_until
    from rosidl_buffer_py.image import allocate_image_msg

    qos = QoSProfile(depth=30, reliability=ReliabilityPolicy.RELIABLE)
    node = rclpy.create_node('cuda_inproc', context=context)
    gpu, plain = [], []

    def on_gpu(msg):
        view = torch.from_dlpack(msg.data)
        gpu.append((type(msg.data).__name__, view.data_ptr(), int(view.min()), int(view.max())))

    def on_plain(msg):
        plain.append(bytes(msg.data))

    rosidl_buffer_py.create_subscription(node, Image, '/cuda_inproc', on_gpu, qos,
                                         acceptable_buffer_backends='cuda')
    node.create_subscription(Image, '/cuda_inproc', on_plain, qos)
    pub = rosidl_buffer_py.create_publisher(node, Image, '/cuda_inproc', qos)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: any(p['channel_serving'] for p in pub.buffer_peers())
                      and pub.get_subscription_count() == 2)
    for i in range(20):
        msg = allocate_image_msg(24, 32, 'rgb8', backend='cuda')
        torch.from_dlpack(msg.data).fill_(i + 1)
        pub.publish(msg)
        executor.spin_once(timeout_sec=0.01)
    assert spin_until(executor, lambda: len(gpu) >= 20 and len(plain) >= 20), (
        len(gpu), len(plain), pub.statistics())
    assert [g[0] for g in gpu] == ['CudaBuffer'] * 20
    assert [g[2:] for g in gpu] == [(i + 1, i + 1) for i in range(20)]
    # a mapping per pooled slot, not a copy per frame
    assert len({g[1] for g in gpu}) <= pub_slots(), gpu
    assert plain == [bytes([i + 1]) * (24 * 32 * 3) for i in range(20)]
    executor.shutdown()
    node.destroy_node()


def pub_slots() -> int:
    from cuda_buffer_backend import lifecycle
    return lifecycle.get_pool(0).stats()['slots']
