"""The one lock of a process's demo backend, and the releases that must not wait for it.

Garbage collection drops a Buffer's pin or hold at any moment, possibly in a thread that holds
the lock already (a collection triggered inside the backend): its release is queued, never
waited for, and run by whoever holds the lock or next takes it.
"""
import threading
from typing import Any, Callable, List, Tuple

from demo_buffer_backend.diagnostics import logger

#: One queued release, ``(func, arg)``: ``func(arg)`` under the lock. A plain pair: every
#: message drops a pin or a hold, and a NamedTuple would cost 0.4 µs more each time.
Release = Tuple[Callable[[Any], None], Any]


class Guard:
    """``with guard:`` holds the lock, and runs the queued releases once it is let go."""

    __slots__ = ('lock', 'pending')

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.pending: List[Release] = []

    def __enter__(self) -> None:
        self.lock.acquire()

    def __exit__(self, *exc) -> None:
        self.lock.release()
        if self.pending:  # (a call saved on every message: nothing is queued, mostly)
            self.drain()

    def defer(self, func: Callable[[Any], None], arg: Any) -> None:
        """Run ``func(arg)`` under the lock, now if it is free, else when its holder lets go."""
        self.pending.append((func, arg))
        self.drain()

    def drain(self) -> None:
        """Run the queued releases if the lock is free (never waits for it)."""
        # Whoever appends tries the lock after appending; whoever holds the lock drains after
        # releasing it: one of the two always sees every entry.
        while self.pending:
            if not self.lock.acquire(blocking=False):
                return
            try:
                while self.pending:
                    func, arg = self.pending.pop()
                    try:
                        func(arg)
                    except Exception as exc:  # pragma: no cover - never lose the others
                        logger.error(f'demo backend release failed: {exc!r}')
            finally:
                self.lock.release()
