"""The process's one :class:`~.pool.Pool` per medium: made on first use, closed at exit or on
``shutdown()`` (and made anew on the next use), forgotten in a forked child.

The token that names this process (in its backend metadata, which endpoints keep) is the same
for its whole life, across pool shutdowns; a forked child gets its own. Each medium has its own
token and listener (:class:`Keeper`); the module-level functions are the demo backend's.
"""
import atexit
import os
import threading
from typing import Any, NamedTuple, Optional

from demo_buffer_backend import handover, memory
from demo_buffer_backend.pool import Pool


class _Token(NamedTuple):
    pid: int
    token: str


class Keeper:
    """The pool of one medium in this process."""

    def __init__(self, medium: Any) -> None:
        self.medium = medium
        self._pool: Optional[Pool] = None
        self._lock = threading.Lock()
        self._atexit_registered = False
        self._token: Optional[_Token] = None
        os.register_at_fork(after_in_child=self._after_fork_in_child)

    def own_token(self) -> str:
        """This process's token for the medium, ``<pid>_<16 hex>``."""
        token = self._token
        if token is None or token.pid != os.getpid():
            token = self._token = _Token(os.getpid(), handover.new_token())
        return token.token

    def get_pool(self) -> Pool:
        """The process-wide pool (created on first use, and anew after :meth:`shutdown`).

        Every describe and every open asks for it: a forked child forgets the parent's pool
        in its at-fork hook, so a pool found here is this process's and no ``getpid()``
        system call is made (one per call before: two per publish, one per take)."""
        pool = self._pool
        if pool is not None:
            return pool
        with self._lock:
            if self._pool is None or self._pool.pid != os.getpid():
                self._pool = Pool(self.own_token(), self.medium)
                if not self._atexit_registered:
                    self._atexit_registered = True
                    atexit.register(self._shutdown_at_exit)
            return self._pool

    def shutdown(self) -> None:
        """Close every segment, link and listener of the medium in this process (also done at
        exit). The backend stays usable: the next use starts afresh (with the same token)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None and pool.pid == os.getpid():
            pool.shutdown()

    def _shutdown_at_exit(self) -> None:
        try:
            self.shutdown()
        except Exception:  # pragma: no cover - never fail the interpreter's exit
            pass

    def _after_fork_in_child(self) -> None:
        self._lock = threading.Lock()
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.forget_after_fork()


#: The demo backend's pool: payloads in sealed shared memory.
_demo = Keeper(memory.SharedMemory)


def own_token() -> str:
    """This process's token, ``<pid>_<16 hex>``."""
    return _demo.own_token()


#: ``get_pool() -> Pool``: the process-wide pool (created on first use, and anew after
#: :func:`shutdown`). The Keeper's method itself: every message calls it, and a wrapper would
#: be one more Python frame each time.
get_pool = _demo.get_pool


def shutdown() -> None:
    """Close every segment, link and listener of this process (also done at exit).

    The backend stays usable: the next use starts afresh (with the same token).
    """
    _demo.shutdown()


def stats() -> dict:
    """Counters and gauges of this process's demo backend (see the package docstring)."""
    return get_pool().stats()
