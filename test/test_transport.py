"""The buffer-aware transport over real Fast DDS: real rclpy nodes, real processes.

The multi-process matrix is harness.scenarios (the same scenarios users run); the
edges that need finer control (restarts, SIGKILL, a second participant, one process) are here.
Every frame carries a counter and a checksum that the subscriber verifies.
"""
import array
import time

import pytest
import rclpy
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

import rosidl_buffer_py
from harness.in_process import frame, spin_until
from harness.scenarios import SCENARIOS, SMALL
from launch_free_demos.domains import fresh_domain
from launch_free_demos.runner import Run
from rosidl_buffer_py import _dds, _native, advertisement, codec
from rosidl_buffer_py import publisher, routes
from rosidl_buffer_py.nodes.frames import check_frame

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)  # bursts fit


@pytest.mark.parametrize('name', list(SCENARIOS))
def test_scenario(name):
    """Every named scenario; ``subscriber_killed`` also checks that the publisher dropped the
    dead subscriber's channel (its report at exit lists no peer) once its lease expired."""
    with fresh_domain():
        result = SCENARIOS[name].run(timeout=40.0)
    assert result.ok, '\n'.join(result.failures) + '\n' + result.diagnostics


def _sub_params(topic, count, **extra):
    return dict(topic=topic, expected_count=count, timeout_sec=40.0, **extra)


def _pub_params(topic, count, **extra):
    params = dict(topic=topic, count=count, rate_hz=50.0, wait_for_subscribers=1,
                  wait_timeout_sec=40.0, linger_sec=10.0, **SMALL)
    params.update(extra)
    return params


def test_publisher_restarted():
    topic = '/restart_image'
    with Run() as run:
        run.start('sub', 'image_subscriber', **_sub_params(
            topic, 40, acceptable_buffer_backends='demo', expected_backend='demo'))
        run.start('pub1', 'image_publisher', **_pub_params(
            topic, 20, backend='demo', wait_for_buffer_peers=1, linger_sec=0.0))
        assert run.wait(['pub1'], 60), run.diagnostics()
        assert run.nodes['pub1'].process.returncode == 0, run.diagnostics()  # it sent all
        run.start('pub2', 'image_publisher', **_pub_params(
            topic, 20, backend='demo', first_frame=20, wait_for_buffer_peers=1))
        assert run.wait(['sub'], 60), run.diagnostics()
        report = run.nodes['sub'].report
    assert report['distinct'] == 40 and report['received'] == 40, (report, run.diagnostics())
    assert report['duplicates'] == report['checksum_failures'] == report['gaps'] == 0, report
    assert report['backends'] == {'demo': 40}, report








@pytest.mark.parametrize('kind', ['stock', 'ours'])
def test_a_slow_subscriber_gets_every_frame_its_publisher_sent_before_exiting(kind):
    """A publisher of 30 frames at 30 Hz that exits 0.5 s after its last one, a subscriber
    spending 0.2 s per frame (RELIABLE KEEP_LAST 50): stock's gets all 30 from its reader's
    history after the writer left, and so does a buffer-aware one: its channel is drained when
    the publisher goes, the frames' memory outlives the publisher, and no slot is reused while
    its descriptor is within the subscription's history (up to 27 wait there, within its
    share of the pool, half of 64 slots: past it, frames would go to it as CPU bytes)."""
    topic, count = f'/exit_{kind}_image', 30
    ours = kind == 'ours'
    with Run() as run:
        run.start('sub', 'image_subscriber', **_sub_params(
            topic, count, depth=50, work_sec=0.2, legacy=not ours,
            **({'acceptable_buffer_backends': 'demo', 'expected_backend': 'demo'}
               if ours else {})))
        run.start('pub', 'image_publisher', **_pub_params(
            topic, count, depth=50, rate_hz=30.0, linger_sec=0.5, legacy=not ours,
            **({'backend': 'demo', 'wait_for_buffer_peers': 1} if ours else {})))
        assert run.wait(['pub', 'sub'], 60), run.diagnostics()
        report = run.nodes['sub'].report
    # (a text: pytest shows it whole, where it cuts a tuple's repr at 240 characters)
    assert report['distinct'] == report['received'] == count, \
        f'{report}\n{run.diagnostics()}'
    assert report['checksum_failures'] == report['gaps'] == 0, report
    if ours:
        assert report['statistics']['rejected'] == 0, report['statistics']  # none went stale
        assert report['backends'] == {'demo': count}, report  # every one zero-copy


