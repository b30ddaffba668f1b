"""The process's one :class:`~.pool.Pool`: made on first use, closed at exit or on
:func:`shutdown` (and made anew on the next use), forgotten in a forked child.

The token that names this process (in its backend metadata, which endpoints keep) is the same
for its whole life, across pool shutdowns; a forked child gets its own.
"""
import atexit
import os
import threading
from typing import NamedTuple, Optional

from demo_buffer_backend import handover
from demo_buffer_backend.pool import Pool


class _Token(NamedTuple):
    pid: int
    token: str


_pool: Optional[Pool] = None
_pool_lock = threading.Lock()
_atexit_registered = False
_token: Optional[_Token] = None


def own_token() -> str:
    """This process's token, ``<pid>_<16 hex>``."""
    global _token
    token = _token
    if token is None or token.pid != os.getpid():
        token = _token = _Token(os.getpid(), handover.new_token())
    return token.token


def get_pool() -> Pool:
    """The process-wide pool (created on first use, and anew after :func:`shutdown`)."""
    global _pool, _atexit_registered
    pool = _pool
    if pool is not None and pool.pid == os.getpid():
        return pool
    with _pool_lock:
        if _pool is None or _pool.pid != os.getpid():
            _pool = Pool(own_token())
            if not _atexit_registered:
                _atexit_registered = True
                atexit.register(_shutdown_at_exit)
        return _pool


def shutdown() -> None:
    """Close every segment, link and listener of this process (also done at exit).

    The backend stays usable: the next use starts afresh (with the same token).
    """
    global _pool
    with _pool_lock:
        pool, _pool = _pool, None
    if pool is not None and pool.pid == os.getpid():
        pool.shutdown()


def stats() -> dict:
    """Counters and gauges of this process's demo backend (see the package docstring)."""
    return get_pool().stats()


def _shutdown_at_exit() -> None:
    try:
        shutdown()
    except Exception:  # pragma: no cover - never fail the interpreter's exit
        pass


def _after_fork_in_child() -> None:
    global _pool, _pool_lock
    _pool_lock = threading.Lock()
    pool, _pool = _pool, None
    if pool is not None:
        pool.forget_after_fork()


os.register_at_fork(after_in_child=_after_fork_in_child)
