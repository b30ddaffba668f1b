"""buffer_record, buffer_play and buffer_bag_info on a real graph, in real processes.

One recording serves most tests: a demo-backed publisher, a CPU publisher (buffer-aware) and a
legacy plain-rclpy publisher send 20 verifiable frames each (``nodes/frames.py``: counter and
CRC in every frame) while ``buffer_record`` records them with small file splits; a fourth
publisher keeps publishing when the recorder gets SIGINT, so the last file is finished
mid-stream. The bag is read back with ``mcap-ros2-support`` and every message compared with the
frame its publisher sent, then played back into a buffer-aware and a plain subscriber.
"""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image

import rosidl_buffer_py  # noqa: F401  (msg.data = Buffer support, as in the nodes)
from harness import installed
from launch_free_demos.runner import Run
from rosidl_buffer_py import codec
from rosidl_buffer_py.nodes.frames import pattern
from rosidl_buffer_py.report import REPORT_PREFIX, last_report
from rosidl_buffer_py.tools.bag import qos_from_yaml
from rosidl_buffer_py.tools.message_definition import full_definition

WIDTH, HEIGHT, COUNT = 64, 48, 20
FINITE = {'/rec/demo': ('image_publisher', 'demo'), '/rec/cpu': ('image_publisher', 'cpu'),
          '/rec/legacy': ('legacy_image_publisher', 'cpu')}
LIVE = '/rec/live'
MAX_BAG_SIZE = 60 * 1024


def _report(stdout: str) -> dict:
    report = last_report(stdout.splitlines())
    assert report is not None, f'no REPORT line in:\n{stdout[-2000:]}'
    return report