def test_beside_a_legacy_listener_served_subscriptions_take_no_main_topic_copies():
    """A demo publisher, a demo subscription and a plain raw one, and a second demo
    subscription that comes and goes meanwhile. The plain subscription gets every frame intact,
    as the canonical CDR bytes (but for alignment padding, as from stock rclpy); the demo ones,
    each served on its channel once it settled, take no main-topic copy from then on (the
    publisher keeps those samples from them), and none loses or repeats a frame while channels
    come and go. A route that a loaded machine brings up by its settle time alone (its probes
    not acknowledged in time) serves unconfirmed for a while, and the main topic's copies of
    those messages reach its subscription too: the publisher counts them
    (``main_topic_doubled``), and only those are allowed beyond the one message both routes
    carry when the channel takes over.

    Every subscription keeps the last 100 (2 s at 50 Hz): with 10, a subscriber process that a
    loaded machine stalls for 200 ms loses frames to its history, stock rclpy's the same way
    (a late joiner stalled for 0.5 s during its bring-up: 15 frames missing mid-stream, legacy
    and demo alike; none with 100), and the loss would not be the routes'."""
    topic = '/withheld_image'
    count = 400  # 8 s at 50 Hz
    depth = 100  # at most MAX_PROBE_DEPTH: the late route's bring-up still probes
    with Run() as run:
        run.start('demo', 'image_subscriber', **_sub_params(
            topic, count, acceptable_buffer_backends='demo', depth=depth))
        run.start('plain', 'image_subscriber', **_sub_params(
            topic, count, legacy=True, raw=True, depth=depth))
        run.start('pub', 'image_publisher', **_pub_params(
            topic, count, backend='demo', wait_for_subscribers=2, wait_for_buffer_peers=1,
            linger_sec=2.0))
        time.sleep(3.0)  # the publisher is publishing
        run.start('late', 'image_subscriber', topic=topic, expected_count=0, timeout_sec=2.5,
                  acceptable_buffer_backends='demo', depth=depth)
        assert run.wait(['demo', 'plain', 'late', 'pub'], 90), run.diagnostics()
        reports = {label: run.nodes[label].report for label in ('demo', 'plain', 'late', 'pub')}
    for label in ('demo', 'plain'):
        report = reports[label]
        assert report['distinct'] == report['received'] == count, (label, report)
        assert report['gaps'] == report['checksum_failures'] == 0, (label, report)
        assert not report['problems'], (label, report)  # plain: canonical CDR bytes
    late = reports['late']
    assert late['distinct'] == late['received'] == \
        late['last_frame'] - late['first_frame'] + 1 > 20, late  # contiguous, once each
    assert late['checksum_failures'] == 0, late
    published = reports['pub']['statistics']
    doubled = published['main_topic_doubled']  # copies to unconfirmed routes (docstring)
    for label in ('demo', 'late'):
        report, stats = reports[label], reports[label]['statistics']
        # every sample taken is delivered or dropped as a duplicate: at most the one message
        # both routes carried when the channel took over, and the copies counted as doubled
        assert stats['from_main_topic'] + stats['from_channels'] == \
            stats['delivered'] + stats['duplicates_dropped'], (label, stats)
        assert stats['delivered'] == report['received'] and \
            stats['duplicates_dropped'] <= 1 + doubled, (label, stats, doubled)
        # main-topic samples: only those from before the channel took over, none after it
        assert stats['from_main_topic'] <= report['backends'].get('cpu', 0) + 1 + doubled and \
            report['backends'].get('cpu', 0) < 50, (label, report, doubled)
    assert published['sent_on_main_topic'] == count, published  # the plain listener's copies
    assert published['main_topic_withheld'] >= count - 50, published
    assert doubled < 50, published  # unconfirmed routes: a bring-up's while, no more


def test_second_participant_reads_user_data_and_stock_typehash(context):
    """Another DDS participant reads BUFBE from discovery; stock rmw still has the typehash."""
    topic = '/user_data_image'
    with Run() as run:
        run.start('pub', 'image_publisher', **_pub_params(
            topic, 1, backend='demo', wait_for_subscribers=1, wait_timeout_sec=20.0,
            linger_sec=0.0))
        node = rclpy.create_node('observer', context=context)
        _native.install_discovery(node)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        seen = {}

        def advertised():
            for event in _dds.drain_discovery_events(node):
                if event.topic == 'rt' + topic and event.kind == 'writer':
                    seen[event.gid] = event.user_data
            return any(advertisement.decode(u) for u in seen.values())

        assert spin_until(executor, advertised), seen
        user_data = next(u for u in seen.values() if advertisement.decode(u))
        assert user_data.startswith(b'typehash=RIHS01_')
        assert b';\0BUFBE:cpu=;demo=mfd1.' in user_data
        assert set(advertisement.decode(user_data)) == {'cpu', 'demo'}
        infos = node.get_publishers_info_by_topic(topic)
        assert infos and infos[0].topic_type_hash.version == 1, infos  # parsed by stock rmw
        run.stop_all()
        node.destroy_node()


@pytest.mark.parametrize('publishers, subscriptions', [(1, 1), (1, 2), (2, 2)])
@pytest.mark.parametrize('backend, accept, expected', [
    ('demo', 'any', 'demo'), ('demo', 'cpu', 'cpu'), ('cpu', 'any', 'cpu')])
