"""Linux open-file-description (OFD) byte-range locks on shared-memory segment files.

OFD locks (``F_OFD_SETLK``/``F_OFD_SETLKW``/``F_OFD_GETLK``) belong to the open file description,
not to the process: two descriptions of the same file conflict even inside one process, closing an
unrelated descriptor of the file does not drop them (unlike classic POSIX locks), and the kernel
drops them when the last descriptor of the description is closed, which includes the death of the
process (SIGKILL included). Locks are advisory and live on file offsets, independent of the bytes
stored there.
"""
import errno
import fcntl
import os
import struct
import time

# struct flock on Linux: short l_type, short l_whence, off_t l_start, off_t l_len, pid_t l_pid
# (native alignment pads after l_whence and at the end). l_pid must be 0 for OFD locks.
_FLOCK = struct.Struct('hhqqi4x')

_F_OFD_GETLK = getattr(fcntl, 'F_OFD_GETLK', 36)
_F_OFD_SETLK = getattr(fcntl, 'F_OFD_SETLK', 37)


def _flock(lock_type: int, byte: int) -> bytes:
    return _FLOCK.pack(lock_type, os.SEEK_SET, byte, 1, 0)


def try_lock(fd: int, byte: int, *, exclusive: bool) -> bool:
    """Take a lock on one byte without waiting; False when another description holds a
    conflicting lock."""
    try:
        fcntl.fcntl(fd, _F_OFD_SETLK, _flock(fcntl.F_WRLCK if exclusive else fcntl.F_RDLCK, byte))
    except OSError as exc:
        if exc.errno in (errno.EAGAIN, errno.EACCES):
            return False
        raise
    return True


def lock_within(fd: int, byte: int, *, exclusive: bool, timeout: float) -> bool:
    """Take a lock on one byte, waiting at most ``timeout`` seconds for conflicting holders;
    False when it could not be had in time.

    Never ``F_OFD_SETLKW``: that waits without bound, and any process of the same user can hold
    the byte for as long as it likes. Polls with a short backoff instead (holders keep these
    locks for a few instructions; a dead holder's lock is dropped by the kernel).
    """
    if try_lock(fd, byte, exclusive=exclusive):
        return True
    deadline = time.monotonic() + timeout
    pause = 0.00005
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        time.sleep(min(pause, remaining))
        pause = min(pause * 2, 0.002)
        if try_lock(fd, byte, exclusive=exclusive):
            return True


def unlock(fd: int, byte: int) -> None:
    """Drop this description's lock on one byte (no error when it holds none)."""
    fcntl.fcntl(fd, _F_OFD_SETLK, _flock(fcntl.F_UNLCK, byte))


def is_locked_by_other(fd: int, byte: int) -> bool:
    """True when another open file description holds any lock on the byte."""
    result = fcntl.fcntl(fd, _F_OFD_GETLK, _flock(fcntl.F_WRLCK, byte))
    return _FLOCK.unpack(result)[0] != fcntl.F_UNLCK
