"""The native rmw_fastrtps layer (rosidl_buffer_py._native via rosidl_buffer_py._dds).

Real rclpy nodes on real Fast DDS. The second process is test/harness/native_dds_peer.py; every
one is reaped. Each test uses its own rclpy Context so rclpy.shutdown() orders can be exercised
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
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image

from harness.in_process import spin_until
from harness.native_dds_peer import RACED
from rosidl_buffer_py import _dds, _native, codec

PEER = os.path.join(os.path.dirname(__file__), 'harness', 'native_dds_peer.py')

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
            [sys.executable, PEER, *map(str, args)], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def send(self, line):
        self.proc.stdin.write(line + '\n')
        self.proc.stdin.flush()

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
        for f in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            try:
                f.close()
            except OSError:  # stdin of a killed peer: broken pipe on flush
                pass


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


def test_the_discovery_epoch_moves_with_each_callback_before_the_matched_count_is_read(ctx):
    """A publisher trusts its route signature while the epoch stands still: every way a
    matched count changes (a local reader created, then destroyed) moves it first."""
    epoch = _dds.discovery_epoch()
    assert epoch.readonly and epoch.format == 'Q' and len(epoch) == 1
    node = _node(ctx, 'epoch_node')
    _native.install_discovery(node)
    topic = '/' + _unique('epoch')
    pub = node.create_publisher(Image, topic, 10)
    assert _wait(lambda: epoch[0] > 0)
    before = epoch[0]
    sub = node.create_subscription(Image, topic, lambda msg: None, 10)
    assert _wait(lambda: pub.get_subscription_count() == 1)
    assert epoch[0] > before  # the reader's callback came before its match was seen
    before = epoch[0]
    node.destroy_subscription(sub)
    assert _wait(lambda: pub.get_subscription_count() == 0)
    assert epoch[0] > before
    node.destroy_node()


def test_user_data_round_trip_and_local_discovery(ctx):
    """Local endpoints DO reach the participant listener (local=True), QoS changes too."""
    node = _node(ctx, 'ud_node')
    assert _native.install_discovery(node) is True
    assert _native.install_discovery(node) is False  # once per participant
    woken = []
    gc = node.create_guard_condition(lambda: woken.append(1))
    assert _native.add_discovery_wakeup(node, gc) is True
    assert _native.add_discovery_wakeup(node, gc) is False
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
    stats = _native.discovery_stats(node)
    assert stats['installed'] and stats['wakeups'] == 1 and stats['dropped'] == 0

    assert _native.remove_discovery_wakeup(gc) is True
    assert _native.remove_discovery_wakeup(gc) is False
    assert _native.uninstall_discovery(node) is True
    assert _native.discovery_stats(node) == {'installed': False}
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
    for _attempt in range(3):
        peer = Peer('watch', 'rt/' + topic, 'demo=m42')
        try:
            result = peer.expect('RESULT ')
            rc = peer.proc.wait(timeout=15)
        finally:
            peer.close()
        if rc != RACED:  # discovery beat the peer's tap: another peer, another try
            break
    assert rc == 0, result
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


def _observer(name):
    """A node of its own Context (its own participant) with the discovery tap installed."""
    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node(name, context=context)
    _native.install_discovery(node)
    return context, node


def _events_of(observer, gid, events, settle):
    """Collect the observer's events of ``gid`` until one arrived and ``settle`` s passed."""
    deadline = None
    while deadline is None or time.monotonic() < deadline:
        events.extend(e for e in _dds.drain_discovery_events(observer) if e.gid == gid)
        if deadline is None and events:
            deadline = time.monotonic() + settle
        time.sleep(0.02)
    return events


def test_hold_enabling_creates_endpoints_disabled_until_let_go(ctx):
    """Held, what rmw creates stays disabled (no match, no announcement) while its USER_DATA
    is set; let go, it is enabled, and the first discovery carries that USER_DATA, with no
    'changed' after it."""
    observer_ctx, observer = _observer('hold_observer')
    try:
        node = _node(ctx, 'hold_node')
        topic = '/' + _unique('hold')
        sub = node.create_subscription(Image, topic, lambda msg: None, 10)
        with _dds.created_disabled(node, 'publisher'):
            pub = node.create_publisher(Image, topic, 10)
            extended = _dds.get_user_data(pub) + b'\0BUFBE:cpu=;'
            _dds.set_user_data(pub, extended)
            time.sleep(0.5)
            assert pub.get_subscription_count() == 0  # disabled: not even the local reader
            gid = _dds.endpoint_gid(pub)
            assert not [e for e in _dds.drain_discovery_events(observer) if e.gid == gid]
        assert _wait(lambda: pub.get_subscription_count() == 1)
        events = _events_of(observer, gid, [], settle=1.0)
        assert [(e.status, e.user_data) for e in events] == [('discovered', extended)], events
        with pytest.raises(ValueError, match="'publisher' or 'subscription'"):
            _native.hold_enabling(node, 'writer', True)
        node.destroy_subscription(sub)
        node.destroy_node()
    finally:
        observer.destroy_node()
        observer_ctx.try_shutdown()


