"""A recording cut short (SIGKILL, a full disk) and ``buffer_bag_reindex``, in real processes.

The recorder is SIGKILLed while a camera (demo backend) and a String talker publish: every
message it received more than a flush period before the kill must be on disk, and
``buffer_bag_reindex`` must make the bag readable by mcap, our own tools and (where installed)
rosbags, every message intact and none missing between the first and the last. A recorder
whose disk fills (a tiny tmpfs in a private mount namespace) must leave a readable bag and never
an empty or partial metadata.yaml. Cuts at every offset of a written file are checked in
process: whatever the cut, every complete message is recovered.
"""
import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import pytest
import yaml
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import String

from launch_free_demos.runner import Run
from rosidl_buffer_py.tools.bag import FLUSH_PERIOD_SEC, BagError, BagReader, BagWriter, Topic
from rosidl_buffer_py.tools.message_definition import full_definition
from rosidl_buffer_py.tools.reindex import reindex_bag

#: Publishes std_msgs/String 'N' (N = 0, 1, ...) at 10 Hz until stopped.
TALKER = '''
import sys, time, rclpy
from rclpy.qos import QoSProfile
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node('talker')
publisher = node.create_publisher(String, sys.argv[1], QoSProfile(depth=100))
i = 0
try:
    while True:
        publisher.publish(String(data=str(i)))
        i += 1
        rclpy.spin_once(node, timeout_sec=0.1)
except KeyboardInterrupt:
    pass
'''


