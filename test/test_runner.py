"""The process runner's clean-up of Fast DDS shared-memory files left by SIGKILLed nodes."""
import fcntl
import os
import time

from launch_free_demos.runner import fastdds_files_of, fastdds_leftovers, remove_fastdds_leftovers


def _touch(name: str) -> str:
    path = os.path.join('/dev/shm', name)
    with open(path, 'wb'):
        pass
    return path


def test_files_of_dead_participants_are_removed_and_live_ones_kept():
    since = time.time() - 1.0
    dead = 'fastrtps_' + f'{os.getpid():016x}'
    live = 'fastrtps_' + f'{os.getpid() + 1:016x}'
    paths = [_touch(n) for n in (dead, dead + '_el', live, live + '_el')]
    holder = open(os.path.join('/dev/shm', live + '_el'), 'ab')
    try:
        fcntl.flock(holder, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a living owner holds its lock
        found = fastdds_leftovers(since, int(os.environ['ROS_DOMAIN_ID']))
        assert dead in found and dead + '_el' in found, found
        assert live not in found and live + '_el' not in found, found
        assert fastdds_leftovers(time.time() + 60, 0) == []  # only files made since `since`
        removed = remove_fastdds_leftovers(since, int(os.environ['ROS_DOMAIN_ID']))
        assert {dead, dead + '_el'} <= set(removed)
        assert not os.path.exists(paths[0]) and os.path.exists(paths[2])
    finally:
        holder.close()
        for path in paths:
            if os.path.exists(path):
                os.remove(path)


def test_files_of_a_process_are_told_apart_from_other_processes_leftovers():
    """fastdds_files_of names the segments a process holds (lock file and semaphore folded
    into their segment), and ``among`` keeps other processes' dead files out of the count."""
    import subprocess
    import sys
    since = time.time() - 1.0
    mine, theirs = (f'fastrtps_{os.getpid() + k:016x}' for k in (7, 8))
    paths = [_touch(n) for n in (mine, mine + '_el', theirs, theirs + '_el')]
    holder = subprocess.Popen(
        [sys.executable, '-c', 'import sys, time; f = open(sys.argv[1], "ab"); '
         'print(flush=True); time.sleep(30)', paths[1]], stdout=subprocess.PIPE)
    try:
        holder.stdout.readline()
        files = fastdds_files_of(holder.pid)
        assert files == {mine}, files
    finally:
        holder.kill()
        holder.wait()
    try:
        found = fastdds_leftovers(since, int(os.environ['ROS_DOMAIN_ID']), among=files)
        assert set(found) == {mine, mine + '_el'}, found
    finally:
        for path in paths:
            if os.path.exists(path):
                os.remove(path)
