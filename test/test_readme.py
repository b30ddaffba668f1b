"""Every command README.md shows is run: here, by another named test, or by CI itself.

A command added to README without a place in COVERAGE fails the first test, so the README
cannot rot silently.
"""
import json
import os
import re
import shlex
import signal
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / 'README.md').read_text()

#: README command -> where it runs: 'here' (below), a test file that runs it, or 'ci'.
COVERAGE = {
    './dev demo': 'here',
    './dev demo --help': 'here',
    './dev test': 'ci',                                   # .ci/run runs exactly this
    './dev bench': 'here',
    './dev bench-transport': 'here',                      # with fewer frames and payloads
    './dev benchmark --quick': 'test_benchmark.py',
    './dev benchmark': 'test_benchmark.py',  # full mode: the quick mode's code, more sizes (12 min)
    './dev setup': 'here',
    '.venv/bin/python -m launch_free_demos.scenarios': 'test_transport.py',  # every scenario
    '.venv/bin/python -m launch_free_demos.equivalence [names] [--echo]': 'test_equivalence.py',
    '.venv/lib/rosidl_buffer_py/image_publisher --ros-args -p backend:=demo -p width:=1920 '
    '-p height:=1080': 'here',
    'buffer_topic_info <topic> [--json] [--wait S] [--probe]': 'test_info.py',
    'colcon build': 'test_colcon.py',
    'colcon test --packages-select rosidl_buffer_py': 'test_colcon.py',
    'colcon test-result --verbose': 'test_colcon.py',
    # the recording example, run as one script
    '.venv/lib/rosidl_buffer_py/image_publisher --ros-args -p backend:=demo -p '
    'topic:=/camera/image -p count:=90 -p wait_for_subscribers:=1 &': 'test_record.py',
    '.venv/lib/rosidl_buffer_py/buffer_record /camera/image -o camera_bag --duration 10':
        'test_record.py',
    '.venv/lib/rosidl_buffer_py/buffer_bag_info camera_bag': 'test_record.py',
    '.venv/lib/rosidl_buffer_py/buffer_play camera_bag --rate 2': 'test_record.py',
    'wait': 'test_record.py',
    './dev bench-record': 'test_record.py',               # 1 s of small frames
}


def readme_commands():
    commands = set()
    for block in re.findall(r'```bash\n(.*?)```', README, re.S):
        for line in block.splitlines():
            line = line.split('#', 1)[0].strip()
            if line:
                commands.add(line)
    for inline in re.findall(r'`([^`\n]+)`', README):
        inline = inline.strip()
        if inline.startswith(('./dev ', '.venv/', 'buffer_topic_info', 'colcon ')) and \
                ' ' in inline:  # a path alone is not a command
            commands.add(inline)
    return commands


def run(command, timeout):
    return subprocess.run(command, shell=True, cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def test_every_readme_command_has_a_place_that_runs_it():
    missing = readme_commands() - set(COVERAGE)
    assert not missing, f'README commands no test runs: {sorted(missing)}'
    for command, where in COVERAGE.items():
        if where.endswith('.py'):
            assert (ROOT / 'test' / where).is_file(), (command, where)


def test_dev_setup_and_demo():
    assert run('./dev setup', 300).returncode == 0
    help_text = run('./dev demo --help', 60)
    assert help_text.returncode == 0 and '--backend' in help_text.stdout
    demo = run('./dev demo', 180)
    assert demo.returncode == 0, demo.stdout[-2000:] + demo.stderr[-2000:]
    assert "| backends seen by the subscriber | {'demo': 150} |" in demo.stdout
    assert '| duplicates / gaps / checksum failures | 0 / 0 / 0 |' in demo.stdout


def test_dev_bench_prints_the_table():
    bench = run('./dev bench', 300)
    assert bench.returncode == 0, bench.stderr[-2000:]
    assert '| 3840x2160 rgb8 | 24,883,200 |' in bench.stdout
    transport = run('./dev bench-transport --frames 5 --payloads "1 KiB"', 300)
    assert transport.returncode == 0, transport.stderr[-2000:]
    assert '| 1 KiB |' in transport.stdout


def test_readme_image_publisher_command_runs_and_stops_cleanly():
    command = [c for c in COVERAGE if c.startswith('.venv/lib/')][0]
    process = subprocess.Popen(shlex.split(command), cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        time.sleep(4.0)
        os.killpg(process.pid, signal.SIGINT)  # the shell and the node, as Ctrl-C would
        out, err = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == 0, err[-2000:]
    assert 'Traceback' not in err
    report = json.loads(next(line for line in out.splitlines()
                             if line.startswith('REPORT '))[len('REPORT '):])
    assert report['published'] > 0 and report['params']['backend'] == 'demo'


@pytest.mark.parametrize('name', ['demo_pub_to_legacy_sub'])
def test_scenarios_command_line(name):
    out = run(f'.venv/bin/python -m launch_free_demos.scenarios {name}', 120)
    assert out.returncode == 0, out.stdout + out.stderr[-2000:]
    assert f'| {name} | PASS |' in out.stdout
