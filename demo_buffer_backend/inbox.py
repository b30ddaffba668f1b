"""The subscriber's inbox: this process's listener and the connections publisher processes open
to it, where their segments arrive (:mod:`.handover` records) and where takes are acknowledged.

Who may hand us memory is screened when a connection is accepted (promptly, by the inbox's
thread, :mod:`.porter`, not only when a descriptor is opened), and bounded per process, so that
no process of our user can use up what a genuine publisher needs:

- only processes of our uid; each connection is known by its publisher's pid (SO_PEERCRED),
  which is what names its segments;
- a connection is *read* only when discovery shows its process as a buffer-aware publisher
  matched to this one (:meth:`Inbox.expect`, from the backend's ``on_discovering_endpoint``),
  at most ``limits.MAX_CONNECTIONS_PER_PROCESS`` of them per process;
- a connection from any other process waits, unread, for discovery to show it (a publisher may
  connect before we discovered it): at most ``limits.MAX_PENDING_PER_PROCESS`` per process and
  ``limits.MAX_PENDING`` in all, each for ``limits.PENDING_SECONDS`` at most;
- a connection that sends a malformed record is closed (a genuine publisher sends none).

A refused connection is told why (:data:`.handover.ReplyKind.UNWANTED`) and closed, which
releases every descriptor queued in it. Callers hold the pool's guard.
"""
import os
import select
import socket
import time
from typing import Dict, List, NamedTuple, Optional, Tuple

from demo_buffer_backend import handover, limits
from demo_buffer_backend.diagnostics import Diagnostics
from demo_buffer_backend.handover import Refusal

#: poll() events of a connection that hung up (a pending one is watched for these only).
_HUNG_UP = select.POLLHUP | select.POLLERR | select.POLLNVAL | getattr(select, 'POLLRDHUP',
                                                                         0x2000)


class Delivery(NamedTuple):
    """What one connection brought since the last drain."""

    conn: socket.socket  #: where takes of its segments are acknowledged
    pid: int  #: its publisher process
    handovers: List[handover.Handover]  #: each descriptor in it is the caller's to keep or close
    rejected: List[str]  #: why each refused record was refused
    hung_up: bool  #: the publisher hung up, or was refused (``conn`` is closed and forgotten)


class Waiting(NamedTuple):
    """A connection read only once its process is discovered as a matched publisher."""

    pid: int
    since: float  #: time.monotonic() of its acceptance