@pytest.mark.parametrize('kind', ['publisher', 'subscription'])
def test_a_buffer_aware_endpoint_is_first_announced_with_its_advertisement(ctx, kind):
    """What another participant first discovers of a buffer-aware endpoint is its
    advertisement, and no USER_DATA change follows (a change right after creation held new
    peers' matches, test/harness/first_frame.py)."""
    import rosidl_buffer_py
    observer_ctx, observer = _observer('advert_observer')
    try:
        node = _node(ctx, 'advert_node')
        topic = '/' + _unique('advert')
        if kind == 'publisher':
            endpoint = rosidl_buffer_py.create_publisher(node, Image, topic, 10)
        else:
            endpoint = rosidl_buffer_py.create_subscription(
                node, Image, topic, lambda msg: None, 10, acceptable_buffer_backends='demo')
        user_data = _dds.get_user_data(endpoint)
        assert b'\0BUFBE:cpu=' in user_data
        events = _events_of(observer, _dds.endpoint_gid(endpoint), [], settle=1.0)
        assert [(e.status, e.user_data) for e in events] == [('discovered', user_data)], events
        node.destroy_node()
    finally:
        observer.destroy_node()
        observer_ctx.try_shutdown()


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


def test_channel_subscription_listens_on_udp_unless_asked_not_to(ctx, monkeypatch):
    """Channel readers stay off the participant's shared-memory segment (README, "Channel
    transport"); rmw's default DataReaderQos is given back after each creation (the second
    one, made without the override, listens where the participant does)."""
    node = _node(ctx, 'chan_udp')
    topic = _channel_topic(_unique('chan_udp'))
    sub = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=5))
    assert sub.on_udp
    monkeypatch.setenv('ROSIDL_BUFFER_PY_CHANNEL_TRANSPORT', 'participant')
    other = _dds.create_channel_subscription(node, Image, _channel_topic(_unique('chan_shm')),
                                             QoSProfile(depth=5))
    assert not other.on_udp
    pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=5))
    assert _wait(lambda: pub.matched_count() == 1 and sub.matched_count() == 1)
    data = serialize_message(_image(64))
    pub.publish(data)
    taken = _wait(sub.take)
    assert taken[0] == data and taken[1] == pub.gid
    for entity in (sub, other, pub):
        entity.destroy()
    node.destroy_node()


def test_channel_pending_counts_announced_samples_until_taken(ctx):
    """``pending`` is what lets the subscription stop after a take without an empty take: it
    never under-counts the announced samples still in the reader."""
    node = _node(ctx, 'chan_pending')
    topic = _channel_topic(_unique('chan_pending'))
    gc = node.create_guard_condition(lambda: None)
    sub = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=5),
                                           guard_condition=gc)
    unguarded = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=5))
    pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=5))
    assert _wait(lambda: pub.matched_count() == 2)
    assert sub.pending == 0 and unguarded.pending == 1  # 1: unknown, take to find out
    data = serialize_message(_image(64))
    for _ in range(3):
        pub.publish(data)
    assert _wait(lambda: sub.pending == 3)
    assert sub.take() is not None and sub.pending == 2
    assert sub.take() is not None and sub.take() is not None and sub.pending == 0
    assert sub.take() is None and sub.pending == 0
    pub.publish(data)
    assert _wait(lambda: sub.pending == 1)
    assert sub.take() is not None and sub.pending == 0
    for channel in (sub, unguarded, pub):
        channel.destroy()
    node.destroy_node()


# ---------------------------------------------------------------- main-topic take


def test_take_serialized_with_gid_of_plain_publisher(ctx):
    node = _node(ctx, 'take_node')
    topic = '/' + _unique('take')
    pub = node.create_publisher(Image, topic, 10)
    sub = node.create_subscription(Image, topic, lambda m: None, 10, raw=True)
    assert _wait(lambda: pub.get_subscription_count() == 1)
    assert _native.take_serialized_with_gid(sub) is None
    msg = _image(300, seed=3)
    pub.publish(msg)
    pub.publish(serialize_message(_image(5)))  # pre-serialized, as the wrappers will do
    first = _wait(lambda: _native.take_serialized_with_gid(sub))
    second = _wait(lambda: _native.take_serialized_with_gid(sub.handle))  # raw handle works too
    assert first[0] == serialize_message(msg)
    assert second[0] == serialize_message(_image(5))
    assert first[1] == second[1] == _dds.endpoint_gid(pub)
    info = first[2]
    assert info['source_timestamp'] > 0 and info['received_timestamp'] >= info['source_timestamp']
    assert second[2]['publication_sequence_number'] == info['publication_sequence_number'] + 1
    node.destroy_node()


# ---------------------------------------------------------------- explicit source timestamps

#: ns since the epoch: odd nanoseconds, 0, and the last second Fast DDS's Time_t can carry
STAMPS = [1_000_000_000_123_456_789, 1_700_000_000_000_000_001, 999_999_999, 0,
          (2**31 - 1) * 10**9 - 1]


def _near_now(ns, slack=60 * 10**9):
    return abs(ns - time.time_ns()) < slack


def _padded(data):
    """What a take in another process sees: Fast DDS pads the DATA submessage to a multiple of
    4 bytes and the reader cannot tell the padding from the payload (rmw's own publish paths do
    the same; deserialize_message ignores it). Takes in the same process get the exact bytes."""
    return data + b'\0' * (-len(data) % 4)


