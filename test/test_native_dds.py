"""The native rmw_fastrtps layer (rosidl_buffer_py._native via rosidl_buffer_py._dds).

Real rclpy nodes on real Fast DDS. The second process is test/native_dds_peer.py; every one is
reaped. Each test uses its own rclpy Context so rclpy.shutdown() orders can be exercised
without disturbing other test modules.
"""
import hashlib
import json
import os
import subprocess
import sys
import time
import uuid

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image

from rosidl_buffer_py import _dds

PEER = os.path.join(os.path.dirname(__file__), 'native_dds_peer.py')

pytestmark = pytest.mark.skipif(
    not _dds.is_supported(), reason='the native DDS layer needs rmw_fastrtps_cpp')


@pytest.fixture
def ctx():
    context = Context()
    rclpy.init(context=context)
    yield context
    context.try_shutdown()


def _node(ctx, name):
    return rclpy.create_node(name, context=ctx)


def _wait(predicate, timeout=10.0, step=0.02):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(step)
    return predicate()


def _unique(prefix):
    return f'{prefix}_{uuid.uuid4().hex[:8]}'


def _image(size, seed=0):
    return Image(height=1, width=size, encoding='mono8', step=size,
                 data=bytes((seed + i) % 251 for i in range(size)))


class Peer:
    """native_dds_peer.py in a child process, reaped in close()."""

    def __init__(self, *args):
        self.proc = subprocess.Popen(
            [sys.executable, PEER, *map(str, args)], stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True)

    def expect(self, prefix, timeout=25.0):
        deadline = time.monotonic() + timeout
        import selectors
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        try:
            while time.monotonic() < deadline:
                if not sel.select(timeout=max(0.0, deadline - time.monotonic())):
                    break
                line = self.proc.stdout.readline()
                if not line:
                    break
                if line.startswith(prefix):
                    rest = line[len(prefix):].strip()
                    return json.loads(rest) if rest else {}
        finally:
            sel.close()
        self.close()
        raise AssertionError(f'peer gave no {prefix!r} line; stderr:\n{self.proc.stderr.read()}')

    def close(self):
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=10)
        for f in (self.proc.stdout, self.proc.stderr):
            f.close()


# ---------------------------------------------------------------- GIDs and USER_DATA


def test_gid_matches_graph(ctx):
    node = _node(ctx, 'gid_node')
    topic = '/' + _unique('gid')
    pub = node.create_publisher(Image, topic, 10)
    sub = node.create_subscription(Image, topic, lambda m: None, 10)
    pubs = _wait(lambda: node.get_publishers_info_by_topic(topic))
    subs = _wait(lambda: node.get_subscriptions_info_by_topic(topic))
    assert [bytes(i.endpoint_gid) for i in pubs] == [_dds.endpoint_gid(pub)]
    assert [bytes(i.endpoint_gid) for i in subs] == [_dds.endpoint_gid(sub)]
    # Raw handles and plain pointers work too.
    assert _dds.endpoint_gid(pub.handle) == _dds.endpoint_gid(pub.handle.pointer, 'publisher')
    assert len(_dds.endpoint_gid(sub)) == 16
    node.destroy_node()