def test_in_process(context, publishers, subscriptions, backend, accept, expected):
    """Publishers and subscriptions in one process (one participant), multi-threaded executor."""
    frames = 20
    pub_node = rclpy.create_node('inproc_pub', context=context)
    sub_node = rclpy.create_node('inproc_sub', context=context)
    received = {name: [] for name in range(subscriptions)}
    group = rclpy.callback_groups.ReentrantCallbackGroup()

    def on_image(name):
        def callback(msg, info):
            check = check_frame(msg)
            assert check.ok, check
            assert 'source_timestamp' in info
            received[name].append((check.counter, getattr(msg.data, 'backend_type', 'cpu')))
        return callback

    subs = [rosidl_buffer_py.create_subscription(
        sub_node, Image, '/inproc_image', on_image(name), RELIABLE, callback_group=group,
        acceptable_buffer_backends=accept) for name in received]
    pubs = [rosidl_buffer_py.create_publisher(pub_node, Image, '/inproc_image', RELIABLE)
            for _ in range(publishers)]
    executor = MultiThreadedExecutor(num_threads=2, context=context)
    executor.add_node(pub_node)
    executor.add_node(sub_node)
    assert spin_until(executor, lambda: all(sum(
        1 for p in pub.buffer_peers() if p['channel_serving']) == subscriptions for pub in pubs))
    for index, pub in enumerate(pubs):
        for counter in range(index * frames, (index + 1) * frames):
            pub.publish(frame(counter, backend))
            executor.spin_once(timeout_sec=0.01)
    total = frames * publishers
    assert spin_until(executor, lambda: all(len(r) >= total for r in received.values())), (
        {name: sorted(set(range(total)) - {c for c, _ in got}) for name, got in received.items()},
        [s.statistics() for s in subs], [p.statistics() for p in pubs])
    executor.spin_once(timeout_sec=0.2)
    for name, got in received.items():
        assert sorted(c for c, _ in got) == list(range(total)), (name, got)  # exactly once
        assert {b for _, b in got} == {expected}, (name, got)
    assert all(s.statistics()['rejected'] == 0 for s in subs)
    executor.shutdown()
    pub_node.destroy_node()
    sub_node.destroy_node()


def test_publishing_from_the_first_matched_instant_switches_each_route_once(context,
                                                                            monkeypatch):
    """Publishers that start at the first matched instant (main topic) bring their channels up
    while publishing: each subscription gets one route fence per publisher, and every message
    exactly once. A channel that started serving in a publish's re-check was once taken off
    again (the main-topic message of that same publish counted as its last), and the
    subscription, which drops main-topic copies from the fence's message on, lost the
    messages of the second switch (CI's equivalence scenario reliable_pub_first_matched_ours).
    Here channels serve by their acknowledged probes only (no settle time) and routes are
    re-checked on every publish: the conditions of that race, every time."""
    monkeypatch.setattr(routes, 'CHANNEL_SETTLE_SECONDS', 60.0)
    monkeypatch.setattr(routes, 'RECHECK_SECONDS', 0.0)
    frames, topic = 30, '/first_matched_image'
    node = rclpy.create_node('first_matched', context=context)
    accepts = ('cpu', 'demo', 'any')
    received = {accept: [] for accept in accepts}
    subs = [rosidl_buffer_py.create_subscription(
        node, Image, topic, lambda m, a=accept: received[a].append(check_frame(m).counter),
        RELIABLE, acceptable_buffer_backends=accept) for accept in accepts]
    pubs = {backend: rosidl_buffer_py.create_publisher(node, Image, topic, RELIABLE)
            for backend in ('cpu', 'demo')}
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: all(
        p.get_subscription_count() == len(subs) for p in pubs.values()))
    for counter in range(frames):
        for index, (backend, pub) in enumerate(pubs.items()):
            pub.publish(frame(index * frames + counter, backend))
        deadline = time.monotonic() + 0.02  # 50 Hz, the executor spinning meanwhile
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.005)
    expected = list(range(frames * len(pubs)))
    assert spin_until(executor, lambda: all(len(r) >= len(expected)
                                            for r in received.values())), (
        {a: sorted(set(expected) - set(r)) for a, r in received.items()},
        [s.statistics() for s in subs])
    executor.spin_once(timeout_sec=0.2)
    for accept, got in received.items():
        assert sorted(got) == expected, (accept, got)  # exactly once
    for sub in subs:
        stats = sub.statistics()
        assert stats['fences'] == len(pubs) and stats['fence_timeouts'] == 0, stats
    node.destroy_node()