def test_publish_serialized_source_timestamp(ctx):
    """rclpy's own take in another process and take_serialized_with_gid here see the stamp."""
    topic = '/' + _unique('stamp')
    # serialized lengths 49..52 (three need padding) and one of 1 MiB + 48
    payloads = [serialize_message(_image(n + 1, seed=n)) for n in range(len(STAMPS) - 1)]
    payloads.append(serialize_message(_image(1 << 20, seed=9)))
    peer = Peer('raw_take', topic, len(STAMPS) + 1)
    try:
        peer.expect('READY ')
        node = _node(ctx, 'stamp_pub')
        pub = node.create_publisher(Image, topic, 10)
        local = node.create_subscription(Image, topic, lambda m: None, 10, raw=True)
        assert _wait(lambda: pub.get_subscription_count() == 2, timeout=15)
        for i, (data, stamp) in enumerate(zip(payloads, STAMPS)):
            buf = (data, bytearray(data), memoryview(data))[i % 3]  # any buffer, no copy
            _native.publish_serialized(pub, buf, stamp)
        pub.publish(_image(7))  # rmw's own path still stamps "now"
        result = peer.expect('RESULT ')
        assert peer.proc.wait(timeout=15) == 0
    finally:
        peer.close()
    got = result['received']
    assert len(got) == len(STAMPS) + 1, result
    assert [bytes.fromhex(r['hex']) for r in got[:-2]] == [_padded(p) for p in payloads[:-1]]
    assert got[-2]['sha'] == hashlib.sha256(payloads[-1]).hexdigest()
    assert [r['source_timestamp'] for r in got[:-1]] == STAMPS
    assert _near_now(got[-1]['source_timestamp'])
    assert all(_near_now(r['received_timestamp']) for r in got)
    gid = _dds.endpoint_gid(pub)
    for data, stamp in zip(payloads, STAMPS):
        taken = _wait(lambda: _native.take_serialized_with_gid(local))
        assert taken[0] == data and taken[1] == gid
        assert taken[2]['source_timestamp'] == stamp
        assert _near_now(taken[2]['received_timestamp'])
    assert _near_now(_wait(lambda: _native.take_serialized_with_gid(local))[2]['source_timestamp'])
    node.destroy_node()


def test_publish_serialized_errors(ctx):
    node = _node(ctx, 'stamp_errors')
    topic = '/' + _unique('stamp_err')
    pub = node.create_publisher(Image, topic, 10)
    sub = node.create_subscription(Image, topic, lambda m: None, 10)
    data = serialize_message(_image(4))
    for bad in (-1, (2**31 - 1) * 10**9, 2**64):
        with pytest.raises(ValueError, match='source_timestamp'):
            _native.publish_serialized(pub, data, bad)
    for bad in (None, 1.5, True):
        with pytest.raises(TypeError, match='source_timestamp'):
            _native.publish_serialized(pub, data, bad)
    with pytest.raises(ValueError, match='too short'):
        _native.publish_serialized(pub, b'\0\1', 1)
    with pytest.raises(TypeError, match='Publisher'):
        _native.publish_serialized(sub, data, 1)
    with pytest.raises(TypeError, match='Publisher'):
        _native.matched_subscription_gids(sub)
    with pytest.raises(TypeError, match='Subscription'):
        _native.set_new_message_wakeup(pub, node.create_guard_condition(lambda: None))
    with pytest.raises(TypeError, match='GuardCondition'):
        _native.set_new_message_wakeup(sub, pub)
    chan = _dds.create_channel_publisher(node, Image, 'rt/err/_buf/3_4', QoSProfile(depth=1))
    with pytest.raises(ValueError, match='source_timestamp'):
        chan.publish(data, source_timestamp=-5)
    chan.publish(data, None)  # None: rmw's path
    chan.destroy()
    with pytest.raises(_dds.DdsError):
        chan.publish(data, source_timestamp=5)
    with pytest.raises(_dds.DdsError):
        chan.matched_gids()
    node.destroy_publisher(pub)
    with pytest.raises(Exception):  # rclpy refuses to hand out a destroyed handle
        _native.publish_serialized(pub, data, 1)
    node.destroy_node()


def test_channel_publish_source_timestamp(ctx):
    topic = _channel_topic(_unique('chan_stamp'))
    stamps = [1_234_567_890_987_654_321, 5, None]
    # multiples of 4 bytes: no transport padding (see _padded)
    payloads = [serialize_message(_image(16 << n, seed=n)) for n in range(len(stamps))]
    assert all(len(p) % 4 == 0 for p in payloads)
    peer = Peer('channel_sub', topic, len(stamps))
    try:
        ready = peer.expect('READY ')
        node = _node(ctx, 'chan_stamp')
        pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=10))
        local = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=10))
        assert _wait(lambda: pub.matched_count() == 2, timeout=15)
        assert set(pub.matched_gids()) == {bytes.fromhex(ready['gid']), local.gid}
        for data, stamp in zip(payloads, stamps):
            if stamp is None:
                pub.publish(memoryview(data))
            else:
                pub.publish(memoryview(data), source_timestamp=stamp)
        result = peer.expect('RESULT ')
        assert peer.proc.wait(timeout=15) == 0
    finally:
        peer.close()
    got = result['received']
    assert [r['sha'] for r in got] == [hashlib.sha256(p).hexdigest() for p in payloads]
    assert [r['source_timestamp'] for r in got[:2]] == stamps[:2]
    assert _near_now(got[2]['source_timestamp'])
    assert {r['gid'] for r in got} == {pub.gid.hex()}
    for data, stamp in zip(payloads, stamps):
        taken = _wait(local.take)
        assert taken[0] == data and taken[1] == pub.gid
        assert taken[2]['source_timestamp'] == stamp if stamp is not None else _near_now(
            taken[2]['source_timestamp'])
    # the peer's reader is gone once it exited cleanly
    assert _wait(lambda: pub.matched_gids() == [local.gid])
    local.destroy()
    pub.destroy()
    node.destroy_node()