def _start(module: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, '-m', module, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


def _finish(process: subprocess.Popen, timeout: float = 60):
    """Wait for ``process`` (killed on timeout); always reaped."""
    try:
        out, err = process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    return process.returncode, out, err


def _run(module: str, *args: str, timeout: float = 60):
    return _finish(_start(module, *args), timeout)


def _publisher(run: Run, topic: str, executable: str, backend: str, **extra):
    params = dict(topic=topic, width=WIDTH, height=HEIGHT, rate_hz=40.0, count=COUNT,
                  depth=100, wait_for_subscribers=1, wait_timeout_sec=60.0, linger_sec=0.5,
                  settle_sec=0.2)
    if executable == 'image_publisher':
        params.update(backend=backend, wait_for_buffer_peers=1)
    params.update(extra)
    return run.start(topic.rsplit('/', 1)[-1], executable, **params)


@pytest.fixture(scope='module')
def recording(tmp_path_factory):
    """Record the mixed graph; SIGINT the recorder while /rec/live still publishes."""
    bag = tmp_path_factory.mktemp('record') / 'bag'
    recorder = _start('rosidl_buffer_py.tools.record', *FINITE, LIVE, '-o', str(bag),
                      '--max-bag-size', str(MAX_BAG_SIZE), '--qos-depth', '100')
    try:
        with Run() as run:
            for topic, (executable, backend) in FINITE.items():
                _publisher(run, topic, executable, backend)
            live = _publisher(run, LIVE, 'image_publisher', 'demo', count=0, rate_hz=20.0)
            # a plain subscriber that ends after a few live frames: the recorder (the one
            # buffer-aware peer the live publisher waits for) is recording /rec/live by then;
            # under load that process may start after the finite publishers are done
            run.start('live_watch', 'legacy_image_subscriber', topic=LIVE, expected_count=5,
                      timeout_sec=90.0, report_period_sec=0.0, depth=100)
            finite = [topic.rsplit('/', 1)[-1] for topic in FINITE]
            assert run.wait(finite + ['live_watch'], timeout=90), run.diagnostics()
            assert live.process.poll() is None, run.diagnostics()
            recorder.send_signal(signal.SIGINT)  # mid-record: /rec/live is still publishing
            code, out, err = _finish(recorder, timeout=60)
            run.stop_all()
            reports = run.reports()
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.communicate()
    return {'bag': bag, 'code': code, 'out': out, 'err': err, 'reports': reports}


def _files(bag: Path):
    return sorted(bag.glob('*.mcap'), key=lambda p: int(p.stem.rsplit('_', 1)[1]))


def _expected_payload(counter: int) -> bytes:
    data = bytearray(pattern(WIDTH * HEIGHT * 3).tobytes())
    data[:8] = counter.to_bytes(8, 'little')
    return bytes(data)


def test_recorder_summary_and_clean_exit_on_sigint(recording):
    assert recording['code'] == 0, recording['err'][-3000:]
    assert 'Traceback' not in recording['err']
    report = _report(recording['out'])
    assert report['errors'] == []
    topics = report['topics']
    for topic in FINITE:
        assert topics[topic]['written'] == COUNT and topics[topic]['dropped'] == 0, topics
    # the demo frames were written from shared memory; CPU frames were not Buffers
    assert topics['/rec/demo']['zero_copy'] == COUNT
    assert topics['/rec/demo']['backends'] == {'demo': COUNT}
    assert topics['/rec/cpu']['zero_copy'] == 0 == topics['/rec/legacy']['zero_copy']
    assert topics[LIVE]['written'] > 0
    assert '| /rec/demo ' in recording['out']  # the table a user reads


def test_buffer_aware_publishers_never_wrote_the_main_topic_for_the_recorder(recording):
    for label in ('demo', 'cpu'):
        statistics = recording['reports'][label]['statistics']
        assert statistics['sent_on_main_topic'] == 0, statistics
        assert [peer['sent_as_descriptor' if label == 'demo' else 'sent_as_cpu']
                for peer in statistics['peers']] == [COUNT], statistics


def test_every_message_is_the_published_frame_in_order(recording):
    messages = {topic: [] for topic in [*FINITE, LIVE]}
    for path in _files(recording['bag']):
        with open(path, 'rb') as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, message, decoded in reader.iter_decoded_messages(
                    log_time_order=False):
                messages[channel.topic].append((message, decoded))
    for topic in FINITE:
        frames = messages[topic]
        assert len(frames) == COUNT, topic
        for counter, (message, decoded) in enumerate(frames):
            # decoded: by mcap-ros2-support's own decoder, from the schema in the file
            assert decoded.header.frame_id.startswith(f'frame={counter} crc='), topic
            expected = Image(height=HEIGHT, width=WIDTH, encoding='rgb8', step=WIDTH * 3)
            expected.header.frame_id = decoded.header.frame_id
            expected.header.stamp.sec = decoded.header.stamp.sec
            expected.header.stamp.nanosec = decoded.header.stamp.nanosec
            expected.data = _expected_payload(counter)
            raw = message.data
            assert bytes(decoded.data) == _expected_payload(counter), (topic, counter)
            # legacy CDR of the CPU equivalent: serialize_message's bytes, padding zeroed
            assert raw == bytes(codec.encode(expected)), (topic, counter)
            assert deserialize_message(raw, Image) == expected, (topic, counter)
            assert message.publish_time <= message.log_time
    live = [int(d.header.frame_id.split()[0][6:]) for _, d in messages[LIVE]]
    assert live and live == list(range(live[0], live[0] + len(live)))


def test_bag_layout_is_rosbag2s(recording):
    bag = recording['bag']
    files = _files(bag)
    assert [p.name for p in files] == [f'bag_{i}.mcap' for i in range(len(files))]
    assert len(files) > 2  # --max-bag-size split it
    metadata = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert metadata['storage_identifier'] == 'mcap' and metadata['version'] == 9
    assert metadata['relative_file_paths'] == [p.name for p in files]
    counts = {t['topic_metadata']['name']: t['message_count']
              for t in metadata['topics_with_message_count']}
    assert all(counts[topic] == COUNT for topic in FINITE)
    assert metadata['message_count'] == sum(counts.values())
    definition = full_definition('sensor_msgs/msg/Image')
    assert 'MSG: std_msgs/Header\n' in definition.text
    total = 0
    for path in files:  # the last one too: it was finished after SIGINT, mid-stream
        with open(path, 'rb') as stream:
            reader = make_reader(stream)
            header = reader.get_header()
            summary = reader.get_summary()
            assert header.profile == 'ros2'
            assert {s.name: (s.encoding, s.data.decode()) for s in summary.schemas.values()} == {
                'sensor_msgs/msg/Image': (definition.encoding, definition.text)}
            for channel in summary.channels.values():
                assert channel.message_encoding == 'cdr'
                assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
                offered = qos_from_yaml(channel.metadata['offered_qos_profiles'])
                assert offered and all(p.reliability.name == 'RELIABLE' for p in offered)
            assert any(m.name == 'rosbag2' for m in reader.iter_metadata())
            statistics = summary.statistics
            assert statistics.message_count == sum(1 for _ in reader.iter_messages())
            total += statistics.message_count
        assert path.stat().st_size < MAX_BAG_SIZE + 2 * WIDTH * HEIGHT * 3
    assert total == metadata['message_count']


def test_bag_info(recording):
    code, out, err = _run('rosidl_buffer_py.tools.bag_info', str(recording['bag']))
    assert code == 0, err
    assert f'Topic: /rec/demo | Type: sensor_msgs/msg/Image | Count: {COUNT} | ' \
           'Serialization Format: cdr' in out
    assert 'Storage id:        mcap' in out and 'bag_0.mcap' in out
    code, out, err = _run('rosidl_buffer_py.tools.bag_info', str(recording['bag']), '--json')
    facts = json.loads(out)
    assert facts['message_count'] == sum(t['count'] for t in facts['topics'])
    assert facts['size'] == sum(p.stat().st_size for p in _files(recording['bag']))
    assert facts['end_ns'] - facts['start_ns'] == facts['duration_ns'] > 0


def test_play_into_buffer_aware_and_plain_subscribers(recording):
    """The demo topic to a demo-accepting and a plain subscriber; the legacy-recorded topic's
    payloads go into shared memory too (--backend demo is the default)."""
    subscriber = dict(expected_count=COUNT, timeout_sec=60.0, report_period_sec=0.0, depth=100)
    with Run() as run:
        run.start('aware', 'image_subscriber', topic='/rec/demo',
                  acceptable_buffer_backends='demo', expected_backend='demo', **subscriber)
        run.start('plain', 'legacy_image_subscriber', topic='/rec/demo', **subscriber)
        run.start('aware_legacy', 'image_subscriber', topic='/rec/legacy',
                  acceptable_buffer_backends='demo', expected_backend='demo', **subscriber)
        run.start('plain_legacy', 'legacy_image_subscriber', topic='/rec/legacy', **subscriber)
        code, out, err = _run('rosidl_buffer_py.tools.play', str(recording['bag']),
                              '--topics', '/rec/demo', '/rec/legacy', '--rate', '2',
                              '--wait-for-subscribers', '2', '--qos-depth', '100',
                              timeout=90)
        assert code == 0, err[-3000:]
        assert run.wait(timeout=60), run.diagnostics()
        reports = run.reports()
    played = _report(out)['topics']
    assert {key: played['/rec/demo'][key] for key in ('published', 'in_backend',
                                                      'buffer_aware')} == \
        {'published': COUNT, 'in_backend': COUNT, 'buffer_aware': True}
    assert played['/rec/demo']['first_late_ms'] < 15
    for label, backend in (('aware', 'demo'), ('plain', 'cpu'), ('aware_legacy', 'demo'),
                           ('plain_legacy', 'cpu')):
        report = reports[label]
        assert report['distinct'] == COUNT and report['gaps'] == 0, report
        assert report['checksum_failures'] == 0 and report['wrong_backend'] == 0, \
            (label, report, report.get('statistics'))
        assert report['backends'] == {backend: COUNT}, report


def test_bad_inputs_get_one_line_and_status_2(recording, tmp_path):
    truncated = tmp_path / 'truncated.mcap'
    with open(_files(recording['bag'])[0], 'rb') as source:
        truncated.write_bytes(source.read(MAX_BAG_SIZE // 2))
    missing = str(tmp_path / 'missing')
    cases = [
        ('rosidl_buffer_py.tools.bag_info', missing),
        ('rosidl_buffer_py.tools.bag_info', str(truncated)),
        ('rosidl_buffer_py.tools.play', missing),
        ('rosidl_buffer_py.tools.play', str(truncated)),
        ('rosidl_buffer_py.tools.play', str(recording['bag']), '--topics', '/no/such/topic'),
        ('rosidl_buffer_py.tools.record', '-o', str(tmp_path / 'out')),  # no topics, no --all
    ]
    for module, *args in cases:
        code, out, err = _run(module, *args)
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1, (module, args, code, err)
        assert lines[0].startswith(f'buffer_{module.rsplit(".", 1)[1]}: error: '), lines
        assert 'Traceback' not in err and out == ''
    assert not (tmp_path / 'out').exists()


def _guide_block(title: str) -> str:
    """The first bash block of the user guide's section ``title``."""
    guide = (Path(__file__).resolve().parent.parent / 'docs' / 'user-guide.md').read_text()
    section = guide.split(f'\n{title}\n', 1)[1]
    return section.split('```bash\n', 1)[1].split('```', 1)[0]


def test_user_guide_recording_example_runs(tmp_path):
    """The user guide's worked example, verbatim, as one script in an empty directory."""
    block = _guide_block('## Recording and playback')
    # the guide's .venv paths, pointing where the package under test was installed (the
    # ./dev venv, or a colcon install space with the interpreter's bin/)
    venv = tmp_path / '.venv'
    (venv / 'lib').mkdir(parents=True)
    (venv / 'lib' / 'rosidl_buffer_py').symlink_to(installed.executable('buffer_record').parent)
    (venv / 'bin').symlink_to(Path(sys.prefix) / 'bin')
    process = subprocess.Popen(['bash', '-e', '-c', block], cwd=tmp_path, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               start_new_session=True)
    try:
        out, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate()
    assert process.returncode == 0, err[-3000:]
    assert 'Topic: /camera/image | Type: sensor_msgs/msg/Image | Count: 90 |' in out, out
    played = [json.loads(line[len(REPORT_PREFIX):]) for line in out.splitlines()
              if line.startswith(REPORT_PREFIX) and '"player"' in line]
    assert played and played[0]['topics']['/camera/image']['in_backend'] == 90
    assert 'Traceback' not in err


def test_bench_record_prints_its_table(tmp_path):
    code, out, err = _run('launch_free_demos.bench.record', '--seconds', '1', '--width', '64',
                          '--height', '48', '--dd-mib', '8', '--dir', str(tmp_path),
                          timeout=180)
    assert code == 0, err[-3000:]
    assert '| buffer_record (demo backend, zero-copy) | 30 | 30 | 0 ' in out, out
    assert '| stock rclpy raw subscription + mcap Writer | 30 |' in out, out
    assert 'dd to the same file system' in out
    assert list(tmp_path.iterdir()) == []  # the bags were deleted


def _counters(bag: Path, topic: str):
    found = []
    for path in _files(bag):
        with open(path, 'rb') as stream:
            for _, channel, message in make_reader(stream).iter_messages(log_time_order=True):
                if channel.topic == topic:
                    data = deserialize_message(message.data, Image).data
                    found.append(int.from_bytes(bytes(data[:8]), 'little'))
    return found


@pytest.mark.parametrize('backend', ['demo', 'cpu'])
def test_recorder_started_first_misses_nothing_after_its_first_frame(tmp_path, backend):
    """A camera that publishes from its first instant (no wait for subscribers): the recorder,
    already running, subscribes as soon as discovery reports the camera, then every frame up to
    the last is in the bag, none missing in the middle. (Frames published before DDS discovery
    reached the recorder's participant cannot reach a volatile reader: that delay is DDS's, up
    to seconds on a loaded machine; the recorder's own is measured from the discovery event.)"""
    bag = tmp_path / 'first'
    count = 90
    recorder = _start('rosidl_buffer_py.tools.record', '/first/image', '-o', str(bag),
                      '--qos-depth', '30')
    try:
        with Run() as run:
            time.sleep(1.5)  # the recorder is up and watching
            camera = _publisher(run, '/first/image', 'image_publisher', backend, count=count,
                                rate_hz=30.0, wait_for_subscribers=0, wait_for_buffer_peers=0,
                                settle_sec=0.0, linger_sec=2.0, depth=30)
            assert run.wait(timeout=60), run.diagnostics()
            assert camera.report['published'] == count
            recorder.send_signal(signal.SIGINT)
            code, out, err = _finish(recorder, timeout=60)
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.communicate()
    assert code == 0, err[-3000:]
    counters = _counters(bag, '/first/image')
    assert counters and counters[-1] == count - 1, counters
    assert counters == list(range(counters[0], count)), f'a gap: {counters}'
    delay = _report(out)['topics']['/first/image']['subscribe_delay_ms']
    assert delay is not None and delay < 250, f'subscribed {delay} ms after discovery'