def test_a_plain_subscriber_joining_a_settled_topic_is_written_to_from_its_match_on(context):
    """The publisher reads its matched counts from DDS only after discovery moved (the
    process's discovery epoch), or every RECHECK_SECONDS. While its one subscription is served
    on a channel it writes no main-topic copy; once its main DataWriter matched a plain
    subscription of another participant that joined long after the routes settled, every
    publish writes the main topic: a cached signature never withholds a message from it.

    What such a late joiner then receives, against the same graph of stock endpoints, is the
    equivalence scenarios' (``transient_local_early_ours``: VOLATILE plain and buffer-aware
    late joiners beside subscriptions served on channels, in processes of their own). Here the
    late joiner was once another participant of this process and the test compared its
    messages with stock's: in one full CI run stock's own reader missed the 30 messages owed
    to it, in another it matched (its matched event came) and received nothing at all in
    20 s, so that comparison measured Fast DDS between two participants of one loaded
    process, not this publisher. Without the epoch re-read (the signature trusted until
    RECHECK_SECONDS), this test fails: the first publishes after the match write no copy."""
    from rosidl_buffer_py.publisher import EPOCH_GRACE_SECONDS
    topic = f'/epoch_image_{time.monotonic_ns()}'  # a failed run's endpoints cannot leak
    other = rclpy.Context()
    rclpy.init(context=other)
    node = legacy_node = None
    try:
        node = rclpy.create_node('epoch_pub', context=context)
        rosidl_buffer_py.create_subscription(node, Image, topic, lambda m: None, RELIABLE)
        pub = rosidl_buffer_py.create_publisher(node, Image, topic, RELIABLE)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        assert spin_until(executor, lambda: any(p['channel_serving'] for p in pub.buffer_peers()))
        counter, quiet_until = 0, time.monotonic() + EPOCH_GRACE_SECONDS + 1.0
        while time.monotonic() < quiet_until:  # past the grace: the signature is trusted
            pub.publish(frame(counter, 'cpu'))
            counter += 1
            executor.spin_once(timeout_sec=0.02)
        assert pub.statistics()['sent_on_main_topic'] == 0  # the channel serves the only one
        legacy_node = rclpy.create_node('epoch_legacy', context=other)
        legacy_node.create_subscription(Image, topic, lambda m: None, RELIABLE)
        other_executor = SingleThreadedExecutor(context=other)
        other_executor.add_node(legacy_node)
        written, deadline = [], time.monotonic() + 20.0
        while len(written) < 30 and time.monotonic() < deadline:
            matched = pub.get_subscription_count() == 2  # DDS's own count, read directly
            before = pub.statistics()['sent_on_main_topic']
            pub.publish(frame(counter, 'cpu'))
            counter += 1
            if matched:  # stock's writer sends this one to the plain subscription
                written.append(pub.statistics()['sent_on_main_topic'] - before)
            executor.spin_once(timeout_sec=0.002)
            other_executor.spin_once(timeout_sec=0.002)
        assert len(written) == 30, (written, pub.statistics())
        assert written == [1] * 30, (written, pub.statistics())
        executor.shutdown()
        other_executor.shutdown()
    finally:
        for created in (legacy_node, node):
            if created is not None:
                created.destroy_node()
        rclpy.try_shutdown(context=other)


def test_cpu_routes_follow_legacy_subscribers_coming_and_going(context):
    """publish() writes to the routes its last call found and re-checks them after the write:
    a legacy subscriber that matched meanwhile still gets every later message, exactly once."""
    node = rclpy.create_node('routes', context=context)
    got, legacy_got = [], []
    sub = rosidl_buffer_py.create_subscription(
        node, Image, '/routes_image', lambda m: got.append(check_frame(m).counter), RELIABLE)
    pub = rosidl_buffer_py.create_publisher(node, Image, '/routes_image', RELIABLE)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: any(p['channel_serving'] for p in pub.buffer_peers()))
    for counter in range(5):
        pub.publish(frame(counter, 'cpu'))
    assert spin_until(executor, lambda: len(got) == 5)
    assert pub.statistics()['sent_on_main_topic'] == 0  # the channel serves the only subscriber
    legacy = node.create_subscription(
        Image, '/routes_image', lambda m: legacy_got.append(check_frame(m).counter), RELIABLE)
    assert spin_until(executor, lambda: pub.get_subscription_count() == 2)
    for counter in range(5, 10):  # the first one goes to the stale routes, then the re-check
        pub.publish(frame(counter, 'cpu'))
    assert spin_until(executor, lambda: len(got) >= 10 and len(legacy_got) >= 5)
    node.destroy_subscription(legacy)
    assert spin_until(executor, lambda: pub.get_subscription_count() == 1)
    for counter in range(10, 15):
        pub.publish(frame(counter, 'cpu'))
    assert spin_until(executor, lambda: len(got) >= 15)
    executor.spin_once(timeout_sec=0.2)
    assert legacy_got == list(range(5, 10))
    assert sorted(got) == list(range(15)), got  # exactly once
    stats = sub.statistics()
    assert stats['rejected'] == 0 and stats['from_channels'] == 15, stats
    assert stats['from_main_topic'] == 0, stats  # the publisher kept the legacy copies from it
    published = pub.statistics()
    assert published['sent_on_main_topic'] in (5, 6), published  # 6: one stale
    assert published['main_topic_withheld'] == published['sent_on_main_topic'], published
    assert published['main_topic_doubled'] == 0, published  # its route was confirmed
    node.destroy_node()