def test_user_data_round_trip_and_local_discovery(ctx):
    """Local endpoints DO reach the participant listener (local=True), QoS changes too."""
    node = _node(ctx, 'ud_node')
    assert _dds.install_discovery(node) is True
    assert _dds.install_discovery(node) is False  # once per participant
    woken = []
    gc = node.create_guard_condition(lambda: woken.append(1))
    assert _dds.add_discovery_wakeup(node, gc) is True
    assert _dds.add_discovery_wakeup(node, gc) is False
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)

    topic = _unique('ud')
    pub = node.create_publisher(Image, '/' + topic, 10)
    original = _dds.get_user_data(pub)
    assert original.startswith(b'typehash=RIHS01_') and original.endswith(b';')
    extended = original + b'BUFBE:cpu=;demo=meta;'
    _dds.set_user_data(pub, extended)
    assert _dds.get_user_data(pub) == extended
    gid = _dds.endpoint_gid(pub)

    events = []

    def mine():
        executor.spin_once(timeout_sec=0.05)
        events.extend(e for e in _dds.drain_discovery_events(node) if e.gid == gid)
        return any(e.status == 'changed' and e.user_data == extended for e in events)

    assert _wait(mine), events
    assert woken
    first = events[0]
    assert first.kind == 'writer' and first.local is True
    assert first.topic == 'rt/' + topic and first.type_name == 'sensor_msgs::msg::dds_::Image_'
    known = [e for e in _dds.list_known_endpoints(node) if e.gid == gid]
    assert len(known) == 1 and known[0].user_data == extended and known[0].status == 'known'
    # The rmw graph still has the endpoint, with its type hash.
    info = _wait(lambda: node.get_publishers_info_by_topic('/' + topic))
    assert info[0].topic_type == 'sensor_msgs/msg/Image'

    node.destroy_publisher(pub)
    assert _wait(lambda: mine() or any(e.status == 'removed' for e in events))
    assert not [e for e in _dds.list_known_endpoints(node) if e.gid == gid]
    stats = _dds.discovery_stats(node)
    assert stats['installed'] and stats['wakeups'] == 1 and stats['dropped'] == 0

    assert _dds.remove_discovery_wakeup(gc) is True
    assert _dds.remove_discovery_wakeup(gc) is False
    assert _dds.uninstall_discovery(node) is True
    assert _dds.discovery_stats(node) == {'installed': False}
    executor.shutdown()
    node.destroy_node()


@pytest.mark.parametrize('suffix, hash_survives', [
    # upstream's advertisement: stock Jazzy rmw's key=value parser (alphanumeric keys,
    # non-empty values) rejects it and the remote graph loses the type hash
    (b'BUFBE:cpu=;demo=m42;', False),
    # the same information as one key=value pair that stock rmw parses
    (b'BUFBE=cpu=,demo=m42;', True),
])
def test_user_data_seen_by_other_process(ctx, suffix, hash_survives):
    topic = _unique('remote_ud')
    node = _node(ctx, 'ud_remote')
    pub = node.create_publisher(Image, '/' + topic, 10)
    original = _dds.get_user_data(pub)
    # Set before the peer exists, so its first discovery already carries the new value.
    _dds.set_user_data(pub, original + suffix)
    peer = Peer('watch', 'rt/' + topic, 'demo=m42')
    try:
        result = peer.expect('RESULT ')
        assert peer.proc.wait(timeout=15) == 0
    finally:
        peer.close()
    assert result['gid'] == _dds.endpoint_gid(pub).hex()
    assert result['user_data'] == (original + suffix).decode()
    assert result['known_user_data'] == result['user_data']
    assert result['local'] is False and result['woken'] is True
    assert result['type_name'] == 'sensor_msgs::msg::dds_::Image_'
    # rmw's listener still fed the remote graph: endpoint and type are there ...
    assert result['graph_type'] == 'sensor_msgs/msg/Image'
    # ... and the type hash only when the USER_DATA stays in rmw's key=value syntax.
    typehash = original.decode()[len('typehash='):].rstrip(';')
    assert (result['graph_type_hash'] == typehash) is hash_survives, result['graph_type_hash']
    # The local graph never parses our own USER_DATA.
    local = _wait(lambda: node.get_publishers_info_by_topic('/' + topic))
    assert str(local[0].topic_type_hash) == typehash
    node.destroy_node()


# ---------------------------------------------------------------- channels


def _channel_topic(base):
    return f'rt/{base}/_buf/{uuid.uuid4().hex}_{uuid.uuid4().hex}'


