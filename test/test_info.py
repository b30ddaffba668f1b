"""buffer_topic_info against real node processes over Fast DDS.

A demo image_publisher, an image_subscriber accepting demo and a legacy subscriber run with the
process runner; the inspector must list all three with their nodes and full GIDs, mark the legacy
one, show the demo backend's metadata of the buffer-aware pair and the channel between them.
DDS discovery takes a variable time on a loaded machine, so the inspector is re-run (a bounded
number of times) until it has seen all three.
"""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

from launch_free_demos.runner import Run
from launch_free_demos.scenarios import SMALL

INFO = Path(sys.prefix) / 'lib' / 'rosidl_buffer_py' / 'buffer_topic_info'
HEX32 = re.compile(r'^[0-9a-f]{32}$')


def _info(*args):
    process = subprocess.run([str(INFO), *args], capture_output=True, text=True, timeout=120)
    return process.returncode, process.stdout, process.stderr


def _inspect_until_complete(topic, *extra, attempts=6):
    result = None
    for _ in range(attempts):
        code, out, err = _info(topic, '--json', '--wait', '4', *extra)
        if code == 0:
            result = json.loads(out)
            aware = [e for e in result['endpoints'] if e['advertisement'] == 'seen']
            named = [e for e in result['endpoints'] if not (e['node_name'] or '_').startswith('_')]
            if len(aware) == len(named) == 3 and result['channels'] and all(
                    c['writer'] and c['reader'] for c in result['channels']):
                return result
    return result


def test_lists_endpoints_backends_and_channels():
    topic = '/info_image'
    with Run() as run:
        run.start('cam', 'image_publisher', topic=topic, backend='demo', rate_hz=10.0, count=0,
                  wait_for_subscribers=2, wait_for_buffer_peers=1, wait_timeout_sec=60.0,
                  **SMALL)
        run.start('viewer', 'image_subscriber', topic=topic, acceptable_buffer_backends='demo',
                  timeout_sec=0.0)
        run.start('recorder', 'legacy_image_subscriber', topic=topic, timeout_sec=0.0)
        result = _inspect_until_complete(topic)
        probed = _inspect_until_complete(topic, '--probe')
        for _ in range(6):  # the text form, re-run like the JSON one until all three are seen
            code, text, err = _info(topic)
            if code == 0 and 'Publisher count: 1 (1 buffer-aware' in text and \
                    'Subscription count: 2 (1 buffer-aware, 1 legacy' in text:
                break
        alive = {label: node.process.poll() for label, node in run.nodes.items()}
    for node in run.nodes.values():  # stopped with SIGINT by the runner: nothing left
        pid = node.process.pid
        assert not [n for n in os.listdir('/dev/shm') if n.startswith('rbpy_') and
                    f'_{pid}_' in n], (node.label, node.process.returncode)
    assert result is not None, run.diagnostics()
    assert alive == {'cam': None, 'viewer': None, 'recorder': None}, run.diagnostics()
    for found in (result, probed):
        assert found['topic'] == topic and found['types'] == ['sensor_msgs/msg/Image']
        by_node = {e['node_name']: e for e in found['endpoints']}
        assert set(by_node) == {'cam', 'viewer', 'recorder'}, found
        cam, viewer, recorder = by_node['cam'], by_node['viewer'], by_node['recorder']
        assert cam['kind'] == 'publisher' and viewer['kind'] == recorder['kind'] == 'subscription'
        assert all(HEX32.match(e['gid']) for e in found['endpoints']), found
        assert recorder['legacy'] is True and recorder['buffer_aware'] is False
        assert recorder['backends'] is None and recorder['channels'] == []
        for aware in (cam, viewer):
            assert aware['buffer_aware'] is True and aware['legacy'] is False, aware
            assert aware['backends']['demo'].startswith('shm1.'), aware  # the demo metadata
        assert set(cam['backends']) == {'cpu', 'demo'}  # publishers also list cpu
        assert found['publisher_count'] == 1 and found['subscription_count'] == 2
        # exactly one channel, from the demo publisher to the buffer-aware subscriber
        assert len(found['channels']) == 1, found['channels']
        channel = found['channels'][0]
        assert channel['publisher_gid'] == cam['gid']
        assert channel['subscription_gid'] == viewer['gid']
        assert channel['dds_topic'] == f"rt{topic}/_buf/{cam['gid']}_{viewer['gid']}"
        assert cam['channels'] == viewer['channels'] == [channel['dds_topic']]
        assert found['notes'] == [], found['notes']
    assert code == 0, err
    assert 'Transport: legacy' in text and 'Transport: buffer-aware' in text, text
    assert f"GID: {cam['gid']}" in text, text


def test_no_endpoints_is_an_error():
    code, out, err = _info('/nobody_here', '--wait', '0.5')
    assert code == 1 and out == ''
    assert 'no publishers or subscriptions on /nobody_here' in err and 'Traceback' not in err