def test_main_topic_copies_to_an_unconfirmed_route_are_counted_and_dropped(context):
    """A BEST_EFFORT channel acknowledges nothing: its route serves by its settle time and is
    never confirmed, so beside a plain subscription the main topic's copies reach the
    buffer-aware subscription too. It delivers each message once (the copies are dropped
    untaken) and the publisher counts every such copy."""
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    node = rclpy.create_node('doubled', context=context)
    got, plain_got = [], []
    sub = rosidl_buffer_py.create_subscription(
        node, Image, '/doubled_image', lambda m: got.append(check_frame(m).counter), qos)
    node.create_subscription(
        Image, '/doubled_image', lambda m: plain_got.append(check_frame(m).counter), qos)
    pub = rosidl_buffer_py.create_publisher(node, Image, '/doubled_image', qos)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: pub.get_subscription_count() == 2 and any(
        p['channel_serving'] for p in pub.buffer_peers()))
    for counter in range(10):
        pub.publish(frame(counter, 'cpu'))
        executor.spin_once(timeout_sec=0.01)
    assert spin_until(executor, lambda: len(got) >= 10 and len(plain_got) >= 10)
    executor.spin_once(timeout_sec=0.2)
    assert sorted(got) == list(range(10)) and sorted(plain_got) == list(range(10)), (
        got, plain_got)
    published, stats = pub.statistics(), sub.statistics()
    assert [p['route_state'] for p in pub.buffer_peers()] == ['serving'], pub.buffer_peers()
    assert published['main_topic_withheld'] == 0, published
    assert published['main_topic_doubled'] == published['sent_on_main_topic'] == 10, published
    assert stats['from_channels'] == 10 and stats['delivered'] == 10, stats
    assert stats['duplicates_dropped'] == stats['from_main_topic'] <= 10, stats
    node.destroy_node()


def test_an_endpoint_without_buffer_aware_peers_never_wakes_its_executor(context):
    """Beside legacy endpoints only, ours create no timer (a stock endpoint wakes nothing);
    the first buffer-aware peer brings the unmatched-channel check."""
    node = rclpy.create_node('no_timer', context=context)
    sub = rosidl_buffer_py.create_subscription(node, Image, '/no_timer', lambda m: None,
                                               RELIABLE)
    plain = node.create_publisher(Image, '/no_timer', RELIABLE)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: sub.get_publisher_count() == 1)
    assert not sub._peers.reannouncer.timer.running and not list(node.timers), list(node.timers)
    pub = rosidl_buffer_py.create_publisher(node, Image, '/no_timer', RELIABLE)
    assert spin_until(executor, lambda: sub._peers.reannouncer.timer.running)
    node.destroy_publisher(plain)
    node.destroy_publisher(pub)
    node.destroy_node()


def test_reannounce_timer_retires_while_every_channel_is_matched(context):
    """The once-a-second check for unmatched channels stops once all are matched (an idle
    executor wake-up costs CPU) and a new peer re-arms it; delivery goes on meanwhile. Once
    every route serves, the node has no timer left, as with stock endpoints: rclpy's executor
    waits on cancelled timers too, paying for each on every wake-up, a message's included."""
    node = rclpy.create_node('retire', context=context)
    got = []
    pub = rosidl_buffer_py.create_publisher(node, Image, '/retire_image', RELIABLE)
    sub = rosidl_buffer_py.create_subscription(
        node, Image, '/retire_image', lambda m: got.append(check_frame(m).counter), RELIABLE)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: any(p['channel_serving'] for p in pub.buffer_peers()))
    for endpoint in (pub, sub):  # the first tick after the match retires each one's timer
        assert spin_until(executor, lambda: not endpoint._peers.reannouncer.timer.running)
        # no publish-time discovery polling
        assert endpoint._peers.reannouncer.spinning(time.monotonic())
    got_second = []
    rosidl_buffer_py.create_subscription(
        node, Image, '/retire_image', lambda m: got_second.append(check_frame(m).counter),
        RELIABLE)
    assert spin_until(executor, lambda: len(pub.buffer_peers()) == 2)
    assert pub._peers.reannouncer.timer.running  # re-armed for the new channel
    assert spin_until(executor, lambda: not pub._peers.reannouncer.timer.running)
    assert all(p['channel_matched'] for p in pub.buffer_peers())
    for counter in range(3):
        pub.publish(frame(counter, 'cpu'))
    assert spin_until(executor, lambda: len(got) == len(got_second) == 3), (got, got_second)
    assert spin_until(executor, lambda: not list(node.timers)), list(node.timers)
    node.destroy_node()


