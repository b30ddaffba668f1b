"""Presence files: how a publisher learns, within a fraction of a second, that a subscriber
process it sends descriptors to has died (SIGKILL included), long before DDS says so.

Every process that advertises the demo backend holds, for as long as its backend lives, an
exclusive OFD lock on ``shm.OWNER_BYTE`` of its own small presence file
``/dev/shm/rbpy_demo_live_<pid>_<16 hex>`` (mode 0600, holding ``shm.PRESENCE_MAGIC``). The
``<pid>_<16 hex>`` part is the process's *token*, advertised after the shm domain in the backend
metadata. The kernel drops the lock when the process dies; :func:`alive` tests it with
``F_OFD_GETLK`` from another open file description. The file is removed at normal exit (pool
shutdown), by whoever finds it dead, and by the scavenging of segments (same prefix, same owner
byte, magic written after the lock).

The 64 random bits of the token (:func:`token_id`) also identify the process in the takers
table of every segment it takes from (see :mod:`.shm`).
"""
import errno
import os
import re
import secrets
import time
from typing import Dict, Optional, Tuple

from demo_buffer_backend import locks, shm

#: ``rbpy_demo_live_<pid>_<16 hex>``; never matches ``shm.NAME_PATTERN`` (segments).
PREFIX = shm.PREFIX + 'live_'
TOKEN_PATTERN = re.compile(r'^([1-9][0-9]{0,9})_([0-9a-f]{16})$')

_OPEN_FLAGS = os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC


def new_token() -> str:
    while True:
        random_part = secrets.token_hex(8)
        if int(random_part, 16):  # 0 marks an empty entry of the takers table
            return f'{os.getpid()}_{random_part}'


def parse_token(text: str) -> Optional[str]:
    """``text`` when it is a well-formed token (it comes from the network), else None."""
    return text if isinstance(text, str) and TOKEN_PATTERN.match(text) else None


def token_id(token: str) -> int:
    return int(token[-16:], 16)


def path_of(token: str) -> str:
    return shm.path_of(PREFIX + token)


class Presence:
    """This process's presence file, locked until :meth:`close`."""

    def __init__(self, token: str) -> None:
        self.token = token
        self.path = path_of(token)
        for attempt in range(2):
            try:
                self.fd = os.open(self.path, _OPEN_FLAGS | os.O_CREAT | os.O_EXCL, 0o600)
                break
            except FileExistsError:
                if attempt:
                    raise
                # Ours from before a pool shutdown that could not remove it, or a dead
                # namesake's (pid reuse with the same 64 random bits: never in practice).
                if alive(token):
                    raise
                try:
                    os.unlink(self.path)
                except FileNotFoundError:
                    pass
        try:
            os.fchmod(self.fd, 0o600)  # whatever the umask
            if not locks.try_lock(self.fd, shm.OWNER_BYTE, exclusive=True):
                raise OSError(errno.EBUSY, f'cannot lock presence file {self.path}')
            os.pwrite(self.fd, shm.PRESENCE_MAGIC, 0)  # after the lock: see shm.scavenge
        except BaseException:
            self.close(remove=True)
            raise

    def close(self, *, remove: bool) -> None:
        """Drop the lock (close the fd) and, with ``remove``, unlink the file first."""
        fd, self.fd = self.fd, -1
        if fd < 0:
            return
        if remove:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
        os.close(fd)


def alive(token: str) -> bool:
    """Whether the process of ``token`` is a live peer of our shm domain: it still holds the
    lock of a presence file that looks as this backend creates them (three syscalls).

    Missing file: gone (it exists before its token is ever advertised, and is removed only at
    shutdown or once found dead). A file of another uid, a symlink, or one with a mode other than
    0600: a process that claims our shm domain but cannot open our segments (another local user
    advertising our metadata), which is no live peer either. When in doubt (a file being created,
    an unexpected error) the answer is True, which only keeps the protection of the bytes. A dead
    one's file is removed here.
    """
    return _test(token, keep=False)[0]


class Watch:
    """Presence files of peers found alive, kept open: testing one again is a single fcntl
    (``F_OFD_GETLK``) on the open file, where :func:`alive` opens, checks, reads and closes it.
    The kernel drops the owner's lock when it dies, whether or not the file is still linked, so
    an unlocked file means gone; its token is then tested afresh by :func:`alive` (a pool
    restarted after a shutdown locks a new file under the same token)."""

    def __init__(self) -> None:
        self._fds: Dict[str, int] = {}

    def alive(self, token: str) -> bool:
        fd = self._fds.get(token)
        if fd is not None:
            try:
                if locks.is_locked_by_other(fd, shm.OWNER_BYTE):
                    return True
            except OSError:
                pass
            self.forget(token)
        answer, kept = _test(token, keep=True)
        if kept is not None:
            self._fds[token] = kept
        return answer

    def forget(self, token: Optional[str]) -> None:
        """Close ``token``'s file, if kept (its peer went away, or the watch is closing)."""
        fd = self._fds.pop(token, None)
        if fd is not None:
            os.close(fd)

    def keep_only(self, tokens) -> None:
        """Close the files of tokens not in ``tokens``."""
        for token in [t for t in self._fds if t not in tokens]:
            self.forget(token)

    def close(self) -> None:
        self.keep_only(())


def _test(token: str, keep: bool) -> Tuple[bool, Optional[int]]:
    """:func:`alive`'s answer and, with ``keep`` and a live, finished presence file, its open fd
    (the caller closes it)."""
    path = path_of(token)
    try:
        fd = os.open(path, _OPEN_FLAGS)
    except FileNotFoundError:
        return False, None
    except OSError as exc:
        if exc.errno in (errno.EACCES, errno.EPERM, errno.ELOOP):
            return False, None  # not ours (another uid, or a symlink): a peer that cannot reach us
        return True, None
    kept = None
    try:
        st = os.fstat(fd)
        if shm.untrusted(st):
            return False, None
        finished = os.pread(fd, len(shm.PRESENCE_MAGIC), 0) == shm.PRESENCE_MAGIC
        if locks.is_locked_by_other(fd, shm.OWNER_BYTE):
            if keep and finished:
                kept = fd
            return True, kept
        if not finished and time.time() - st.st_mtime < shm.UNFINISHED_SEGMENT_AGE:
            return True, None  # being created
        try:  # dead: scavenge it now (unless the name was just taken by a new file)
            if os.stat(path, follow_symlinks=False).st_ino == st.st_ino:
                os.unlink(path)
        except OSError:
            pass
        return False, None
    except OSError:
        return True, None
    finally:
        if kept is None:
            os.close(fd)
