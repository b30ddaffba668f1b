"""The bag format pieces without DDS: definitions, QoS metadata, writer and reader, codec parts."""
import array
import os
import sys
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image, PointCloud2
from std_msgs.msg import String

import rosidl_buffer_py
from rosidl_buffer_py import codec
from rosidl_buffer_py.tools.bag import (
    BagError, BagReader, BagWriter, Topic, qos_from_yaml, qos_to_yaml)
from rosidl_buffer_py.tools.message_definition import (
    DefinitionNotFoundError, full_definition, import_message_type, type_hash, type_name)

SHARE = Path(sys.prefix) / 'share'
RULE = '=' * 80


def _msg(path: str) -> str:
    return (SHARE / path).read_text()


def test_full_definition_is_rosbag2s_text():
    definition = full_definition('sensor_msgs/msg/Image')
    assert definition.encoding == 'ros2msg'
    assert definition.text == (
        _msg('sensor_msgs/msg/Image.msg') + f'\n{RULE}\nMSG: std_msgs/Header\n' +
        _msg('std_msgs/msg/Header.msg') + f'\n{RULE}\nMSG: builtin_interfaces/Time\n' +
        _msg('builtin_interfaces/msg/Time.msg'))
    # dependencies sorted, each once, depth first: PointField before std_msgs/Header
    text = full_definition('sensor_msgs/msg/PointCloud2').text
    assert [line for line in text.splitlines() if line.startswith('MSG: ')] == [
        'MSG: sensor_msgs/PointField', 'MSG: std_msgs/Header', 'MSG: builtin_interfaces/Time']
    assert type_hash('sensor_msgs/msg/Image').startswith('RIHS01_')


def test_definition_errors_name_the_type():
    with pytest.raises(DefinitionNotFoundError, match='no_such_pkg/msg/Nope'):
        full_definition('no_such_pkg/msg/Nope')
    with pytest.raises(ValueError, match='not a message type name'):
        full_definition('Image')
    with pytest.raises(ValueError, match='cannot import'):
        import_message_type('no_such_pkg/msg/Nope')
    assert import_message_type('sensor_msgs/msg/Image') is Image
    assert type_name(PointCloud2) == 'sensor_msgs/msg/PointCloud2'


def test_qos_yaml_is_rosbag2s_and_round_trips():
    profile = QoSProfile(depth=7, reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         deadline=Duration(seconds=1, nanoseconds=5))
    text = qos_to_yaml([profile])
    assert text.startswith('- history: keep_last\n  depth: 7\n  reliability: best_effort\n'
                           '  durability: transient_local\n  deadline:\n    sec: 1\n'
                           '    nsec: 5\n')
    [back] = qos_from_yaml(text)
    assert (back.depth, back.reliability, back.durability, back.deadline) == (
        7, profile.reliability, profile.durability, profile.deadline)
    # metadata before version 9 stored the enums as integers
    [old] = qos_from_yaml('- history: 1\n  depth: 5\n  reliability: 1\n  durability: 2\n')
    assert old.reliability == ReliabilityPolicy.RELIABLE
    assert qos_from_yaml('') == []
    with pytest.raises(ValueError, match='reliability'):
        qos_from_yaml('- reliability: sometimes\n')


def test_encode_parts_and_split_payload():
    from demo_buffer_backend import DemoBuffer
    msg = Image(height=2, width=3, encoding='rgb8', step=9, is_bigendian=1)
    msg.header.frame_id = 'abc'
    msg.data = DemoBuffer.from_cpu(bytes(range(18)))
    parts = codec.encode_parts(msg)
    assert parts.payload.obj is not None and parts.payload.nbytes == 18
    assert b''.join(parts) == bytes(codec.encode(msg)) and parts.nbytes == len(codec.encode(msg))
    decoded, payload = codec.split_payload(bytes(codec.encode(msg)), Image)
    assert bytes(payload) == bytes(range(18)) and len(decoded.data) == 0
    assert decoded.header.frame_id == 'abc' and decoded.is_bigendian == 1
    with pytest.raises(codec.CodecError, match='descriptor'):
        codec.split_payload(codec.encode(msg, descriptor=('demo', b'x')), Image)
    del parts, msg


