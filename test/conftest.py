"""Test-wide isolation: a DDS domain of our own, localhost discovery, nothing left in /dev/shm.

Each pytest run takes a ROS_DOMAIN_ID nobody else on the machine holds (an flock'ed file per
domain id), so parallel runs never see each other's traffic. Child processes inherit it.

Every test runs directly in the ``./dev`` venv (``./dev test``, or ``pytest test/x.py`` with
that venv's interpreter); test_colcon.py builds the package with colcon and runs a few test
files inside ``colcon test`` against the install space, as a ROS user runs them.
"""
import os
import signal
import sys
import time
from pathlib import Path

import pytest

# Under `colcon test` pytest runs in the source tree, whose rosidl_buffer_py/ has no compiled
# extension (colcon built it into the install space): let the installed package be imported.
_ROOT = Path(__file__).resolve().parent.parent
# The processes tests start (`python -m ...` from the source tree, scripts in test/harness)
# must import the installed package too: PYTHONSAFEPATH keeps their working directory and
# script directory off sys.path (harness scripts add test/ themselves).
if not list((_ROOT / 'rosidl_buffer_py').glob('_native*.so')):
    sys.path[:] = [p for p in sys.path if Path(p or '.').resolve() != _ROOT]
    os.environ['PYTHONSAFEPATH'] = '1'
# launch_free_demos (the demo, the benchmarks, the process runner) is not installed: this
# process and the ones tests start find it in the checkout's root, put last on sys.path and on
# PYTHONPATH. Under colcon the install space comes earlier on PYTHONPATH and wins; in the ./dev
# venv the package under test is this checkout anyway (an editable install).
if _ROOT not in {Path(p or '.').resolve() for p in sys.path}:
    sys.path.append(str(_ROOT))
_PYTHONPATH = [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]
if str(_ROOT) not in _PYTHONPATH:
    os.environ['PYTHONPATH'] = os.pathsep.join(_PYTHONPATH + [str(_ROOT)])

from launch_free_demos.domains import claim_domain_ids  # noqa: E402 (after the path fix)

# A shell starts a background job (`cmd &` without job control) with SIGINT ignored, and an
# ignored signal stays ignored in every process started below it: the nodes the Ctrl-C tests
# interrupt would then not see Ctrl-C at all. A handler (not an ignore) is reset to the default
# by exec, so the processes tests start get Ctrl-C as a terminal would give it.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

os.environ['ROS_DOMAIN_ID'] = str(claim_domain_ids()[0])
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ['RMW_IMPLEMENTATION'] = 'rmw_fastrtps_cpp'

#: Prefixes of everything this project creates in /dev/shm.
SHM_PREFIXES = ('rbpy_',)


def _our_shm_files():
    return {n for n in os.listdir('/dev/shm') if n.startswith(SHM_PREFIXES)}


def _owner_alive(name: str) -> bool:
    """Files are named <prefix>_<owner pid>_<hex>; a live owner (another test run on this
    machine) has not leaked its file yet."""
    digits = [part for part in name.split('_') if part.isdigit()]
    if not digits or int(digits[0]) == os.getpid():
        return False
    try:
        os.kill(int(digits[0]), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@pytest.fixture
def context():
    """A private rclpy context (its own DDS participant) for in-process tests."""
    import rclpy
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture(scope='session')
def extra_domain_ids():
    """Two more domain ids of this run's own (same flock scheme as its ROS_DOMAIN_ID), for
    tests that run graphs side by side, one per domain; Fast DDS files that their SIGKILLed
    processes leave are removed at the end, as for the main domain."""
    since = time.time() - 1.0
    ids = claim_domain_ids(2)
    yield ids
    from launch_free_demos.runner import remove_fastdds_leftovers
    for domain_id in ids:
        remove_fastdds_leftovers(since, domain_id)


@pytest.fixture(scope='session', autouse=True)
def no_shm_leftovers():
    """Fail the session if it leaves files of ours in /dev/shm.

    The test process's own demo backend is shut down first, as at interpreter exit. Files of
    processes that are still alive belong to another run on this machine and are not counted.
    """
    before = _our_shm_files()
    yield
    import sys
    if 'demo_buffer_backend' in sys.modules:
        sys.modules['demo_buffer_backend'].shutdown()
    left = {n for n in _our_shm_files() - before if not _owner_alive(n)}
    assert not left, f'tests left files in /dev/shm: {sorted(left)}'


@pytest.fixture(scope='session', autouse=True)
def no_fastdds_leftovers():
    """Remove the Fast DDS files of the participants our tests SIGKILLed (deliberately, or when
    a node did not stop), so that a test run leaves nothing in /dev/shm."""
    since = time.time() - 1.0  # mtimes have coarse clocks on some filesystems
    yield
    from launch_free_demos.runner import remove_fastdds_leftovers
    remove_fastdds_leftovers(since, int(os.environ['ROS_DOMAIN_ID']))