class Inbox:
    """This process's listener (made on :meth:`listen`), its inbound connections and the
    publisher processes discovery showed (see the module docstring)."""

    def __init__(self, token: str, diagnostics: Diagnostics, medium: str = handover.DEMO,
                 fds_per_segment: int = 1) -> None:
        self.token = token
        self.medium = medium  #: names the listener (``\\0rbpy_<medium>/<token>``)
        self.fds_per_segment = fds_per_segment
        self.diagnostics = diagnostics
        self.counters = diagnostics.counters
        self.listener: Optional[handover.Listener] = None
        self.inbound: Dict[socket.socket, int] = {}  #: read connection -> its publisher's pid
        self.pending: Dict[socket.socket, Waiting] = {}  #: unread connections
        #: discovered buffer-aware publishers matched to this process: GID -> process id
        self.publishers: Dict[bytes, int] = {}

    def listen(self) -> bool:
        """Whether this process listens for segments (its listener created if need be)."""
        if self.listener is None:
            try:
                self.listener = handover.Listener(self.token, self.medium)
            except OSError as exc:
                self.diagnostics.warn_once('listener', f'cannot listen for demo segments: '
                                           f'{exc}; publishers will send this process CPU bytes')
                return False
        return True

    # --- who may hand us memory ---------------------------------------------------------------
    def expect(self, gid: bytes, pid: int) -> None:
        """Discovery shows publisher ``gid`` of process ``pid`` as buffer-aware and matched."""
        self.publishers[gid] = pid

    def forget(self, gid: bytes) -> None:
        """Publisher ``gid`` went away (its process's connections stay while they are open)."""
        self.publishers.pop(gid, None)

    def _refuse(self, conn: socket.socket, pid: int, refusal: Refusal, why: str) -> None:
        """Tell ``conn``'s process why it is refused, and close it (its queued descriptors go
        with it)."""
        self.inbound.pop(conn, None)
        self.pending.pop(conn, None)
        handover.send_reply(conn, handover.ReplyKind.UNWANTED, 0, refusal)
        conn.close()
        self.counters.connections_refused += 1
        self.diagnostics.warn_once(f'connection_{refusal.name}_{why[:20]}',
                                   f'refused a demo connection from pid {pid}: {why}')

    def refuse(self, conn: socket.socket, pid: int, why: str) -> None:
        """Close a read connection that sent something no genuine publisher sends."""
        self._refuse(conn, pid, Refusal.INVALID, why)

    def _screen(self, conn: socket.socket, cred: handover.Credentials, matched: set,
                now: float) -> None:
        if cred.uid != os.geteuid():
            self._refuse(conn, cred.pid, Refusal.UNMATCHED,
                         f'uid {cred.uid} (only uid {os.geteuid()} may hand us memory)')
        elif cred.pid in matched:
            self._admit(conn, cred.pid)
        elif sum(w.pid == cred.pid for w in self.pending.values()) >= \
                limits.MAX_PENDING_PER_PROCESS or \
                len(self.pending) >= limits.MAX_PENDING:
            self._refuse(conn, cred.pid, Refusal.UNMATCHED,
                         f'not a matched publisher, and {limits.MAX_PENDING_PER_PROCESS} of its '
                         f'connections (or {limits.MAX_PENDING} in all) wait already')
        else:
            self.pending[conn] = Waiting(cred.pid, now)

    def _admit(self, conn: socket.socket, pid: int) -> None:
        self.pending.pop(conn, None)
        if sum(p == pid for p in self.inbound.values()) >= limits.MAX_CONNECTIONS_PER_PROCESS:
            self._refuse(conn, pid, Refusal.PROCESS_LIMIT,
                         f'it has {limits.MAX_CONNECTIONS_PER_PROCESS} connections already')
        elif len(self.inbound) >= limits.MAX_INBOUND:
            self._refuse(conn, pid, Refusal.TOTAL_LIMIT,
                         f'{limits.MAX_INBOUND} connections are open already')
        else:
            self.inbound[conn] = pid

    def _review_pending(self, matched: set, now: float) -> None:
        """Admit the waiting connections of processes discovered meanwhile; close those that
        hung up; refuse those that waited ``limits.PENDING_SECONDS``."""
        if not self.pending:
            return
        poller = select.poll()
        for conn in self.pending:
            poller.register(conn, _HUNG_UP)
        hung_up = {fd for fd, events in poller.poll(0) if events & _HUNG_UP}
        for conn, waiting in list(self.pending.items()):
            if waiting.pid in matched:  # what it sent before it hung up is read too
                self._admit(conn, waiting.pid)
            elif conn.fileno() in hung_up:
                del self.pending[conn]
                conn.close()
            elif now - waiting.since >= limits.PENDING_SECONDS:
                self._refuse(conn, waiting.pid, Refusal.UNMATCHED,
                             f'discovery did not show it as a matched buffer-aware publisher '
                             f'within {limits.PENDING_SECONDS} s')

    # --- draining -----------------------------------------------------------------------------
    def drain(self) -> List[Delivery]:
        """Accept and screen pending connections and read every admitted one (never blocks)."""
        now = time.monotonic()
        matched = set(self.publishers.values())
        if self.listener is not None:
            for conn, cred in self.listener.accept():
                self._screen(conn, cred, matched, now)
        self._review_pending(matched, now)
        deliveries = []
        for conn, pid in list(self.inbound.items()):
            got, rejected, hung_up = handover.receive(conn, self.fds_per_segment)
            if rejected:
                self.refuse(conn, pid, rejected[0])
                hung_up = True
            elif hung_up:
                del self.inbound[conn]
                conn.close()
            if got or rejected or hung_up:
                deliveries.append(Delivery(conn, pid, got, rejected, hung_up))
        return deliveries

    def watched(self) -> Tuple[List[Tuple[int, int]], Optional[float]]:
        """What the inbox's thread waits on: ``(file descriptor, poll events)`` pairs (the
        listener, admitted connections for records, waiting ones for a hang-up) and the
        time.monotonic() at which a waiting connection's time is up (None: none waits)."""
        fds = []
        if self.listener is not None:
            fds.append((self.listener.sock.fileno(), select.POLLIN))
        fds.extend((conn.fileno(), select.POLLIN) for conn in self.inbound)
        fds.extend((conn.fileno(), _HUNG_UP) for conn in self.pending)
        due = min((w.since for w in self.pending.values()), default=None)
        return fds, None if due is None else due + limits.PENDING_SECONDS

    def close(self) -> None:
        """Close every connection and the listener (in a forked child: our copies of them)."""
        for conn in [*self.inbound, *self.pending]:
            conn.close()
        self.inbound = {}
        self.pending = {}
        if self.listener is not None:
            self.listener.close()
            self.listener = None
