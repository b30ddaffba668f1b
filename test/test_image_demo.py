"""``./dev demo`` (launch_free_demos.image_demo) stops at once when a node fails, ends with the
publisher naming lost frames, validates its options; Ctrl-C
ends it with the summary so far, no traceback."""
import os
import signal
import subprocess
import sys
import time

DEMO = [sys.executable, '-m', 'launch_free_demos.image_demo']


def _start(*args):
    return subprocess.Popen([*DEMO, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


def _finish(process, timeout):
    try:
        return process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate()


def test_a_node_failing_at_start_up_stops_the_demo_at_once():
    for option, value, line in (
            ('--backend', 'foo', "image_publisher: parameter backend: 'foo' is not accepted; "
                                 'expected one of cpu, demo'),
            ('--encoding', 'bogus', "image_publisher: parameter encoding: 'bogus' is not "
                                    'accepted; expected mono8')):
        # without fail-fast the demo would wait for the subscriber's timeout (--seconds + 60 s)
        # and be killed at _finish's timeout
        process = _start(option, value, '--seconds', '30')
        out, err = _finish(process, 60)
        assert process.returncode == 1, out + err
        assert 'demo: demo_publisher (image_publisher) exited with status 2; its last error ' \
               'lines:' in err, err
        assert f'  {line}' in err and 'Traceback' not in err, err
        assert 'received' not in out, out  # stopped before the subscriber's first summary


def test_ctrl_c_stops_the_nodes_and_prints_the_summary_so_far():
    process = _start('--width', '64', '--height', '48', '--rate', '20', '--seconds', '60')
    try:
        deadline = time.monotonic() + 60
        for line in process.stdout:  # the subscriber's once-a-second summary
            if "backends {'demo'" in line or time.monotonic() > deadline:
                break
        os.kill(process.pid, signal.SIGINT)  # what Ctrl-C sends the demo
        rest, err = _finish(process, 60)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == 130, rest[-2000:] + err[-2000:]
    assert 'Traceback' not in err and 'KeyboardInterrupt' not in err, err
    assert 'demo: interrupted; the summary so far:' in rest, rest
    assert '| frames published |' in rest and '| frames received (distinct) |' in rest, rest
    published = int(rest.split('| frames published | ')[1].split(' ')[0])
    assert published > 0, rest


def test_lost_frames_end_the_demo_with_the_publisher_and_are_named():
    """A slow subscriber with --depth 1 loses frames: the demo ends a few seconds after the
    publisher (not at the subscriber's 60 s timeout), names the lost frames and says why."""
    started = time.monotonic()
    process = _start('--width', '64', '--height', '48', '--rate', '30', '--seconds', '1',
                     '--depth', '1', '--slow-subscriber', '0.1')
    out, err = _finish(process, 90)
    assert process.returncode == 1, out[-2000:] + err[-2000:]
    assert time.monotonic() - started < 40, 'the demo waited for the subscriber\'s timeout'
    assert 'frames published and never received: ' in out, out
    assert 'Likely why: a KEEP_LAST history of depth 1' in out
    assert '--slow-subscriber 0.1 s per frame' in out
    assert 'The table: frames the publisher sent' in out  # the legend under the table


def test_two_demos_in_one_domain_are_told_apart():
    """Two demos at once in one ROS domain: each subscriber matches both publishers and counts
    the other's frames (numbered from 0 too) as duplicates; each demo says so and how to run
    them apart, instead of an unexplained failure."""
    small = ('--width', '64', '--height', '48', '--rate', '10', '--seconds', '3')
    processes = [_start(*small), _start(*small)]
    outs = [_finish(process, 120) for process in processes]
    told = [out for out, _ in outs if 'demo: the subscriber matched 2 publishers on /demo/image'
            in out and 'ROS_DOMAIN_ID=<n> ./dev demo' in out]
    assert told, [out[-1500:] + err[-1500:] for out, err in outs]


def test_options_are_validated_and_help_is_plain():
    for option, value in (('--rate', '0'), ('--seconds', '-1'), ('--depth', '0'),
                          ('--width', 'x')):
        process = _start(option, value)
        out, err = _finish(process, 30)
        assert process.returncode == 2, (option, out, err)
        assert f'./dev demo: error: argument {option}:' in err and value in err, err
    process = _start('--help')
    out, err = _finish(process, 30)
    assert process.returncode == 0
    assert out.startswith('usage: ./dev demo') and '``' not in out, out
    assert 'The summary table:' in out
