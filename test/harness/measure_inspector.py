"""How often buffer_topic_info sees the whole graph on the first try (not a test: a measurement).

Starts a demo image_publisher, a buffer-aware image_subscriber and a legacy subscriber, waits
until frames flow, then runs the inspector N times (extra arguments go to it) and prints one line
per run and the count of complete views: all three endpoints with their node names and
advertisements, and the channel.

    .venv/bin/python test/harness/measure_inspector.py 20
    .venv/bin/python test/harness/measure_inspector.py 10 --wait 1
"""
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

if __package__ in (None, ''):  # run as a file: harness is a package of test/, and
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    # launch_free_demos (not installed) is the checkout's, after the installed packages
    sys.path.append(str(Path(__file__).resolve().parents[2]))

from harness.installed import executable  # noqa: E402 (after the path fix)
from harness.scenarios import SMALL  # noqa: E402
from launch_free_demos.runner import Run  # noqa: E402

#: How long the nodes may take until the viewer reports demo frames.
STARTUP_SECONDS = 60.0


def main(argv) -> int:
    runs, extra = int(argv[0]), argv[1:]
    # SIGTERM (a timeout's) takes Ctrl-C's path: the nodes and probes it started are reaped
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(101, 200)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    topic = '/measure_inspector'
    complete = 0
    with Run() as run:
        run.start('cam', 'image_publisher', topic=topic, backend='demo', rate_hz=10.0, count=0,
                  wait_for_subscribers=2, wait_for_buffer_peers=1, wait_timeout_sec=60.0,
                  **SMALL)
        run.start('viewer', 'image_subscriber', topic=topic, acceptable_buffer_backends='demo',
                  timeout_sec=0.0, report_period_sec=0.2)
        run.start('recorder', 'legacy_image_subscriber', topic=topic, timeout_sec=0.0)
        deadline = time.monotonic() + STARTUP_SECONDS
        while not any("'demo'" in line for line in run.nodes['viewer'].stderr):
            gone = [name for name, node in run.nodes.items() if node.process.poll() is not None]
            if gone or time.monotonic() > deadline:
                print(f'no demo frames at the viewer after {STARTUP_SECONDS} s' if not gone
                      else f'{", ".join(gone)} exited before frames flowed', file=sys.stderr)
                return 1
            time.sleep(0.1)
        for i in range(runs):
            started = time.monotonic()
            done = subprocess.run([str(executable('buffer_topic_info')), topic, '--json', *extra],
                                  capture_output=True, text=True, timeout=60)
            seconds = time.monotonic() - started
            if done.returncode != 0:
                print(f'{i}: exit {done.returncode}: {done.stderr.strip()}')
                continue
            result = json.loads(done.stdout)
            names = sorted(e['node_name'] or '?' for e in result['endpoints'])
            seen = [e['advertisement'] for e in result['endpoints']]
            ok = (names == ['cam', 'recorder', 'viewer'] and seen == ['seen'] * 3 and
                  len(result['channels']) == 1)
            complete += ok
            print(f"{i}: {seconds:.1f} s {'complete' if ok else 'INCOMPLETE'} {names} "
                  f"{result['notes']}", flush=True)
    print(f'complete on the first try: {complete} of {runs}')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
