"""Every message type through the package's endpoints, and rclpy's own contract for them.

- every installed message type can be published and subscribed through
  ``rosidl_buffer_py.create_publisher`` / ``create_subscription``; a type without ``uint8[]``
  fields makes stock endpoints (no channels, no advertisement);
- messages with nested and several payloads travel as descriptors to a demo subscription, as
  identical CPU bytes to a plain one (real processes);
- creating endpoints with bad arguments raises what rclpy raises, stock against ours.
"""
import select
import subprocess
import sys
import textwrap
import time

import pytest
import rclpy
from rclpy.exceptions import InvalidTopicNameException
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import String

import rosidl_buffer_py
from harness import stuck
from harness.in_process import spin_until
from test_codec_general import installed_message_types

TYPES = installed_message_types()


def test_every_installed_message_type_makes_endpoints(context):
    """Publisher and subscription of every installed type are created, listed by their node
    and destroyed; the buffer-aware ones are exactly the types with a uint8[] field."""
    node = rclpy.create_node('every_type', context=context)
    aware = []
    for index, (name, msg_type) in enumerate(sorted(TYPES.items())):
        topic = f'/every_{index}'
        pub = rosidl_buffer_py.create_publisher(node, msg_type, topic, 1)
        sub = rosidl_buffer_py.create_subscription(node, msg_type, topic, lambda m: None, 1,
                                                   acceptable_buffer_backends='any')
        assert pub in node.publishers and sub in node.subscriptions, name
        if sub.statistics()['buffer_aware']:
            aware.append(name)
        assert bool(pub.statistics()['buffer_aware']) == (name in aware), name
        assert node.destroy_publisher(pub) and node.destroy_subscription(sub), name
    with_payloads = sorted(n for n, t in TYPES.items() if rosidl_buffer_py.codec.buffer_paths(t))
    assert aware == with_payloads and 'sensor_msgs/msg/Image' in aware and \
        'stereo_msgs/msg/DisparityImage' in aware and 'std_msgs/msg/String' not in aware
    node.destroy_node()


@pytest.mark.parametrize('type_name', [
    'std_msgs/msg/String', 'sensor_msgs/msg/CameraInfo', 'test_msgs/msg/BasicTypes',
    'stereo_msgs/msg/DisparityImage', 'test_msgs/msg/UnboundedSequences',
    'test_msgs/msg/MultiNested', 'visualization_msgs/msg/Marker'])
def test_messages_of_many_shapes_arrive_intact(context, type_name):
    """In one process over real DDS: a publisher of ours to a subscription of ours accepting
    any backend and to a plain one; both get the message as sent."""
    from rclpy.serialization import deserialize_message, serialize_message
    msg_type = TYPES[type_name]
    msg = msg_type()
    for path in rosidl_buffer_py.codec.field_paths(msg):
        rosidl_buffer_py.codec.set_at(msg, path, bytes(range(7)))
    node = rclpy.create_node('shapes', context=context)
    topic = '/shapes_' + type_name.replace('/', '_')
    got = {'ours': [], 'plain': []}
    rosidl_buffer_py.create_subscription(node, msg_type, topic, got['ours'].append, 10,
                                         acceptable_buffer_backends='any')
    node.create_subscription(msg_type, topic, got['plain'].append, 10)
    pub = rosidl_buffer_py.create_publisher(node, msg_type, topic, 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: pub.get_subscription_count() == 2)
    pub.publish(msg)
    assert spin_until(executor, lambda: got['ours'] and got['plain']), got
    sent = deserialize_message(serialize_message(msg), msg_type)  # as a stock take gives it
    for received in (got['ours'][0], got['plain'][0]):
        assert received == sent
    node.destroy_node()


_PUBLISHER = textwrap.dedent('''
    import sys, time, rclpy
    from stereo_msgs.msg import DisparityImage
    import rosidl_buffer_py
    from rosidl_buffer_py.image import allocate_image_msg, from_output_msg
    rclpy.init()
    node = rclpy.create_node('disparity_pub')
    pub = rosidl_buffer_py.create_publisher(node, DisparityImage, '/disparity', 10)
    deadline = time.monotonic() + 30
    while (pub.get_subscription_count() < 2 or
           not any(p['channel_serving'] for p in pub.buffer_peers())):
        assert time.monotonic() < deadline, pub.buffer_peers()
        rclpy.spin_once(node, timeout_sec=0.05)
    sys.stdin.readline()  # both subscriptions matched us too: go
    for counter in range(5):
        msg = DisparityImage()
        msg.image = allocate_image_msg(48, 64, 'rgb8', backend='demo')
        from_output_msg(msg.image)[...] = counter
        msg.min_disparity = float(counter)
        pub.publish(msg)
        rclpy.spin_once(node, timeout_sec=0.05)
    while pub.get_subscription_count():
        rclpy.spin_once(node, timeout_sec=0.05)
''')