# ---------------------------------------------------------------- messages converted in C


@pytest.mark.parametrize('by_program', [False, True], ids=['c_struct', 'slot_program'])
def test_write_message_and_take_message(ctx, by_program):
    """One conversion (the C struct rmw serializes, or the CDR written from the slots by the
    type's slot program), written to a channel and an rclpy publisher; taken back as
    messages."""
    program = codec.program_of(Image) if by_program else None
    topic = '/' + _unique('wmsg')
    chan_topic = _channel_topic(_unique('wmsg'))
    messages = [_image(300, seed=1), _image(7, seed=2), _image(1 << 20, seed=3)]
    messages[1].header.frame_id = 'camera'
    peer = Peer('raw_take', topic, len(messages))
    try:
        peer.expect('READY ')
        node = _node(ctx, 'wmsg')
        main = node.create_publisher(Image, topic, 10)
        local = node.create_subscription(Image, topic, lambda m: None, 10)
        chan = _dds.create_channel_publisher(node, Image, chan_topic, QoSProfile(depth=10))
        chan_sub = _dds.create_channel_subscription(node, Image, chan_topic, QoSProfile(depth=10))
        assert _wait(lambda: main.get_subscription_count() == 2 and chan.matched_count() == 1,
                     timeout=15)
        for msg, stamp in zip(messages, STAMPS):
            _native.write_message(msg, stamp, [chan, main], program)
        result = peer.expect('RESULT ')
        assert peer.proc.wait(timeout=15) == 0
    finally:
        peer.close()
    # rclpy's own take in another process: the stamps, and the same messages
    got = result['received']
    assert [r['source_timestamp'] for r in got] == STAMPS[:len(messages)]
    assert [deserialize_message(bytes.fromhex(r['hex']), Image) for r in got[:2]] == \
        messages[:2]
    if by_program:  # canonical bytes: serialize_message's, with zero padding
        assert [bytes.fromhex(r['hex']) for r in got[:2]] == \
            [_padded(bytes(codec.encode(m))) for m in messages[:2]]
    for msg, stamp in zip(messages, STAMPS):
        taken = _wait(lambda: chan_sub.take_message(Image))
        assert type(taken[0]) is Image and taken[0] == msg
        assert taken[1] == chan.gid and taken[2]['source_timestamp'] == stamp
        taken = _wait(lambda: _native.take_message_with_gid(local, Image))
        assert type(taken[0]) is Image and taken[0] == msg
        assert taken[1] == _dds.endpoint_gid(main) and taken[2]['source_timestamp'] == stamp
    assert chan_sub.take_message(Image) is None
    assert _native.take_message_with_gid(local, Image) is None
    node.destroy_node()


def test_take_message_hands_back_what_does_not_deserialize(ctx):
    """Descriptor payloads, truncated CDR and other encapsulations come back as the bytes."""
    from rosidl_buffer_py import codec
    node = _node(ctx, 'take_bytes')
    topic = '/' + _unique('take_bytes')
    chan_topic = _channel_topic(_unique('take_bytes'))
    pub = node.create_publisher(Image, topic, 10)
    sub = node.create_subscription(Image, topic, lambda m: None, 10)
    chan = _dds.create_channel_publisher(node, Image, chan_topic, QoSProfile(depth=10))
    chan_sub = _dds.create_channel_subscription(node, Image, chan_topic, QoSProfile(depth=10))
    assert _wait(lambda: pub.get_subscription_count() == 1 and chan.matched_count() == 1)
    good = serialize_message(_image(12, seed=4))
    samples = [bytes(codec.encode(_image(12), ('demo', b'descriptor'))), good[:30],
               b'\x00\x07' + good[2:], good]
    for data in samples:
        pub.publish(data)
        chan.publish(data, source_timestamp=1)
    for take in (lambda: _native.take_message_with_gid(sub, Image),
                 lambda: chan_sub.take_message(Image)):
        results = [_wait(take)[0] for _ in samples]
        assert results[:3] == samples[:3]
        assert results[3] == _image(12, seed=4)
    # max_size: longer samples come back as bytes, shorter ones as messages
    pub.publish(good)
    chan.publish(good, source_timestamp=2)
    for take in (lambda size: _native.take_message_with_gid(sub, Image, size),
                 lambda size: chan_sub.take_message(Image, max_size=size)):
        assert _wait(lambda: take(len(good) - 1))[0] == good
    pub.publish(good)
    chan.publish(good, source_timestamp=3)
    for take in (lambda: _native.take_message_with_gid(sub, Image, len(good)),
                 lambda: chan_sub.take_message(Image, len(good))):
        assert _wait(take)[0] == _image(12, seed=4)
    node.destroy_node()