def test_destroy_node_removes_channels_and_destroy_is_idempotent(context):
    node = rclpy.create_node('destroy_me', context=context)
    observer = rclpy.create_node('observer2', context=context)
    sub = rosidl_buffer_py.create_subscription(node, Image, '/destroy_image', lambda m: None,
                                               10, acceptable_buffer_backends='demo')
    pub = rosidl_buffer_py.create_publisher(node, Image, '/destroy_image', 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(observer)

    def channel_topics():
        return [name for name, _ in observer.get_topic_names_and_types(no_demangle=True)
                if '/_buf/' in name]

    # Each side opens its end of the channel when it discovers the other: the topic shows
    # in the graph once the first did, the second may not have yet.
    assert spin_until(executor, lambda: len(channel_topics()) == 1
                      and pub.buffer_peers() and sub.buffer_peers()), channel_topics()
    # diagnostics name each peer's node (from the ROS graph)
    assert spin_until(executor, lambda: pub.buffer_peers()[0]['node'] == '/destroy_me')
    assert sub.buffer_peers()[0]['node'] == '/destroy_me'
    name = channel_topics()[0]
    assert name == (f'rt/destroy_image/_buf/{pub.statistics()["gid"]}_'
                    f'{sub.statistics()["gid"]}')
    node.destroy_node()
    assert spin_until(executor, lambda: not channel_topics()), channel_topics()
    assert pub.buffer_peers() == [] and sub.buffer_peers() == []
    observer.destroy_node()


def test_malformed_descriptors_are_rejected_counted_and_survived(context, capfd):
    """A rogue plain publisher sends descriptor bytes; the subscription rejects them and lives.
    Jazzy's C type support prints a line to stderr for data it cannot deserialize: once for
    this publisher, whose later samples go to the codec (which rejects them silently)."""
    node = rclpy.create_node('rogue', context=context)
    good = []
    sub = rosidl_buffer_py.create_subscription(node, Image, '/rogue_image', good.append, 20,
                                               acceptable_buffer_backends='any')
    rogue = node.create_publisher(Image, '/rogue_image', 20)  # depths that hold the burst
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: rogue.get_subscription_count() == 1)
    bad = [codec.encode(frame(0), ('demo', b'\x00' * 10)),             # garbage descriptor
           codec.encode(frame(1), ('nosuch', b'x')),                   # unknown backend
           codec.encode(frame(2))[:40],                                # truncated
           b'\x00\x07\x00\x00' + bytes(60)]                             # bad encapsulation
    for _ in range(3):
        for raw in bad:
            rogue.publish(bytes(raw))
    rogue.publish(bytes(codec.encode(frame(3))))
    assert spin_until(executor, lambda: len(good) == 1)
    executor.spin_once(timeout_sec=0.2)
    assert check_frame(good[0]).counter == 3 and isinstance(good[0].data, array.array)
    assert sub.statistics()['rejected'] == 3 * len(bad)
    err = capfd.readouterr().err
    assert err.count('sequence size exceeds remaining buffer') <= 1, err
    node.destroy_node()


def test_other_rmw_falls_back_to_plain_rclpy(context, monkeypatch, capfd):
    """Under another rmw the wrappers are plain rclpy pub/sub on the main topic, one warning."""
    monkeypatch.setattr(rclpy, 'get_rmw_implementation_identifier', lambda: 'rmw_other_cpp')
    monkeypatch.setattr(_dds, '_warned_rmw', set())
    node = rclpy.create_node('fallback', context=context)
    got = []
    sub = rosidl_buffer_py.create_subscription(node, Image, '/fallback_image', got.append, 10,
                                               acceptable_buffer_backends='any')
    pub = rosidl_buffer_py.create_publisher(node, Image, '/fallback_image', 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: pub.get_subscription_count() == 1)
    pub.publish(frame(5))
    assert spin_until(executor, lambda: got)
    assert check_frame(got[0]).ok and isinstance(got[0].data, array.array)
    assert not sub.statistics()['buffer_aware']
    err = capfd.readouterr().err
    assert err.count('rmw_other_cpp is not supported by rosidl_buffer_py') == 1, err
    node.destroy_node()


def test_a_rogue_writer_on_a_channel_is_rejected(context):
    """Any participant can create a writer on a channel's topic; the subscription accepts
    channel data only from the discovered publisher's participant, rejects and counts the
    rest, and keeps delivering the real publisher's messages."""
    node = rclpy.create_node('victim', context=context)
    got = []
    pub = rosidl_buffer_py.create_publisher(node, Image, '/rogue_image', RELIABLE)
    sub = rosidl_buffer_py.create_subscription(
        node, Image, '/rogue_image', lambda m: got.append(check_frame(m).counter), RELIABLE,
        acceptable_buffer_backends='any')
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: any(p['channel_serving'] for p in pub.buffer_peers()))
    channel = sub.buffer_peers()[0]['channel_topic']
    rogue_context = rclpy.Context()
    rclpy.init(context=rogue_context)
    try:
        rogue_node = rclpy.create_node('rogue', context=rogue_context)
        rogue = _dds.create_channel_publisher(rogue_node, Image, channel, RELIABLE)
        assert spin_until(executor, lambda: rogue.matched_count() == 1)
        for counter in range(100, 105):
            rogue.publish(codec.encode(frame(counter)), time.time_ns())
        for counter in range(3):
            pub.publish(frame(counter, 'demo'))
        assert spin_until(executor, lambda: len(got) == 3 and sub.statistics()['rejected'] == 5)
        assert got == [0, 1, 2]
        rogue.destroy()
        rogue_node.destroy_node()
    finally:
        rclpy.try_shutdown(context=rogue_context)
    node.destroy_node()