def test_writer_reader_round_trip_with_splits(tmp_path):
    bag = BagWriter(tmp_path / 'b', max_bag_duration_ns=1000)
    image = Topic('/img', 'sensor_msgs/msg/Image', full_definition('sensor_msgs/msg/Image'),
                  [QoSProfile(depth=3)], 'RIHS01_x')
    bag.add_topic(image)
    text = Topic('/txt', 'std_msgs/msg/String', full_definition('std_msgs/msg/String'))
    bag.add_topic(text)
    with pytest.raises(BagError, match='already'):
        bag.add_topic(text)
    sent = []
    for i in range(6):
        msg = Image(height=1, width=4, encoding='mono8', step=4)
        msg.data = array.array('B', [i] * 4)
        bag.write('/img', 1000 + 600 * i, 900 + 600 * i, codec.encode_parts(msg))
        sent.append(('/img', bytes(codec.encode(msg))))
        raw = serialize_message(String(data=f's{i}'))
        bag.write('/txt', 1001 + 600 * i, 0, [raw])
        sent.append(('/txt', raw))
    bag.close()
    names = sorted(p.name for p in (tmp_path / 'b').iterdir())
    assert names == ['b_0.mcap', 'b_1.mcap', 'b_2.mcap', 'metadata.yaml']
    reader = BagReader(tmp_path / 'b')
    assert reader.message_count == 12 and reader.time_range() == (1000, 4001)
    assert reader.topics['/img']['count'] == 6 and reader.topics['/img']['type_hash'] == 'RIHS01_x'
    assert [(c.topic, m.data) for c, m in reader.messages()] == sent
    assert [m.data for _, m in reader.messages(['/txt'])] == [d for t, d in sent if t == '/txt']
    with open(tmp_path / 'b' / 'b_1.mcap', 'rb') as stream:
        decoded = [m for *_, m in make_reader(stream, decoder_factories=[DecoderFactory()])
                   .iter_decoded_messages(log_time_order=False)]
    assert [list(m.data) for m in decoded if hasattr(m, 'width')] == [[2] * 4, [3] * 4]
    with pytest.raises(BagError, match='already exists'):
        BagWriter(tmp_path / 'b')


def test_reader_errors(tmp_path):
    with pytest.raises(BagError, match='no such file'):
        BagReader(tmp_path / 'missing')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(BagError, match='no .mcap files'):
        BagReader(tmp_path / 'empty')
    (tmp_path / 'text.mcap').write_text('hello')
    with pytest.raises(BagError, match='not an MCAP file'):
        BagReader(tmp_path / 'text.mcap')
    assert rosidl_buffer_py.Buffer  # the package is importable alongside


def test_large_shared_memory_payloads_go_to_the_disk_page_aligned(tmp_path):
    """A page-aligned payload of at least DIRECT_MIN_BYTES is written with O_DIRECT after a
    private padding record; every reader still sees the same message bytes."""
    from demo_buffer_backend import DemoBuffer
    from rosidl_buffer_py.tools.bag import DIRECT_ALIGNMENT, DIRECT_MIN_BYTES, PADDING_OPCODE
    nbytes = DIRECT_MIN_BYTES + 3 * DIRECT_ALIGNMENT + 5  # an unaligned tail too
    bag = BagWriter(tmp_path / 'd')
    bag.add_topic(Topic('/img', 'sensor_msgs/msg/Image', full_definition('sensor_msgs/msg/Image')))
    sent = []
    for i in range(3):
        msg = Image(height=1, width=nbytes, encoding='mono8', step=nbytes)
        msg.header.frame_id = 'x' * i  # a different head length each time
        buffer = DemoBuffer.allocate(nbytes)
        memoryview(buffer)[:] = bytes([i]) * nbytes  # payload starts page-aligned in memory
        msg.data = buffer
        bag.write('/img', 10 + i, 10 + i, codec.encode_parts(msg))
        sent.append(bytes(codec.encode(msg)))
        del msg, buffer
    bag.close()
    path = tmp_path / 'd' / 'd_0.mcap'
    assert [m.data for _, m in BagReader(path).messages()] == sent
    with open(path, 'rb') as stream:
        decoded = [m for *_, m in make_reader(stream, decoder_factories=[DecoderFactory()])
                   .iter_decoded_messages(log_time_order=False)]
    assert [bytes(m.data[:1]) for m in decoded] == [b'\x00', b'\x01', b'\x02']
    content = path.read_bytes()
    direct = os.open(path, os.O_RDONLY | getattr(os, 'O_DIRECT', 0)) if hasattr(os, 'O_DIRECT') \
        else -1
    if direct >= 0:  # the file system supports O_DIRECT: the payloads were padded to pages
        os.close(direct)
        for cdr in sent:
            assert (content.index(cdr) + len(cdr) - nbytes) % DIRECT_ALIGNMENT == 0
        assert content.count(bytes([PADDING_OPCODE])) >= 3


def test_ros_distro_from_rosbag2s_embedded_metadata(tmp_path):
    """rosbag2 writes the distribution inside its ``rosbag2`` metadata record's
    serialized_metadata (no ROS_DISTRO key): buffer_bag_info shows it."""
    from mcap.writer import Writer
    from rosidl_buffer_py.tools.bag_info import format_info, info
    path = tmp_path / 'rosbag2.mcap'
    with open(path, 'wb') as stream:
        writer = Writer(stream)
        writer.start(profile='ros2', library='rosbag2')
        writer.add_metadata('rosbag2', {'serialized_metadata': yaml.safe_dump(
            {'rosbag2_bagfile_information': {'version': 9, 'ros_distro': 'rolling'}})})
        writer.finish()
    facts = info(BagReader(path))
    assert facts['ros_distro'] == 'rolling'
    assert 'ROS Distro:        rolling' in format_info(facts)