def test_write_message_errors(ctx):
    from std_msgs.msg import String
    node = _node(ctx, 'wmsg_errors')
    pub = node.create_publisher(Image, '/' + _unique('wmsg_err'), 10)
    sub = node.create_subscription(Image, '/' + _unique('wmsg_err'), lambda m: None, 10)
    chan = _dds.create_channel_publisher(node, Image, 'rt/err/_buf/5_6', QoSProfile(depth=1))
    msg = _image(4)
    with pytest.raises(TypeError, match='does not publish'):
        _native.write_message(String(data='x'), 1, [chan])
    with pytest.raises(TypeError, match='does not publish'):
        _native.write_message(String(data='x'), 1, [pub])
    with pytest.raises(TypeError, match='does not publish'):  # written from its slots
        _native.write_message(String(data='x'), 1, [chan], codec.program_of(String))
    with pytest.raises(TypeError, match='Publisher'):
        _native.write_message(msg, 1, [sub])
    with pytest.raises(ValueError, match='source_timestamp'):
        _native.write_message(msg, -1, [pub])
    with pytest.raises(TypeError, match='not a generated ROS message class'):
        _native.write_message(object(), 1, [pub])
    with pytest.raises(TypeError, match='not a generated ROS message class'):
        _native.take_message_with_gid(sub, dict)
    _native.write_message(msg, 1, [])  # nothing to write to
    chan.destroy()
    with pytest.raises(_dds.DdsError, match='destroyed'):
        _native.write_message(msg, 1, [pub, chan])
    node.destroy_node()


# ---------------------------------------------------------------- matched subscriptions


def test_matched_subscription_gids(ctx):
    topic = '/' + _unique('matched')
    node = _node(ctx, 'matched')
    pub = node.create_publisher(Image, topic, 10)
    assert _native.matched_subscription_gids(pub) == []
    local = node.create_subscription(Image, topic, lambda m: None, 10)
    # a best-effort publisher's incompatible reliable reader would not match: only compatible
    peer = Peer('plain_sub', topic)
    try:
        remote = bytes.fromhex(peer.expect('READY ')['gid'])
        expected = {_dds.endpoint_gid(local), remote}
        assert _wait(lambda: set(_native.matched_subscription_gids(pub)) == expected, timeout=15)
        assert len(_native.matched_subscription_gids(pub.handle)) == 2  # raw handle
        assert _native.matched_subscription_gids(pub.handle.pointer)  # pointer int
        graph = {bytes(i.endpoint_gid) for i in node.get_subscriptions_info_by_topic(topic)}
        assert graph == expected
        assert pub.get_subscription_count() == 2
        peer.send('quit')
        assert peer.expect('RESULT ') == {'ok': True}
        assert peer.proc.wait(timeout=15) == 0
    finally:
        peer.close()
    # a clean exit unmatches at once (no lease expiry)
    t0 = time.monotonic()
    assert _wait(lambda: _native.matched_subscription_gids(pub) == [_dds.endpoint_gid(local)],
                 timeout=5)
    assert time.monotonic() - t0 < 5
    node.destroy_subscription(local)
    assert _wait(lambda: _native.matched_subscription_gids(pub) == [])
    node.destroy_node()


@pytest.mark.parametrize('reliability', ['reliable', 'best_effort'])
def test_exclude_from_next_write_keeps_a_sample_from_the_named_readers(ctx, reliability):
    """Every other sample is kept from one of two readers; the other gets all of them. Taking
    the filter off gives every reader every sample again."""
    from rclpy.qos import ReliabilityPolicy
    from std_msgs.msg import String
    qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE if reliability ==
                     'reliable' else ReliabilityPolicy.BEST_EFFORT)
    topic = '/' + _unique('exclude')
    node = _node(ctx, 'exclude')
    pub = node.create_publisher(String, topic, qos)
    got = {'a': [], 'b': []}
    sub_a = node.create_subscription(String, topic, lambda m: got['a'].append(m.data), qos)
    node.create_subscription(String, topic, lambda m: got['b'].append(m.data), qos)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    assert spin_until(executor, lambda: pub.get_subscription_count() == 2)
    for i in range(10):
        assert _native.exclude_from_next_write(pub, [_dds.endpoint_gid(sub_a)] if i % 2 else [])
        pub.publish(String(data=str(i)))
    assert spin_until(executor, lambda: len(got['b']) == 10)
    executor.spin_once(timeout_sec=0.2)
    assert got == {'a': [str(i) for i in range(0, 10, 2)], 'b': [str(i) for i in range(10)]}
    assert _native.exclude_from_next_write(pub, [_dds.endpoint_gid(sub_a)])
    _native.remove_write_exclusions(pub)  # the registration goes with the filter
    _native.remove_write_exclusions(pub)  # nothing left to remove
    pub.publish(String(data='after'))
    assert spin_until(executor, lambda: got['a'][-1:] == got['b'][-1:] == ['after'])
    with pytest.raises(ValueError, match=r'reader_gids\[0\] must be 16 bytes'):
        _native.exclude_from_next_write(pub, [b'short'])
    with pytest.raises(TypeError):
        _native.exclude_from_next_write(sub_a, [])  # not a publisher
    executor.shutdown()
    node.destroy_node()


