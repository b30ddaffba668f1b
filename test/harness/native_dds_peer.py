"""Second process for test_native_dds.py (not collected by pytest).

    python native_dds_peer.py watch TOPIC MARKER       discovery: wait for a writer on DDS
        topic TOPIC whose USER_DATA contains MARKER; print it and the rmw graph's view. Exits
        3 (RACED) when rmw discovered the writer before the tap was installed: the tap then
        never sees its USER_DATA, and the caller starts another peer.
    python native_dds_peer.py channel_sub TOPIC COUNT  ChannelSubscription woken through a
        guard condition by an executor; print what COUNT messages looked like.
    python native_dds_peer.py linger                   create channels and wakeups, never
        destroy them, exit (interpreter exit must not crash).
    python native_dds_peer.py raw_take TOPIC COUNT     plain rclpy raw subscription (rclpy's
        own take_message); print the bytes' hashes and message infos of COUNT messages.
    python native_dds_peer.py plain_sub TOPIC          plain rclpy subscription; print its GID,
        then exit cleanly at the first stdin line (or EOF).
    python native_dds_peer.py pub_on_demand TOPIC      plain rclpy publisher; publish one Image
        per stdin line 'pub <seed>', print 'SENT <seed>'; exit cleanly at 'quit' or EOF.

Prints one JSON line prefixed with 'RESULT ' (and 'READY' once set up); exits 0 on success.
"""
import hashlib
import json
import sys
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import Image

from rosidl_buffer_py import _dds, _native


#: Exit status of `watch` when discovery beat the tap (see the module docstring).
RACED = 3


def say(line: str) -> None:
    print(line, flush=True)


def watch(topic: str, marker: str) -> int:
    node = rclpy.create_node('native_dds_watch')
    _native.install_discovery(node)  # right after creating the node: nothing is missed
    woken = []
    gc = node.create_guard_condition(lambda: woken.append(1))
    _native.add_discovery_wakeup(node, gc)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    say('READY')
    ros_topic = '/' + topic[len('rt/'):]
    events = []
    found = None
    deadline = time.monotonic() + 20
    in_graph_since = None
    while found is None and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.2)
        for ev in _dds.drain_discovery_events(node):
            events.append(ev)
            if (ev.kind == 'writer' and ev.topic == topic and marker.encode() in ev.user_data
                    and ev.status in ('discovered', 'changed')):
                found = ev
        # The participant exists from create_node() on, so Fast DDS may discover the writer
        # in the moment before install_discovery(): rmw's graph then has it, the tap never
        # will. (The tap calls rmw's listener first, so allow it a moment to record.)
        if found is None and in_graph_since is None and not any(
                e.topic == topic for e in events) and node.get_publishers_info_by_topic(
                    ros_topic):
            in_graph_since = time.monotonic()
        if found is None and in_graph_since is not None and not any(
                e.topic == topic for e in events) and time.monotonic() > in_graph_since + 1:
            say('RESULT ' + json.dumps({'error': 'raced', 'events': len(events)}))
            return RACED
    if found is None:
        say('RESULT ' + json.dumps({'error': 'not found', 'events': len(events)}))
        return 1
    # rmw's graph must still know the endpoint, with a non-zero type hash.
    graph = []
    while time.monotonic() < deadline:
        graph = [i for i in node.get_publishers_info_by_topic(ros_topic)
                 if bytes(i.endpoint_gid) == found.gid]
        if graph:
            break
        time.sleep(0.05)
    known = [e for e in _dds.list_known_endpoints(node) if e.gid == found.gid]
    result = {
        'gid': found.gid.hex(),
        'status': found.status,
        'user_data': found.user_data.decode(),
        'type_name': found.type_name,
        'local': found.local,
        'known_user_data': known[0].user_data.decode() if known else None,
        'graph_type': graph[0].topic_type if graph else None,
        'graph_type_hash': str(graph[0].topic_type_hash) if graph else None,
        'woken': len(woken) > 0,
        'statuses': sorted({e.status for e in events if e.gid == found.gid}),
    }
    _native.remove_discovery_wakeup(gc)
    executor.shutdown()
    node.destroy_node()
    say('RESULT ' + json.dumps(result))
    return 0


def channel_sub(topic: str, count: int) -> int:
    node = rclpy.create_node('native_dds_channel_sub')
    received = []
    sub = None

    def on_wake():
        while True:
            taken = sub.take()
            if taken is None:
                return
            data, gid, info = taken
            received.append({
                'sha': hashlib.sha256(data).hexdigest(),
                'len': len(data),
                'gid': gid.hex(),
                'info_keys': sorted(info),
                'pub_seq': info['publication_sequence_number'],
                'source_timestamp': info['source_timestamp'],
            })

    gc = node.create_guard_condition(on_wake)
    sub = _dds.create_channel_subscription(
        node, Image, topic, rclpy.qos.QoSProfile(depth=10), guard_condition=gc)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    say('READY ' + json.dumps({'gid': sub.gid.hex()}))
    deadline = time.monotonic() + 20
    while len(received) < count and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.2)
    sub.destroy()
    executor.shutdown()
    node.destroy_node()
    say('RESULT ' + json.dumps({'received': received}))
    return 0 if len(received) >= count else 1


