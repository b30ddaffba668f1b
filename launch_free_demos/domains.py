"""ROS_DOMAIN_IDs that no other test run or demo on this machine uses at the same time.

A domain id is held through an flock on ``/tmp/rosidl_buffer_py_domain_<id>.lock`` for as long
as this process lives; the test session (test/conftest.py) and the equivalence suite, which
runs the stock and the buffer-aware variant of a scenario side by side, take theirs here.
"""
import contextlib
import fcntl
import os
import random
from typing import Iterator, List

LOCK_DIR = '/tmp'
#: The ids handed out (Fast DDS maps an id to UDP ports 7400 + 250 x id: up to 232 are valid).
DOMAIN_IDS = range(1, 201)
_held: list = []  # the lock files, open until the interpreter exits


def claim_domain_ids(count: int = 1) -> List[int]:
    """``count`` domain ids nobody else holds, held until this process exits."""
    ids = list(DOMAIN_IDS)
    random.shuffle(ids)
    claimed = []
    for domain_id in ids:
        f = open(os.path.join(LOCK_DIR, f'rosidl_buffer_py_domain_{domain_id}.lock'), 'w')
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        _held.append(f)
        claimed.append(domain_id)
        if len(claimed) == count:
            return claimed
    raise RuntimeError(f'only {len(claimed)} free ROS_DOMAIN_IDs in {DOMAIN_IDS}, '
                       f'{count} wanted (that many concurrent test runs?)')


@contextlib.contextmanager
def fresh_domain() -> Iterator[int]:
    """A domain id nobody else holds, as ``ROS_DOMAIN_ID`` of the processes started in the
    block (their graph alone in it: no participant of this process, no process of an earlier
    graph), released with the Fast DDS files its SIGKILLed processes left."""
    import time
    from launch_free_demos.runner import remove_fastdds_leftovers
    since = time.time() - 1.0
    domain_id = claim_domain_ids()[0]
    handle = _held.pop()
    previous = os.environ.get('ROS_DOMAIN_ID')
    os.environ['ROS_DOMAIN_ID'] = str(domain_id)
    try:
        yield domain_id
    finally:
        if previous is None:
            del os.environ['ROS_DOMAIN_ID']
        else:
            os.environ['ROS_DOMAIN_ID'] = previous
        remove_fastdds_leftovers(since, domain_id)
        handle.close()  # the flock goes with it
