"""The inbox's thread: it accepts and screens connections and takes handovers as they arrive.

Without it a process would accept connections only when it opens a descriptor, and a listen
backlog filled by connections that send nothing would never clear: every publisher's connect
would then fail, and it would send CPU bytes. The thread sleeps in ``poll()`` on the listener,
the admitted connections (for records) and the waiting ones (for a hang-up), wakes at the
latest every ``limits.SWEEP_INTERVAL`` seconds (segments to close, waiting connections whose
time is up), and does its work under the pool's guard through one call, ``receive``.
"""
import os
import select
import threading
import time
from typing import Callable, Optional

from demo_buffer_backend import limits
from demo_buffer_backend.diagnostics import Diagnostics
from demo_buffer_backend.guard import Guard
from demo_buffer_backend.inbox import Inbox

#: Wake-ups with work in a row after which the thread pauses this long (seconds): a peer that
#: keeps its connections readable costs it a bounded share of a core, never all of one.
BUSY_WAKEUPS = 8
BUSY_PAUSE = 0.002


class Porter:
    """One daemon thread serving ``inbox``: ``receive()`` runs under ``guard`` whenever a
    watched descriptor is ready or a timer is due."""

    def __init__(self, guard: Guard, inbox: Inbox, receive: Callable[[], None],
                 diagnostics: Diagnostics) -> None:
        self.guard = guard
        self.inbox = inbox
        self.receive = receive
        self.diagnostics = diagnostics
        self.stopped = False
        self._wake_r, self._wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self._thread: Optional[threading.Thread] = threading.Thread(
            target=self._run, name='demo_buffer_backend inbox', daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Something the thread waits on changed (a publisher discovered, a shutdown)."""
        try:
            os.write(self._wake_w, b'x')
        except OSError:  # full: it is awake already; closed: it is stopped
            pass

    def stop(self) -> None:
        """Ask the thread to end (with the guard held); :meth:`join` waits for it."""
        self.stopped = True
        self.wake()

    def join(self, timeout: float = 5.0) -> None:
        """Wait for the thread to end, then close the wake-up pipe (without the guard held)."""
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
        if thread is None or not thread.is_alive():
            self._close_pipe()

    def forget_after_fork(self) -> None:
        """In a forked child (where the thread does not exist): close our copy of the pipe."""
        self.stopped = True
        self._thread = None
        self._close_pipe()

    def _close_pipe(self) -> None:
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._wake_r = self._wake_w = -1

    def _run(self) -> None:
        busy = 0
        while True:
            with self.guard:
                if self.stopped:
                    return
                watched, due = self.inbox.watched()
            timeout = limits.SWEEP_INTERVAL
            if due is not None:
                timeout = min(timeout, max(0.0, due - time.monotonic()) + 0.001)
            poller = select.poll()
            poller.register(self._wake_r, select.POLLIN)
            for fd, events in watched:
                poller.register(fd, events)
            try:
                ready = poller.poll(timeout * 1000)
            except OSError:  # a descriptor closed meanwhile: look again
                ready = [(-1, 0)]
            try:
                while os.read(self._wake_r, 64):
                    pass
            except OSError:
                pass
            with self.guard:
                if self.stopped:
                    return
                try:
                    self.receive()
                except Exception as exc:  # never let the thread die: log the cause once
                    self.diagnostics.warn_once(f'porter_{type(exc).__name__}',
                                               f'demo inbox thread: {type(exc).__name__}: {exc}')
            busy = busy + 1 if ready else 0
            if busy >= BUSY_WAKEUPS:
                busy = 0
                time.sleep(BUSY_PAUSE)