def linger() -> int:
    node = rclpy.create_node('native_dds_linger')
    gc = node.create_guard_condition(lambda: None)
    _native.add_discovery_wakeup(node, gc)
    pub = _dds.create_channel_publisher(
        node, Image, 'rt/linger/_buf/0a_0b', rclpy.qos.QoSProfile(depth=1))
    sub = _dds.create_channel_subscription(
        node, Image, 'rt/linger/_buf/0a_0b', rclpy.qos.QoSProfile(depth=1), guard_condition=gc)
    # a new-message wakeup that is never cleared, on a raw rclpy subscription
    _dds.type_support(Image)
    raw_sub = rclpy._rclpy_pybind11.Subscription(
        node.handle, Image, '/linger_raw', rclpy.qos.QoSProfile(depth=1).get_c_qos_profile())
    _native.set_new_message_wakeup(raw_sub, gc)
    raw_pub = node.create_publisher(Image, '/linger_raw', 1)
    pub.publish(rclpy.serialization.serialize_message(Image(width=1)))
    _native.publish_serialized(raw_pub, rclpy.serialization.serialize_message(Image(width=2)), 1)
    time.sleep(0.2)
    # keep references in a module global so they die during interpreter finalization
    globals()['_keep'] = (node, gc, pub, sub, raw_sub, raw_pub)
    say('RESULT ' + json.dumps({'ok': True}))
    return 0


def raw_take(topic: str, count: int) -> int:
    node = rclpy.create_node('native_dds_raw_take')
    sub = node.create_subscription(Image, topic, lambda msg: None, 10, raw=True)
    say('READY ' + json.dumps({'gid': _dds.endpoint_gid(sub).hex()}))
    received = []
    deadline = time.monotonic() + 20
    while len(received) < count and time.monotonic() < deadline:
        with sub.handle:  # rclpy's own take, as its executor does it
            taken = sub.handle.take_message(Image, True)
        if taken is None:
            time.sleep(0.005)
            continue
        data, info = taken
        received.append({'sha': hashlib.sha256(data).hexdigest(),
                         'hex': data.hex() if len(data) <= 4096 else None,
                         'source_timestamp': info['source_timestamp'],
                         'received_timestamp': info['received_timestamp']})
    node.destroy_node()
    say('RESULT ' + json.dumps({'received': received}))
    return 0 if len(received) >= count else 1


def plain_sub(topic: str) -> int:
    node = rclpy.create_node('native_dds_plain_sub')
    sub = node.create_subscription(Image, topic, lambda msg: None, 10)
    say('READY ' + json.dumps({'gid': _dds.endpoint_gid(sub).hex()}))
    sys.stdin.readline()  # the test says when to go (EOF also does)
    node.destroy_node()
    say('RESULT ' + json.dumps({'ok': True}))
    return 0


def pub_on_demand(topic: str) -> int:
    node = rclpy.create_node('native_dds_pub_on_demand')
    pub = node.create_publisher(Image, topic, 10)
    while pub.get_subscription_count() < 1:  # volatile: a sample before the match is lost
        time.sleep(0.01)
    say('READY ' + json.dumps({'gid': _dds.endpoint_gid(pub).hex()}))
    sent = 0
    for line in sys.stdin:
        words = line.split()
        if not words or words[0] != 'pub':
            break
        seed = int(words[1])
        pub.publish(Image(height=1, width=8, encoding='mono8', step=8, data=bytes([seed] * 8)))
        sent += 1
        say(f'SENT {seed}')
    node.destroy_node()
    say('RESULT ' + json.dumps({'sent': sent}))
    return 0


def main(argv) -> int:
    rclpy.init()
    mode = argv[1]
    if mode == 'watch':
        rc = watch(argv[2], argv[3])
    elif mode == 'channel_sub':
        rc = channel_sub(argv[2], int(argv[3]))
    elif mode == 'raw_take':
        rc = raw_take(argv[2], int(argv[3]))
    elif mode == 'plain_sub':
        rc = plain_sub(argv[2])
    elif mode == 'pub_on_demand':
        rc = pub_on_demand(argv[2])
    elif mode == 'linger':
        return linger()  # no shutdown, no destroy: finalization does it
    else:
        raise SystemExit(f'unknown mode {mode}')
    rclpy.try_shutdown()
    return rc


if __name__ == '__main__':
    import rclpy.serialization  # noqa: F401  (used by linger)
    sys.exit(main(sys.argv))