# ---------------------------------------------------------------- new-message wakeups


def _raw_subscription(node, topic, depth=10):
    """A bare rclpy._rclpy_pybind11.Subscription: no executor ever takes from it."""
    from rclpy import _rclpy_pybind11 as rclpy_c
    _dds.type_support(Image)  # imports it (rclpy's create_subscription would)
    with node.handle:
        return rclpy_c.Subscription(
            node.handle, Image, topic, QoSProfile(depth=depth).get_c_qos_profile())


def _drain(sub):
    out = []
    while True:
        taken = _native.take_serialized_with_gid(sub)
        if taken is None:
            return out
        out.append(taken)


def test_new_message_wakeup_cross_process(ctx):
    topic = '/' + _unique('wake')
    node = _node(ctx, 'wake')
    woken = []
    gc = node.create_guard_condition(lambda: woken.append(1))
    sub = _raw_subscription(node, topic)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)

    def spin_until(predicate, timeout=10.0):
        return _wait(lambda: executor.spin_once(timeout_sec=0.02) or predicate(), timeout)

    def settle():
        for _ in range(5):  # run triggers that are already latched
            executor.spin_once(timeout_sec=0.01)
        woken.clear()

    _native.set_new_message_wakeup(sub, gc)
    peer = Peer('pub_on_demand', topic)
    try:
        peer_gid = bytes.fromhex(peer.expect('READY ')['gid'])
        # both ends matched (the peer says READY once its writer matched our reader), so the
        # volatile samples below cannot be lost, however slow the machine
        assert _wait(lambda: sub.get_publisher_count() == 1, timeout=15)
        peer.send('pub 1')
        assert spin_until(lambda: woken)
        assert [t[1] for t in _wait(lambda: _drain(sub))] == [peer_gid]
        # every new message wakes again (once all was taken)
        settle()
        peer.send('pub 2')
        assert spin_until(lambda: woken)
        assert len(_wait(lambda: _drain(sub))) == 1

        # clear is a barrier: a message arrives (we take it) and nothing wakes
        _native.clear_new_message_wakeup(sub)
        _native.clear_new_message_wakeup(sub)  # no-op
        settle()
        peer.send('pub 3')
        assert len(_wait(lambda: _drain(sub))) == 1
        for _ in range(10):
            executor.spin_once(timeout_sec=0.02)
        assert not woken

        # set again, replacing with a second guard condition: only that one wakes
        woken2 = []
        gc2 = node.create_guard_condition(lambda: woken2.append(1))
        _native.set_new_message_wakeup(sub.pointer, gc)  # pointer int works too
        _native.set_new_message_wakeup(sub, gc2.handle)  # replaces (and unpins) gc
        settle()
        peer.send('pub 4')
        assert spin_until(lambda: woken2)
        assert not woken
        assert len(_wait(lambda: _drain(sub))) == 1
        _native.clear_new_message_wakeup(sub)
        node.destroy_guard_condition(gc2)  # unpinned: destroyed right away
        peer.send('quit')
        assert peer.expect('RESULT ') == {'sent': 4}
        assert peer.proc.wait(timeout=15) == 0
    finally:
        peer.close()
    executor.shutdown()
    sub.destroy_when_not_in_use()
    node.destroy_node()


def test_new_message_wakeup_with_unread_messages(ctx):
    """rmw calls back at once when messages are already waiting."""
    topic = '/' + _unique('wake_unread')
    node = _node(ctx, 'wake_unread')
    woken = []
    gc = node.create_guard_condition(lambda: woken.append(1))
    sub = _raw_subscription(node, topic)
    pub = node.create_publisher(Image, topic, 10)
    assert _wait(lambda: pub.get_subscription_count() == 1)
    pub.publish(_image(3))
    pub.publish(_image(4))
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    _wait(lambda: executor.spin_once(timeout_sec=0.05) or False, timeout=0.2)
    assert not woken
    _native.set_new_message_wakeup(sub, gc)
    assert _wait(lambda: executor.spin_once(timeout_sec=0.05) or woken)
    assert len(_drain(sub)) == 2
    _native.clear_new_message_wakeup(sub)
    executor.shutdown()
    sub.destroy_when_not_in_use()
    node.destroy_node()


