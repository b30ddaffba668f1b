"""Processes a test starts and waits for, which say where they hung if they do.

Each runs with ``PYTHONFAULTHANDLER``; one still running at the deadline gets SIGABRT, so its
faulthandler prints every thread's Python stack to its stderr, and the test fails with
:class:`Stuck`, carrying every process's last output. A rare hang then names its place the
first time it happens (a process exit that hangs once in hundreds cannot be caught by running
it again).
"""
import os
import signal
import subprocess
import time
from typing import List, Sequence, Tuple


class Stuck(AssertionError):
    """Processes were not done in time; the message holds what each printed last."""


def popen(command: Sequence[str], **kwargs) -> subprocess.Popen:
    """``subprocess.Popen`` with text pipes, a session of its own and faulthandler on."""
    env = dict(kwargs.pop('env', None) or os.environ, PYTHONFAULTHANDLER='1')
    return subprocess.Popen(list(command), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, env=env, **kwargs)


def communicate_all(processes: Sequence[subprocess.Popen],
                    timeout: float) -> List[Tuple[int, str, str]]:
    """Wait for every process, all within ``timeout`` seconds; their (code, out, err).

    :raises Stuck: Some process was still running at the deadline (each such one got SIGABRT
        first; every process's last output is in the message).
    """
    deadline = time.monotonic() + timeout
    results = []
    try:
        for process in processes:
            out, err = process.communicate(timeout=max(0.1, deadline - time.monotonic()))
            results.append((process.returncode, out, err))
    except subprocess.TimeoutExpired:
        raise Stuck(f'not done in {timeout} s:\n' + abort_and_report(processes)) from None
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.communicate()
    return results


def abort_and_report(processes: Sequence[subprocess.Popen]) -> str:
    """SIGABRT each process still running (its faulthandler prints its stacks); what every
    process printed last, with its exit status."""
    report = []
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGABRT)
        try:
            out, err = process.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            out, err = process.communicate()
        except ValueError:  # its pipes were read already
            out, err = '', ''
        report.append(f'--- {process.args} (exit {process.returncode}):\n'
                      f'{(out or "")[-1000:]}\n{(err or "")[-6000:]}')
    return '\n'.join(report)