def test_channel_cross_process(ctx):
    base = _unique('chan')
    topic = _channel_topic(base)
    peer = Peer('channel_sub', topic, 3)
    try:
        ready = peer.expect('READY ')
        node = _node(ctx, 'chan_pub')
        pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=10))
        assert pub.topic_name == topic and len(pub.gid) == 16
        assert _wait(lambda: pub.matched_count() >= 1, timeout=15)
        payloads = [serialize_message(_image(n, seed=n)) for n in (16, 1000, 1 << 20)]
        pub.publish(payloads[0])                  # bytes
        pub.publish(bytearray(payloads[1]))       # any buffer
        pub.publish(memoryview(payloads[2]))      # no copy in Python
        result = peer.expect('RESULT ')
        assert peer.proc.wait(timeout=15) == 0
        # Visible in the ROS graph under the full DDS name (rcl rejects the digit tokens of
        # the ROS form, so query it with no_mangle=True).
        pubs = node.get_publishers_info_by_topic(topic, no_mangle=True)
        assert pub.gid in [bytes(i.endpoint_gid) for i in pubs]
        # no_mangle also leaves the type name in its DDS form
        assert pubs[0].topic_type == 'sensor_msgs::msg::dds_::Image_'
        names = dict(node.get_topic_names_and_types())
        assert names['/' + topic[len('rt/'):]] == ['sensor_msgs/msg/Image']
    finally:
        peer.close()
    got = result['received']
    assert [r['sha'] for r in got] == [hashlib.sha256(p).hexdigest() for p in payloads]
    assert {r['gid'] for r in got} == {pub.gid.hex()}
    assert [r['pub_seq'] for r in got] == sorted(r['pub_seq'] for r in got)
    assert got[0]['info_keys'] == sorted([
        'from_intra_process', 'publication_sequence_number', 'received_timestamp',
        'reception_sequence_number', 'source_timestamp'])
    assert ready['gid'] != pub.gid.hex()
    pub.destroy()
    node.destroy_node()


def test_channel_in_process_wakeup_and_subscription_gid(ctx):
    node = _node(ctx, 'chan_local')
    topic = _channel_topic(_unique('chan_local'))
    woken = []
    gc = node.create_guard_condition(lambda: woken.append(1))
    sub = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=5),
                                           guard_condition=gc)
    pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=5))
    assert _wait(lambda: pub.matched_count() == 1 and sub.matched_count() == 1)
    subs = node.get_subscriptions_info_by_topic(topic, no_mangle=True)
    assert [bytes(i.endpoint_gid) for i in subs] == [sub.gid]
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    data = serialize_message(_image(64))
    pub.publish(data)
    assert _wait(lambda: executor.spin_once(timeout_sec=0.05) or woken)
    taken = _wait(sub.take)
    assert taken[0] == data and taken[1] == pub.gid
    assert sub.take() is None
    executor.shutdown()
    sub.destroy()
    pub.destroy()
    node.destroy_node()


# ---------------------------------------------------------------- main-topic take


def test_take_serialized_with_gid_of_plain_publisher(ctx):
    node = _node(ctx, 'take_node')
    topic = '/' + _unique('take')
    pub = node.create_publisher(Image, topic, 10)
    sub = node.create_subscription(Image, topic, lambda m: None, 10, raw=True)
    assert _wait(lambda: pub.get_subscription_count() == 1)
    assert _dds.take_serialized_with_gid(sub) is None
    msg = _image(300, seed=3)
    pub.publish(msg)
    pub.publish(serialize_message(_image(5)))  # pre-serialized, as the wrappers will do
    first = _wait(lambda: _dds.take_serialized_with_gid(sub))
    second = _wait(lambda: _dds.take_serialized_with_gid(sub.handle))  # raw handle works too
    assert first[0] == serialize_message(msg)
    assert second[0] == serialize_message(_image(5))
    assert first[1] == second[1] == _dds.endpoint_gid(pub)
    info = first[2]
    assert info['source_timestamp'] > 0 and info['received_timestamp'] >= info['source_timestamp']
    assert second[2]['publication_sequence_number'] == info['publication_sequence_number'] + 1
    node.destroy_node()