@pytest.mark.parametrize('first', ['subscription', 'guard_condition', 'node', 'shutdown'])
def test_new_message_wakeup_destroy_orders(ctx, first):
    """Destroying anything before clear is deferred by the pins; clear then lets go."""
    topic = '/' + _unique('wake_order')
    node = _node(ctx, 'wake_order')
    pub_node = _node(ctx, 'wake_order_pub')
    gc = node.create_guard_condition(lambda: None)
    sub = node.create_subscription(Image, topic, lambda m: None, 10, raw=True)
    pub = pub_node.create_publisher(Image, topic, 10)
    assert _wait(lambda: pub.get_subscription_count() == 1)
    _native.set_new_message_wakeup(sub, gc)
    sub_pointer = sub.handle.pointer
    if first == 'subscription':
        node.destroy_subscription(sub)
    elif first == 'guard_condition':
        node.destroy_guard_condition(gc)
    elif first == 'node':
        node.destroy_node()
    else:
        ctx.shutdown()
    # Messages still arrive and trigger the (still alive) guard condition. Write through the
    # DataWriter: it works after rclpy.shutdown() too.
    _native.publish_serialized(pub.handle.pointer, serialize_message(_image(4)), 42)
    taken = _wait(lambda: _native.take_serialized_with_gid(sub_pointer))
    assert taken[2]['source_timestamp'] == 42
    _native.clear_new_message_wakeup(sub)  # works after destroy was requested
    if first in ('subscription', 'node'):
        with pytest.raises(Exception):  # the deferred destroy happened in clear
            _dds.endpoint_gid(sub)
    _native.clear_new_message_wakeup(sub.handle)  # nothing set (or destroyed): no-op
    node.destroy_node()
    pub_node.destroy_node()


# ---------------------------------------------------------------- lifetimes and errors


def test_node_destroyed_before_channels(ctx):
    node = _node(ctx, 'destroy_order')
    topic = _channel_topic(_unique('order'))
    gc = node.create_guard_condition(lambda: None)
    pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=5))
    sub = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=5),
                                           guard_condition=gc)
    _native.add_discovery_wakeup(node, gc)
    node.destroy_node()  # deferred by the pins: channels keep working
    assert _wait(lambda: pub.matched_count() == 1)
    pub.publish(serialize_message(_image(8)))
    assert _wait(sub.take)[1] == pub.gid
    assert _native.remove_discovery_wakeup(gc) is True  # after destroy was requested
    sub.destroy()
    sub.destroy()  # idempotent
    pub.destroy()
    assert not pub.valid and not sub.valid
    with pytest.raises(_dds.DdsError):
        pub.publish(b'\0\1\0\0')
    with pytest.raises(_dds.DdsError):
        sub.take()
    with pytest.raises(Exception):  # the rcl node is gone now
        _native.install_discovery(node.handle)


def test_shutdown_before_channels(ctx):
    node = _node(ctx, 'shutdown_order')
    topic = _channel_topic(_unique('shutdown'))
    gc = node.create_guard_condition(lambda: None)
    pub = _dds.create_channel_publisher(node, Image, topic, QoSProfile(depth=5))
    sub = _dds.create_channel_subscription(node, Image, topic, QoSProfile(depth=5),
                                           guard_condition=gc)
    _native.add_discovery_wakeup(node, gc)
    ctx.shutdown()
    sub.destroy()
    pub.destroy()
    _native.remove_discovery_wakeup(gc)
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


def test_silence_discovery_stops_the_participant_listening(ctx):
    """What shutdown and exit do before rmw destroys a participant (src/native/README.md,
    "Never Fast DDS's default wait in set_listener")."""
    node = _node(ctx, 'silenced')
    other = _node(ctx, 'silenced_other')  # the same participant
    remote_ctx = Context()
    rclpy.init(context=remote_ctx)
    try:
        remote = _node(remote_ctx, 'silenced_remote')
        assert _native.install_discovery(node) is True
        before, after = '/' + _unique('before'), '/' + _unique('after')
        remote.create_publisher(Image, before, 10)
        assert _wait(lambda: node.count_publishers(before) == 1)  # the graph listens
        assert _native.silence_discovery(node) is True
        assert _native.silence_discovery(other) is False  # once per participant
        assert _native.discovery_stats(node) == {'installed': False}
        with pytest.raises(_dds.DdsError, match='stopped listening'):
            _native.install_discovery(other)  # never a tap again
        remote.create_publisher(Image, after, 10)
        time.sleep(2.0)  # discovery of the first publisher took well under that
        assert node.count_publishers(after) == 0
        started = time.monotonic()
        node.destroy_node()
        other.destroy_node()  # the participant goes: nothing to wait for
        assert time.monotonic() - started < 5.0
    finally:
        remote_ctx.try_shutdown()


def test_context_shutdown_and_exit_silence_the_participant(ctx, tmp_path):
    from rosidl_buffer_py import create_publisher, discovery
    node = _node(ctx, 'shutdown_silenced')
    create_publisher(node, Image, '/' + _unique('silenced'), 10)
    first = discovery.for_node(node)
    assert _native.discovery_stats(node)['installed']
    ctx.shutdown()
    assert _native.discovery_stats(node) == {'installed': False}
    node.destroy_node()
    assert first not in discovery.registered()  # forgotten with its context
    # at exit, before the interpreter collects nodes (and rmw destroys their participant)
    script = tmp_path / 'exit_silences.py'
    script.write_text(
        'import atexit, sys\n'
        'import rclpy\n'
        'from sensor_msgs.msg import Image\n'
        'def after():  # registered before rosidl_buffer_py is imported: runs after its own\n'
        '    print("STATS", sys.modules["rosidl_buffer_py._native"].discovery_stats(node))\n'
        'atexit.register(after)\n'
        'import rosidl_buffer_py\n'
        'rclpy.init()\n'
        'node = rclpy.create_node("exit_silenced")\n'
        'sub = rosidl_buffer_py.create_subscription(node, Image, "exit_silenced", print, 10)\n'
        'print("STATS", rosidl_buffer_py._native.discovery_stats(node)["installed"])\n')
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ['STATS True', "STATS {'installed': False}"]


