"""A zero-copy subscriber beside a legacy listener is never held behind the main topic's traffic
(issue #19, part 4).

Real nodes in real processes over Fast DDS: a demo publisher of 640x480 rgb8 frames at 30 Hz, a
subscriber accepting ``demo`` (descriptors on its channel) and a plain rclpy subscriber (full
frames on the main topic). Before the fix the channel's descriptors went through the
publisher's shared-memory segment, where the main topic's 921 KB frames recycled them before
the demo subscriber read them: its p99 was 0.3 to 1.6 s, 5 to 50 times the plain subscriber's.
Nothing here is compared with an absolute time: the demo subscriber's p99 is compared with the
plain subscriber's of the same run (whatever the machine's load did to both), with a 100 ms
margin, far below the stalls this guards against. With
ROSIDL_BUFFER_PY_CHANNEL_TRANSPORT=participant (channels back in shared memory, as before the
fix) it fails: demo p99 279 ms against 22 ms.
"""
from launch_free_demos.bench.mixed import run_latency


def test_channel_frames_are_not_held_behind_a_legacy_listeners_frames():
    result = run_latency('mixed', 640, 480, frames=240, rate=30.0, depth=10,
                         topic='/test_mixed_latency/image', patience=10.0)
    demo, plain = result['demo_sub'], result['plain_sub']
    assert demo['channels'] == 240 - demo['lost'], result  # the frames came on the channel
    assert demo['p99'] <= plain['p99'] + 100.0, result
    assert demo['lost'] == 0, result  # a descriptor lost and not repaired before 10 newer ones
