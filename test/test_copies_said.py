"""A subscription says once, in its node's log, when a publisher's messages arrive as CPU
copies although the publisher offers zero-copy (#29: "a fallback to copies is said once"), and
says nothing when they arrive zero-copy. Publisher and subscriber are separate processes over
Fast DDS."""
import sys
import textwrap

import pytest

from harness.stuck import communicate_all, popen

FRAMES = 20

_SCRIPT = textwrap.dedent('''
    import sys, time
    import rclpy
    from rclpy.duration import Duration
    from sensor_msgs.msg import Image
    import rosidl_buffer_py
    from rosidl_buffer_py.image import allocate_image_msg, from_output_msg
    role, topic, mode, frames = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    rclpy.init()
    node = rclpy.create_node(role)
    end = time.monotonic() + 60
    if role == 'pub':
        pub = rosidl_buffer_py.create_publisher(node, Image, topic, 10)
        assert pub.wait_for_buffer_peers(1, timeout_sec=30), 'no subscriber'
        for counter in range(frames):
            msg = allocate_image_msg(64, 64, 'mono8', backend=mode)  # demo: shared memory
            from_output_msg(msg)[...] = counter
            pub.publish(msg)
            rclpy.spin_once(node, timeout_sec=0.02)
        pub.wait_for_all_acked(Duration(seconds=10))
    else:
        got = []
        sub = rosidl_buffer_py.create_subscription(
            node, Image, topic, lambda msg: got.append(type(msg.data).__name__), 10,
            acceptable_buffer_backends=mode)
        print('subscribed', flush=True)
        # until every frame came, or the publisher came and went (KEEP_LAST 10 may drop
        # some, with stock endpoints too)
        while len(got) < frames and time.monotonic() < end and not (
                got and node.count_publishers(topic) == 0):
            rclpy.spin_once(node, timeout_sec=0.1)
        print(sorted(set(got)), bool(got), flush=True)
    node.destroy_node()
    rclpy.shutdown()
''')


@pytest.mark.parametrize('published, accepted, said', [
    ('demo', 'cpu', 'it offers demo and this subscription accepts cpu'),
    ('cpu', 'demo', 'the publisher sent CPU data'),
    ('demo', 'demo', None),
])
def test_copies_are_said_once_per_publisher(tmp_path, published, accepted, said):
    script = tmp_path / 'copies.py'
    script.write_text(_SCRIPT)
    topic = f'/copies_{published}_{accepted}'
    sub = popen([sys.executable, str(script), 'sub', topic, accepted, str(FRAMES)])
    try:
        assert sub.stdout.readline().strip() == 'subscribed'
    except BaseException:
        sub.kill()
        sub.communicate()
        raise
    pub = popen([sys.executable, str(script), 'pub', topic, published, str(FRAMES)])
    (pcode, _, perr), (scode, out, err) = communicate_all([pub, sub], 90)
    assert pcode == 0, perr[-2000:]
    assert scode == 0, err[-2000:]
    kind = 'DemoBuffer' if said is None else 'array'
    assert out.strip() == f"['{kind}'] True", (out, err[-2000:])
    lines = [line for line in err.splitlines() if 'arrive as CPU copies' in line]
    if said is None:
        assert lines == [], err[-2000:]
    else:
        assert len(lines) == 1 and said in lines[0] and topic in lines[0], err[-2000:]