def test_the_last_node_destroyed_silences_the_participant_first(ctx):
    """rmw destroys the context's participant with its last node, inside destroy_node(), with
    the unbounded wait the context's shutdown avoids: the participant stops listening before,
    and only then (another node keeps rmw's graph and the tap)."""
    from rosidl_buffer_py import create_publisher, create_subscription, discovery
    first, second = _node(ctx, 'last_node_a'), _node(ctx, 'last_node_b')
    topic = '/' + _unique('last_node')
    create_publisher(first, Image, topic, 10)
    create_subscription(second, Image, topic, print, 10)
    tap = discovery.for_node(second)
    assert _native.silence_discovery_if_last_node(first) is False  # two nodes share it
    assert _native.discovery_stats(second)['installed']
    first.destroy_node()
    assert _native.discovery_stats(second)['installed']  # the other node still listens
    assert tap in discovery.registered()
    assert second.count_publishers(topic) == 0  # rmw's graph saw the publisher go
    second.destroy_node()  # the last one: silenced, then rmw destroys the participant
    assert tap not in discovery.registered()
    third = _node(ctx, 'last_node_c')  # a new participant of the same context: a new tap
    create_publisher(third, Image, topic, 10)
    assert _native.discovery_stats(third)['installed']
    assert discovery.for_node(third) is not tap
    third.destroy_node()


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
        _native.ChannelPublisher(node, object(), 'rt/x')
    with pytest.raises(ValueError, match='QoS'):
        _native.ChannelPublisher(node, _dds.type_support(Image), 'rt/x', reliability=7)
    chan = _dds.create_channel_publisher(node, Image, 'rt/err/_buf/1_2', QoSProfile(depth=1))
    with pytest.raises(ValueError, match='too short'):
        chan.publish(b'')
    chan.destroy()
    node.destroy_publisher(pub)
    with pytest.raises(Exception):  # rclpy refuses to hand out a destroyed handle
        _dds.endpoint_gid(pub)
    node.destroy_node()


def test_write_message_writes_the_descriptor_form_from_the_slots_and_take_described_reads_it(
        ctx):
    """``write_message(..., descriptor=)`` writes codec.encode's descriptor bytes to channels
    in one call; ``take_described`` gives those bytes with codec.decode's reading of them, and
    None for everything that is not a descriptor message."""
    from rosidl_buffer_py import control
    node = _node(ctx, 'wdesc')
    chan_topic = _channel_topic(_unique('wdesc'))
    chan = _dds.create_channel_publisher(node, Image, chan_topic, QoSProfile(depth=10))
    chan_sub = _dds.create_channel_subscription(node, Image, chan_topic, QoSProfile(depth=10))
    main = node.create_publisher(Image, '/' + _unique('wdesc'), 10)
    assert _wait(lambda: chan.matched_count() == 1)
    msg = _image(300, seed=5)
    msg.header.frame_id = 'camera'
    program = codec.descriptor_program(Image)
    assert program is not None
    pair = ('demo', b'\x01' * 52)
    assert _native.write_message(msg, STAMPS[0], [chan], program, pair) is True
    # no program: nothing written (the codec's path is the caller's)
    assert _native.write_message(msg, STAMPS[1], [chan], None, pair) is False
    with pytest.raises(TypeError, match='not a ChannelPublisher'):
        _native.write_message(msg, STAMPS[1], [chan, main], program, pair)
    with pytest.raises(TypeError, match='backend_type, descriptor bytes'):
        _native.write_message(msg, STAMPS[1], [chan], program, ('demo', 'text'))
    good = serialize_message(_image(12, seed=6))
    # a descriptor message with a control message's encapsulation options is not read as one
    marked = b'\x00\x01RB' + bytes(codec.encode(msg, pair))[4:]
    samples = (good, control.PROBE_BYTES, good[:30], marked)
    for data in samples:
        chan.publish(data, source_timestamp=STAMPS[1])
    reading = codec.descriptor_reading(Image)
    assert reading.field == 'data' and codec.payload_field(Image) == 'data'
    raw, gid, info, described = _wait(lambda: chan_sub.take_described(*reading.args))
    assert raw == bytes(codec.encode(msg, pair)) and gid == chan.gid
    assert info['source_timestamp'] == STAMPS[0]
    decoded = codec.decode(raw, Image)
    assert type(described[0]) is Image and described[0] == decoded.msg
    assert described[1:] == pair
    for data in samples:  # read by the codec, as bytes
        taken = _wait(lambda: chan_sub.take_described(*reading.args))
        assert taken[0] == data and taken[1] == chan.gid and taken[3] is None
    assert chan_sub.take_described(*reading.args) is None
    from std_msgs.msg import String  # no uint8[] payload: no descriptor form
    assert codec.descriptor_reading(String) is None and codec.descriptor_program(String) is None
    chan.destroy()
    chan_sub.destroy()
    node.destroy_node()
