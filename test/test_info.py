"""buffer_topic_info against real node processes over Fast DDS.

A demo image_publisher, an image_subscriber accepting demo and a legacy subscriber run with the
process runner; the inspector must list all three with their nodes and full GIDs, mark the legacy
one, show the demo backend's metadata of the buffer-aware pair and the channel between them.
The inspector's default wait must suffice on the first try: every endpoint, with its node name
and advertisement (it keeps listening while node names or channel sides are missing).
"""
import json
import os
import re
import subprocess
import time

from harness.installed import executable
from harness.scenarios import SMALL
from launch_free_demos.runner import Run

INFO = executable('buffer_topic_info')
HEX32 = re.compile(r'^[0-9a-f]{32}$')


def _info(*args):
    process = subprocess.run([str(INFO), *args], capture_output=True, text=True, timeout=120)
    return process.returncode, process.stdout, process.stderr


def _inspect(topic, *extra):
    """One run of the inspector at its default wait (JSON)."""
    code, out, err = _info(topic, '--json', *extra)
    assert code == 0, err
    return json.loads(out)


def _wait_until_served(run, label, timeout=60.0):
    """Until the publisher's subscriber sees frames from the demo backend (the graph is up)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any("'demo'" in line and 'received' in line for line in run.nodes[label].stderr):
            return
        time.sleep(0.1)
    raise AssertionError(run.diagnostics())


def test_lists_endpoints_backends_and_channels():
    topic = '/info_image'
    with Run() as run:
        run.start('cam', 'image_publisher', topic=topic, backend='demo', rate_hz=10.0, count=0,
                  wait_for_subscribers=2, wait_for_buffer_peers=1, wait_timeout_sec=60.0,
                  **SMALL)
        run.start('viewer', 'image_subscriber', topic=topic, acceptable_buffer_backends='demo',
                  timeout_sec=0.0, report_period_sec=0.2)
        run.start('recorder', 'legacy_image_subscriber', topic=topic, timeout_sec=0.0)
        _wait_until_served(run, 'viewer')
        result = _inspect(topic)
        probed = _inspect(topic, '--probe')
        code, text, err = _info(topic)
        short = _inspect(topic, '--wait', '0.2')
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
            assert aware['backends']['demo'].startswith('mfd1.'), aware  # the demo metadata
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
    # a short --wait says what it may have missed
    assert _short_wait_note(short) == ['listened 0.2 s, less than a Fast DDS announcement period '
                                       '(3 s): endpoints of processes not discovered yet may be '
                                       'missing, as may their node names and advertisements']
    assert code == 0, err
    assert 'Publisher count: 1 (1 buffer-aware' in text, text
    assert 'Subscription count: 2 (1 buffer-aware, 1 legacy' in text, text
    assert 'Transport: legacy' in text and 'Transport: buffer-aware' in text, text
    assert f"GID: {cam['gid']}" in text, text


def test_no_endpoints_is_an_error():
    code, out, err = _info('/nobody_here', '--wait', '0.5')
    assert code == 1 and out == ''
    assert err == 'buffer_topic_info: no publishers or subscriptions on /nobody_here (listened ' \
        'for 0.5 s; a shorter --wait than 3 s may miss running ones)\n', err


def _short_wait_note(found):
    return [note for note in found['notes'] if note.startswith('listened 0.2 s, less than')]


def test_json_output_is_only_json_when_native_code_writes_to_stdout():
    """Fast DDS logs through std::cout (``RTPS_TRANSPORT_SHM Error Failed init_port ...`` when a
    shared-memory port is busy or stale, as on a machine where tests SIGKILL nodes): a line
    there once broke a script's ``json.loads`` of the inspector's output (CI, the inspector
    measurement). Native writes to file descriptor 1 go to stderr; the JSON alone to stdout."""
    import sys
    code = (
        'import os, sys\n'
        'from rosidl_buffer_py.tools import info\n'
        'def inspect(node, topic, wait, probe, tapped):\n'
        '    os.write(1, b"RTPS_TRANSPORT_SHM Error Failed init_port (as Fast DDS)\\n")\n'
        '    return {"topic": topic, "endpoints": [{"node_name": "n"}], "channels": [],\n'
        '            "notes": []}\n'
        'info.inspect_topic = inspect\n'
        'sys.exit(info.main(["buffer_topic_info", "/t", "--json"]))\n')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=60, env=dict(os.environ))
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)['topic'] == '/t', done.stdout
    assert 'Failed init_port' in done.stderr, done.stderr