_SUBSCRIBER = textwrap.dedent('''
    import sys, rclpy
    from stereo_msgs.msg import DisparityImage
    import rosidl_buffer_py
    rclpy.init()
    node = rclpy.create_node('disparity_' + sys.argv[1])
    got = []
    def on(msg):
        data = msg.image.data
        got.append((type(data).__name__, getattr(data, 'backend_type', 'cpu'),
                    bytes(memoryview(data)) == bytes([int(msg.min_disparity)]) * (48 * 64 * 3)))
    if sys.argv[1] == 'demo':
        sub = rosidl_buffer_py.create_subscription(node, DisparityImage, '/disparity', on, 10,
                                                   acceptable_buffer_backends='demo')
    else:
        sub = node.create_subscription(DisparityImage, '/disparity', on, 10)
    while sub.get_publisher_count() < 1:
        rclpy.spin_once(node, timeout_sec=0.05)
    print('ready', flush=True)
    while len(got) < 5:
        rclpy.spin_once(node, timeout_sec=0.1)
    print(got, flush=True)
''')


def test_a_nested_payload_travels_as_a_descriptor_and_as_identical_bytes():
    """stereo_msgs/DisparityImage with a demo Buffer in image.data, three processes: the demo
    subscription gets a demo Buffer there, the plain one the same bytes. The publisher starts
    once both subscriptions matched it on their side too (its own count says only that it
    matched them: a plain reader that matches later misses the first frames, as with stock)."""
    subs = {kind: stuck.popen([sys.executable, '-c', _SUBSCRIBER, kind])
            for kind in ('demo', 'plain')}
    pub = stuck.popen([sys.executable, '-c', _PUBLISHER], stdin=subprocess.PIPE)
    processes = [*subs.values(), pub]
    deadline = time.monotonic() + 60
    for kind, proc in subs.items():
        if not select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))[0]:
            raise stuck.Stuck(f'the {kind} subscription never matched the publisher:\n' +
                              stuck.abort_and_report(processes))
        assert proc.stdout.readline() == 'ready\n', stuck.abort_and_report(processes)
    pub.stdin.write('go\n')
    pub.stdin.flush()
    (demo_code, demo_out, _), (plain_code, plain_out, _), (pub_code, _, pub_err) = \
        stuck.communicate_all(processes, timeout=60)
    assert (demo_code, plain_code, pub_code) == (0, 0, 0), pub_err[-3000:]
    demo = eval(demo_out)  # noqa: S307 (our own subprocess's repr of a list)
    plain = eval(plain_out)  # noqa: S307
    assert demo == [('DemoBuffer', 'demo', True)] * 5, demo_out
    assert [(backend, ok) for _, backend, ok in plain] == [('cpu', True)] * 5, plain_out


# --- rclpy's contract: the same arguments raise the same errors --------------------------------

def _create(kind, node, what, topic, qos):
    if what == 'publisher':
        return (node.create_publisher(String, topic, qos) if kind == 'stock' else
                rosidl_buffer_py.create_publisher(node, String, topic, qos))
    from sensor_msgs.msg import Image
    return (node.create_subscription(Image, topic, lambda m: None, qos) if kind == 'stock' else
            rosidl_buffer_py.create_subscription(node, Image, topic, lambda m: None, qos))


@pytest.mark.parametrize('what', ['publisher', 'subscription'])
@pytest.mark.parametrize('topic, qos', [
    ('chatter?', 10), ('{bad_sub}', 10), ('/ok', -1), ('/ok', 'ten'), ('/ok', True),
    ('/ok', 10), ('~/private', 10), ('relative/name', 10)])
def test_bad_arguments_raise_what_rclpy_raises(context, what, topic, qos):
    outcomes = {}
    for kind in ('stock', 'ours'):
        node = rclpy.create_node('contract', namespace='/ns', context=context)
        try:
            endpoint = _create(kind, node, what, topic, qos)
            outcomes[kind] = ('ok', endpoint.topic_name, endpoint.qos_profile.depth)
        except Exception as exc:  # the exception itself is what is compared
            outcomes[kind] = (type(exc), str(exc))
        node.destroy_node()
    assert outcomes['ours'] == outcomes['stock'], outcomes
    if topic == 'chatter?':
        assert outcomes['ours'][0] is InvalidTopicNameException


def test_a_type_without_payloads_sends_no_advertisement(context):
    """A String publisher and subscription of ours are stock endpoints: no USER_DATA beyond
    rmw's own, no channels, no timers."""
    from rosidl_buffer_py import _dds
    node = rclpy.create_node('plain_types', context=context)
    pub = rosidl_buffer_py.create_publisher(node, String, '/plain_string', 10)
    sub = rosidl_buffer_py.create_subscription(node, String, '/plain_string', lambda m: None, 10)
    assert b'BUFBE' not in _dds.get_user_data(pub)
    assert b'BUFBE' not in _dds.get_user_data(sub.handle, 'subscription')
    assert pub.buffer_peers() == [] and sub.buffer_peers() == [] and not list(node.timers)
    time.sleep(0.1)
    node.destroy_node()