def _start(*command: str) -> subprocess.Popen:
    return subprocess.Popen(list(command), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


def _reap(process: subprocess.Popen, timeout: float = 60):
    try:
        out, err = process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    return process.returncode, out, err


def _messages(path: Path):
    """(topic, log time, data) of every message of every file, read back with mcap."""
    found = []
    for file in sorted(path.glob('*.mcap')):
        with open(file, 'rb') as stream:
            found += [(c.topic, m.log_time, m.data)
                      for _, c, m in make_reader(stream).iter_messages(log_time_order=True)]
    return found


def _image_counter(data: bytes) -> int:
    return int.from_bytes(bytes(deserialize_message(data, Image).data[:8]), 'little')


def _assert_contiguous(counters, what: str) -> None:
    assert counters, f'no {what} recorded'
    assert counters == list(range(counters[0], counters[0] + len(counters))), \
        f'{what}: a gap in {counters}'


def _read_with_rosbags(bag: Path) -> Optional[int]:
    """Messages rosbags reads from ``bag``; None when rosbags is not installed (it is not a
    dependency: `pip install rosbags` to check with it too)."""
    if importlib.util.find_spec('rosbags') is None:
        return None
    from rosbags.rosbag2 import Reader
    with Reader(bag) as reader:
        return sum(1 for _ in reader.messages())


def test_sigkilled_recorder_then_reindex(tmp_path):
    bag = tmp_path / 'crash'
    recorder = _start(sys.executable, '-m', 'rosidl_buffer_py.tools.record', '/crash/image',
                      '/crash/text', '-o', str(bag), '--qos-depth', '100')
    talker = _start(sys.executable, '-c', TALKER, '/crash/text')
    try:
        with Run() as run:
            run.start('camera', 'image_publisher', topic='/crash/image', backend='demo',
                      width=64, height=48, rate_hz=20.0, count=0, depth=100, settle_sec=0.0,
                      linger_sec=0.0)
            time.sleep(6.0)
            assert recorder.poll() is None and talker.poll() is None, run.diagnostics()
            killed_at = time.time_ns()
            recorder.send_signal(signal.SIGKILL)
            code, out, err = _reap(recorder)
            run.stop_all()
    finally:
        for process in (recorder, talker):
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
            _reap(process, 10)
    assert code == -signal.SIGKILL
    assert 'recording /crash/image' in out and 'recording /crash/text' in out, out + err
    assert not (bag / 'metadata.yaml').exists()
    with pytest.raises(BagError, match='buffer_bag_reindex'):
        BagReader(bag)

    code, out, err = _reap(_start(sys.executable, '-m', 'rosidl_buffer_py.tools.reindex', str(bag)))
    assert code == 0, err
    assert 'recovered' in out and 'metadata.yaml written' in out, out

    messages = _messages(bag)
    by_topic = {'/crash/image': [], '/crash/text': []}
    for topic, log_time, data in messages:
        by_topic[topic].append((log_time, data))
    images = [_image_counter(data) for _, data in by_topic['/crash/image']]
    texts = [int(deserialize_message(data, String).data) for _, data in by_topic['/crash/text']]
    _assert_contiguous(images, 'camera frames')
    _assert_contiguous(texts, 'talker messages')
    # what arrived more than a flush period (and a scheduling margin) before the kill is there
    margin = int((FLUSH_PERIOD_SEC + 0.6) * 1e9)
    for topic, received in by_topic.items():
        assert max(t for t, _ in received) >= killed_at - margin, \
            f'{topic}: last message {(killed_at - max(t for t, _ in received)) / 1e9:.2f} s ' \
            'before the kill'
    reader = BagReader(bag)
    assert reader.message_count == len(messages)
    metadata = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert metadata['message_count'] == len(messages)
    assert {t['topic_metadata']['name']: t['message_count']
            for t in metadata['topics_with_message_count']} == \
        {topic: len(received) for topic, received in by_topic.items()}
    # a second run changes nothing
    code, out, _ = _reap(_start(sys.executable, '-m', 'rosidl_buffer_py.tools.reindex', str(bag)))
    assert code == 0 and 'complete' in out and 'finished' in out
    assert _messages(bag) == messages
    assert _read_with_rosbags(bag) in (None, len(messages))


def test_every_cut_of_a_file_recovers_every_complete_message(tmp_path):
    """Cut a written file at many offsets (SIGKILL stops a write anywhere): reindexing keeps
    exactly the messages whose chunk, or whose record inside a cut chunk, is complete."""
    source = BagWriter(tmp_path / 'src', chunk_size=4096)
    source.add_topic(Topic('/t', 'std_msgs/msg/String', full_definition('std_msgs/msg/String')))
    source.add_topic(Topic('/i', 'sensor_msgs/msg/Image',
                           full_definition('sensor_msgs/msg/Image')))
    sent = []
    for i in range(60):
        raw = serialize_message(String(data=f'{i}' * 40))
        source.write('/t', 1000 + i, 0, [raw])
        sent.append(raw)
        if i % 10 == 0:  # a chunk of its own (larger than the chunk size)
            raw = serialize_message(Image(height=1, width=5000, step=5000, data=[i] * 5000))
            source.write('/i', 1000 + i, 0, [raw])
            sent.append(raw)
    source.close()
    full = (tmp_path / 'src' / 'src_0.mcap').read_bytes()
    assert len(_messages(tmp_path / 'src')) == len(sent)
    previous = 0
    for cut in list(range(8, len(full) - 200, 211)) + [len(full) - 1]:
        bag = tmp_path / f'cut{cut}'
        bag.mkdir()
        (bag / 'cut_0.mcap').write_bytes(full[:cut])
        repair, = reindex_bag(bag)
        data = [d for _, _, d in _messages(bag)]
        assert repair.messages == len(data) == BagReader(bag).message_count
        assert sorted(data) == sorted(sent[:len(data)]), f'cut at {cut}: not a prefix'
        assert len(data) >= previous, f'cut at {cut}: fewer messages than an earlier cut'
        previous = len(data)
        shutil.rmtree(bag)
    assert previous == len(sent)  # the summary was cut: every message is still there


def _unshare_command():
    """``unshare`` arguments for a private mount namespace, or None with the reason."""
    if shutil.which('unshare') is None:
        return None, 'unshare (util-linux) is not installed'
    command = ['unshare', '-m'] if os.geteuid() == 0 else ['unshare', '-r', '-m']
    probe = subprocess.run(command + ['true'], capture_output=True, text=True)
    if probe.returncode != 0:
        return None, f'{" ".join(command)} is not permitted here: {probe.stderr.strip()}'
    return command, ''


def test_full_disk_leaves_a_readable_bag(tmp_path):
    unshare, reason = _unshare_command()
    if unshare is None:
        pytest.skip(f'needs a private mount namespace for a tiny tmpfs: {reason}')
    disk, out_dir = tmp_path / 'disk', tmp_path / 'copied'
    disk.mkdir()
    # inside the namespace: a 2 MiB tmpfs, the recorder on it, then its bag copied out
    script = ('mount -t tmpfs -o size=2m tmpfs "$1" || exit 97; '
              '"$2" -m rosidl_buffer_py.tools.record /full/image -o "$1/bag" --duration 30; '
              'status=$?; ls -la "$1/bag" >&2; cp -a "$1/bag" "$3"; exit $status')
    recorder = _start(*unshare, 'sh', '-c', script, 'sh', str(disk), sys.executable,
                      str(out_dir))
    try:
        with Run() as run:
            camera = run.start('camera', 'image_publisher', topic='/full/image', backend='demo',
                               width=160, height=120, rate_hz=50.0, count=0, depth=100,
                               wait_for_subscribers=1, settle_sec=0.0, linger_sec=0.0)
            code, out, err = _reap(recorder, 60)
            assert camera.process.poll() is None, run.diagnostics()
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.communicate()
    assert code != 97, f'mounting the tmpfs failed: {err}'
    assert code == 1, f'exit {code}\n{out}\n{err}'
    assert 'No space left on device' in err, err
    assert "| /full/image | sensor_msgs/msg/Image | " in out  # the summary still printed
    metadata = out_dir / 'metadata.yaml'
    assert not metadata.exists() or metadata.stat().st_size > 0
    assert not list(out_dir.glob('.metadata.yaml*')), 'a temporary file was left'
    if not metadata.exists():  # the recorder could not finish: reindexing does
        assert 'buffer_bag_reindex' in err, err
        reindex_bag(out_dir)
    info = yaml.safe_load(metadata.read_text())['rosbag2_bagfile_information']
    messages = _messages(out_dir)
    assert info['message_count'] == len(messages) == BagReader(out_dir).message_count
    assert len(messages) >= 5, f'only {len(messages)} frames on a 2 MiB disk'
    _assert_contiguous([_image_counter(data) for _, _, data in messages], 'camera frames')