@pytest.mark.parametrize('kind', ['stock', 'ours'])
def test_serialized_publishing_while_routes_come_up_reaches_every_subscription(context, kind):
    """publish(serialized bytes) from the first matched instant, while buffer-aware
    subscriptions' routes come up (probes, fences): every subscription gets every message, as
    from a stock publisher (a fence used to need a message object and raised for bytes)."""
    from rclpy.serialization import serialize_message
    node = rclpy.create_node(f'serialized_{kind}', context=context)
    topic = f'/serialized_{kind}'
    got = {accept: [] for accept in ('cpu', 'demo', 'plain')}
    for accept in ('cpu', 'demo'):
        rosidl_buffer_py.create_subscription(
            node, Image, topic, lambda m, a=accept: got[a].append(check_frame(m).counter),
            RELIABLE, acceptable_buffer_backends=accept)
    node.create_subscription(Image, topic, lambda m: got['plain'].append(check_frame(m).counter),
                             RELIABLE)
    pub = (node.create_publisher(Image, topic, RELIABLE) if kind == 'stock' else
           rosidl_buffer_py.create_publisher(node, Image, topic, RELIABLE))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: pub.get_subscription_count() == 3)
    for counter in range(40):
        pub.publish(serialize_message(frame(counter)))
        executor.spin_once(timeout_sec=0.01)
    assert spin_until(executor, lambda: all(len(g) >= 40 for g in got.values())), (
        {a: sorted(set(range(40)) - set(g)) for a, g in got.items()},
        [s.statistics() for s in node.subscriptions if hasattr(s, 'statistics')])
    assert all(g == list(range(40)) for g in got.values()), got
    node.destroy_node()


@pytest.mark.parametrize('kind', ['stock', 'ours'])
def test_a_raising_callback_leaves_spin_once_and_the_next_spin_delivers_the_next_message(
        context, kind):
    """As with rclpy: the exception of a subscription callback comes out of spin_once, and the
    subscription goes on with the next message at the next spin (it used to stall)."""
    node = rclpy.create_node(f'raising_{kind}', context=context)
    topic = f'/raising_{kind}'
    got = []

    def callback(msg):
        got.append(check_frame(msg).counter)
        if len(got) == 2:
            raise RuntimeError('user callback failed')

    if kind == 'stock':
        node.create_subscription(Image, topic, callback, RELIABLE)
    else:
        rosidl_buffer_py.create_subscription(node, Image, topic, callback, RELIABLE,
                                             acceptable_buffer_backends='demo')
    pub = rosidl_buffer_py.create_publisher(node, Image, topic, RELIABLE)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: kind == 'stock' or any(
        p['channel_serving'] for p in pub.buffer_peers()))
    for counter in range(5):
        pub.publish(frame(counter, 'demo'))
    raised = 0
    deadline = time.monotonic() + 10.0
    while len(got) < 5 and time.monotonic() < deadline:
        try:
            executor.spin_once(timeout_sec=0.05)
        except RuntimeError as exc:
            assert 'user callback failed' in str(exc)
            raised += 1
    assert raised == 1 and got == [0, 1, 2, 3, 4], (raised, got)
    node.destroy_node()


def test_a_quiet_publishers_channel_costs_no_take_per_message_of_another(context, monkeypatch):
    """Two buffer-aware publishers of a topic, one of them silent: the subscription takes
    from the busy one's channel only (a take per message), never from the silent one's; what
    lands on a channel announces itself through its guard condition. The silent one then
    publishes: its message is taken too."""
    from rosidl_buffer_py import subscription
    takes = {}
    take = subscription._PublisherPeer.take

    def counting(peer, reading):
        taken = take(peer, reading)
        key = peer.info.gid
        takes[key] = takes.get(key, 0) + 1
        return taken

    monkeypatch.setattr(subscription._PublisherPeer, 'take', counting)
    node = rclpy.create_node('quiet_channel', context=context)
    busy = rosidl_buffer_py.create_publisher(node, Image, '/quiet_channel', RELIABLE)
    quiet = rosidl_buffer_py.create_publisher(node, Image, '/quiet_channel', RELIABLE)
    got = []
    rosidl_buffer_py.create_subscription(
        node, Image, '/quiet_channel', lambda m: got.append(check_frame(m).counter), RELIABLE,
        acceptable_buffer_backends='any')
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    assert spin_until(executor, lambda: all(
        any(p['channel_serving'] for p in pub.buffer_peers()) for pub in (busy, quiet)))
    executor.spin_once(timeout_sec=0.2)  # what bring-up left on the channels
    takes.clear()
    for counter in range(20):
        busy.publish(frame(counter, 'demo'))
        assert spin_until(executor, lambda: len(got) == counter + 1)
    quiet_gid, busy_gid = (_dds.endpoint_gid(p, 'publisher') for p in (quiet, busy))
    assert takes.get(quiet_gid, 0) == 0, takes
    assert 20 <= takes[busy_gid] <= 22, takes  # an over-counted announcement: one empty take
    quiet.publish(frame(20, 'demo'))
    assert spin_until(executor, lambda: got[-1:] == [20])
    assert takes[quiet_gid] >= 1
    node.destroy_node()


def _demo_publisher(context, name: str, topic: str):
    """A buffer-aware Image publisher on its own node, and an executor that spins that node."""
    node = rclpy.create_node(name, context=context)
    pub = rosidl_buffer_py.create_publisher(node, Image, topic, RELIABLE)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    return node, pub, executor


