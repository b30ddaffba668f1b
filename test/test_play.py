"""buffer_play in real processes: log-time order whatever the file order, the first message of
each topic on time, nothing but its own output on stdout."""
import json
import os
import random
import signal
import subprocess
import sys
import time

from mcap.writer import CompressionType, Writer
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import String

from rosidl_buffer_py.report import REPORT_PREFIX
from rosidl_buffer_py.tools.message_definition import full_definition

IMAGES, TEXTS, PERIOD_NS = 45, 15, 50_000_000

#: Prints one JSON line per message: topic, counter, receive time; it stops on SIGINT.
LISTENER = '''
import json, sys, time, rclpy
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node('listener')
def on_image(msg):
    counter = int.from_bytes(bytes(msg.data[:8]), 'little')
    print(json.dumps(['/ooo/image', counter, time.time()]), flush=True)
def on_text(msg):
    print(json.dumps(['/ooo/text', int(msg.data), time.time()]), flush=True)
subscriptions = [node.create_subscription(Image, '/ooo/image', on_image, QoSProfile(depth=100)),
                 node.create_subscription(String, '/ooo/text', on_text, QoSProfile(depth=100))]
print('ready', flush=True)
try:
    rclpy.spin(node)
except KeyboardInterrupt:
    pass
'''


def _write_out_of_order_bag(path) -> None:
    """A valid, indexed, chunked MCAP (mcap's own writer, as rosbags writes them) whose records
    are shuffled: file order is not log-time order, and chunks overlap in time."""
    t0 = time.time_ns()
    messages = []
    for i in range(IMAGES):
        image = Image(height=1, width=64, encoding='mono8', step=64,
                      data=list(i.to_bytes(8, 'little')) + [0] * 56)
        messages.append(('/ooo/image', t0 + i * PERIOD_NS, serialize_message(image)))
    for i in range(TEXTS):
        messages.append(('/ooo/text', t0 + 3 * i * PERIOD_NS + 1, serialize_message(
            String(data=str(i)))))
    random.Random(7).shuffle(messages)
    with open(path, 'wb') as stream:
        writer = Writer(stream, chunk_size=600, compression=CompressionType.NONE)
        writer.start(profile='ros2', library='test')
        channels = {}
        for topic, type_name in (('/ooo/image', 'sensor_msgs/msg/Image'),
                                 ('/ooo/text', 'std_msgs/msg/String')):
            definition = full_definition(type_name)
            schema = writer.register_schema(type_name, definition.encoding,
                                            definition.text.encode())
            channels[topic] = writer.register_channel(topic, 'cdr', schema, {})
        for sequence, (topic, log_time, data) in enumerate(messages):
            writer.add_message(channels[topic], log_time, data, log_time, sequence)
        writer.finish()


def test_out_of_order_bag_plays_in_log_time_order_and_on_time(tmp_path):
    bag = tmp_path / 'shuffled.mcap'
    _write_out_of_order_bag(bag)
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    listener = subprocess.Popen([sys.executable, '-c', LISTENER], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env=env,
                                start_new_session=True)
    try:
        assert listener.stdout.readline().strip() == 'ready'
        play = subprocess.run([sys.executable, '-m', 'rosidl_buffer_py.tools.play', str(bag),
                               '--wait-for-subscribers', '1', '--linger', '2'],
                              capture_output=True, text=True, env=env, timeout=120)
        time.sleep(0.5)
    finally:
        listener.send_signal(signal.SIGINT)
        try:
            out, err = listener.communicate(timeout=20)
        finally:
            if listener.poll() is None:
                listener.kill()
                out, err = listener.communicate()
    assert play.returncode == 0, play.stderr[-3000:]
    # stdout is the player's own: its REPORT line and nothing from Fast DDS
    lines = play.stdout.splitlines()
    assert [line for line in lines if not line.startswith(REPORT_PREFIX)] == [], lines
    report = json.loads(lines[-1][len(REPORT_PREFIX):])
    received = [json.loads(line) for line in out.splitlines() if line.startswith('[')]
    images = [counter for topic, counter, _ in received if topic == '/ooo/image']
    texts = [counter for topic, counter, _ in received if topic == '/ooo/text']
    assert images == list(range(IMAGES)), images
    assert texts == list(range(TEXTS)), texts
    for topic, entry in report['topics'].items():
        # the clock starts once the first message is ready: no topic's first message is late
        assert entry['first_late_ms'] < 15, (topic, entry)
    # the receive times follow the recorded times (50 ms apart), not the file order
    times = [t for topic, _, t in received if topic == '/ooo/image']
    assert times[-1] - times[0] > (IMAGES - 1) * PERIOD_NS / 1e9 * 0.8