# ---------------------------------------------------------------- lifetimes and errors


def test_node_destroyed_before_channels(ctx):
    node = _node(ctx, 'destroy_order')
    topic = _channel_topic(_unique('order'))
    gc = node.create_guard_condition(lambda: None)
    pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=5))
    sub = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=5),
                                           guard_condition=gc)
    _dds.add_discovery_wakeup(node, gc)
    node.destroy_node()  # deferred by the pins: channels keep working
    assert _wait(lambda: pub.matched_count() == 1)
    pub.publish(serialize_message(_image(8)))
    assert _wait(sub.take)[1] == pub.gid
    assert _dds.remove_discovery_wakeup(gc) is True  # after destroy was requested
    sub.destroy()
    sub.destroy()  # idempotent
    pub.destroy()
    assert not pub.valid and not sub.valid
    with pytest.raises(_dds.DdsError):
        pub.publish(b'\0\1\0\0')
    with pytest.raises(_dds.DdsError):
        sub.take()
    with pytest.raises(Exception):  # the rcl node is gone now
        _dds.install_discovery(node.handle)


def test_shutdown_before_channels(ctx):
    node = _node(ctx, 'shutdown_order')
    topic = _channel_topic(_unique('shutdown'))
    gc = node.create_guard_condition(lambda: None)
    pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=5))
    sub = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=5),
                                           guard_condition=gc)
    _dds.add_discovery_wakeup(node, gc)
    ctx.shutdown()
    sub.destroy()
    pub.destroy()
    _dds.remove_discovery_wakeup(gc)
    node.destroy_node()


def test_guard_condition_destroyed_while_pinned(ctx):
    node = _node(ctx, 'gc_pinned')
    topic = _channel_topic(_unique('gc'))
    gc = node.create_guard_condition(lambda: None)
    sub = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=5),
                                           guard_condition=gc)
    pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=5))
    node.destroy_guard_condition(gc)  # deferred: the subscription still triggers it safely
    assert _wait(lambda: pub.matched_count() == 1)
    for _ in range(3):
        pub.publish(serialize_message(_image(8)))
    assert _wait(sub.take)
    del sub  # dealloc destroys and unpins
    pub.destroy()
    node.destroy_node()


def test_interpreter_exit_without_cleanup():
    peer = Peer('linger')
    try:
        assert peer.expect('RESULT ') == {'ok': True}
        assert peer.proc.wait(timeout=20) == 0, peer.proc.stderr.read()
    finally:
        peer.close()


def test_errors(ctx):
    node = _node(ctx, 'errors')
    pub = node.create_publisher(Image, '/' + _unique('err'), 10)
    with pytest.raises(ValueError, match='kind'):
        _dds.endpoint_gid(pub, 'bogus')
    with pytest.raises(TypeError):
        _dds.endpoint_gid(None, 'publisher')
    with pytest.raises(TypeError, match='cannot tell the kind'):
        _dds.endpoint_gid(object())
    with pytest.raises(TypeError, match='_TYPE_SUPPORT'):
        _dds.ChannelPublisher(node, object(), 'rt/x')
    with pytest.raises(ValueError, match='QoS'):
        _dds.ChannelPublisher(node, _dds.type_support(Image), 'rt/x', reliability=7)
    chan = _dds.create_channel_publisher(node, Image, 'rt/err/_buf/1_2', QoSProfile(depth=1))
    with pytest.raises(ValueError, match='too short'):
        chan.publish(b'')
    chan.destroy()
    node.destroy_publisher(pub)
    with pytest.raises(Exception):  # rclpy refuses to hand out a destroyed handle
        _dds.endpoint_gid(pub)
    node.destroy_node()