def test_a_camera_that_publishes_at_once_takes_its_lane_once_its_node_is_known_to_spin(
        context):
    """A camera that publishes as soon as its subscriber is served (``wait_for_buffer_peers``)
    meets the route table's steady answer before its node is known to spin (the
    re-announcer's retirement, which the lane needs). A re-plan keeps that answer, the same
    object: the lane is tried for it once the node is known to spin, not given up for good at
    the first message (every message then took the full path)."""
    topic = '/camera_lane'
    node, pub, executor = _demo_publisher(context, 'camera_lane_pub', topic)
    count = 60
    with Run() as run:
        run.start('sub', 'image_subscriber', **_sub_params(
            topic, count, acceptable_buffer_backends='demo', depth=100))
        assert pub.wait_for_buffer_peers(1, timeout_sec=30.0), run.diagnostics()
        next_at = time.monotonic()
        for counter in range(count):
            next_at += 1 / 30
            pub.publish(frame(counter, 'demo'))
            executor.spin_once(timeout_sec=max(0.0, next_at - time.monotonic()))
        assert run.wait(['sub'], 60), run.diagnostics()
        report = run.nodes['sub'].report
    stats = pub.statistics()
    assert stats.published_on_lane > 0, stats
    assert report['distinct'] == report['received'] == count, report
    assert report['backends'].get('demo', 0) > 0, report
    node.destroy_node()


def test_a_steady_publisher_writes_through_its_lane_and_transitions_lose_nothing(context):
    """Once its routes are steady, publish() writes the descriptors it prepared for the
    table's steady dispatch (``Publisher._publish_steady``); a new subscriber (another
    process), a subscriber of its own process (whose descriptors the lane's describer
    declines: the full path serves it) and the subscriber's exit each change the routes, and
    every subscriber gets every frame once, in order, zero-copy where its share of the pool
    allows. The subscription of its own process, with one channel, takes its descriptor
    messages through ``Subscription._steady_step``, which delivers them opened by the demo
    backend's steady opener (``statistics().delivered_steady``). (Its readers keep 100 samples: once this
    process's subscription gets each frame, ``spin_once`` returns at once and the frames go
    out back to back, a burst that overflows KEEP_LAST 10 readers; stock endpoints in this
    graph lose frames in 6 runs of 8.)"""
    topic = '/lane_image'
    node, pub, executor = _demo_publisher(context, 'lane_pub', topic)
    counter = 0

    def publish(count: int, pause: float = 0.0) -> None:
        nonlocal counter
        for _ in range(count):
            pub.publish(frame(counter, 'demo'))
            counter += 1
            executor.spin_once(timeout_sec=0.02)
            time.sleep(pause)

    def serving(count: int) -> bool:
        peers = pub.buffer_peers()
        if len(peers) != count or not all(p['channel_serving'] for p in peers) or \
                pub._peers.reannouncer.timer.running:
            return False
        # discovery's grace: the routes' view reads DDS on every message for a while
        settle_until = time.monotonic() + publisher.EPOCH_GRACE_SECONDS + 0.2
        while time.monotonic() < settle_until:
            executor.spin_once(timeout_sec=0.05)
        return True

    with Run() as run:
        run.start('first', 'image_subscriber', **_sub_params(
            topic, 60, acceptable_buffer_backends='demo', depth=100))
        assert spin_until(executor, lambda: serving(1), timeout=30.0), run.diagnostics()
        # the route confirms (its channel samples acknowledged, the main-topic copies end),
        # and the first message under that plan prepares the lane
        while pub.statistics().published_on_lane == 0 and counter < 10:
            publish(1)
        on_lane, left, started = pub.statistics().published_on_lane, 20 - counter, time.monotonic()
        assert on_lane == 1, pub.statistics()
        publish(left, pause=1.5 / left)
        assert time.monotonic() - started > 2 * routes.RECHECK_SECONDS
        # the periodic re-plans keep the table's steady answer, and their messages the lane
        assert pub.statistics().published_on_lane == on_lane + left, pub.statistics()
        run.start('second', 'image_subscriber', **_sub_params(
            topic, 40, acceptable_buffer_backends='demo', depth=100))
        assert spin_until(executor, lambda: serving(2), timeout=30.0), run.diagnostics()
        assert pub._lane is None or pub._lane.dispatch is not pub._table.steady
        mine = []
        own = rosidl_buffer_py.create_subscription(
            node, Image, topic, lambda m: mine.append(check_frame(m).counter), RELIABLE,
            acceptable_buffer_backends='demo')
        assert spin_until(executor, lambda: serving(3), timeout=30.0), run.diagnostics()
        first_mine, on_lane = counter, pub.statistics().published_on_lane
        publish(40 - (counter - 20))
        assert pub.statistics().published_on_lane > on_lane, pub.statistics()
        assert run.wait(['first', 'second'], 60), run.diagnostics()
        reports = {label: run.nodes[label].report for label in ('first', 'second')}
    publish(3)  # its peers gone: the lane goes, the own-process subscriber still gets all
    assert spin_until(executor, lambda: mine == list(range(first_mine, counter))), mine
    stats = own.statistics()  # its one channel's descriptor messages, taken and opened there
    assert 0 < stats.delivered_steady <= stats.from_channels, stats
    for label, report in reports.items():
        count = 60 if label == 'first' else 40  # (the second's first frame is the 21st)
        assert report['distinct'] == report['received'] == count, (label, report)
        assert report['duplicates'] == 0 and report['gaps'] == 60 - count, report
        assert report['backends'].get('demo', 0) > 0, report
    node.destroy_node()
