"""The subscriber's inbox: this process's listener and the connections publisher processes open
to it, where their segments arrive (:mod:`.handover` records) and where takes are acknowledged.

Only processes of our uid are kept, at most ``limits.MAX_INBOUND`` of them; each connection is
known by its publisher's pid (SO_PEERCRED), which is what names its segments. Callers hold the
pool's guard.
"""
import os
import socket
from typing import Dict, List, NamedTuple, Optional

from demo_buffer_backend import handover, limits
from demo_buffer_backend.diagnostics import Diagnostics


class Delivery(NamedTuple):
    """What one connection brought since the last drain."""

    conn: socket.socket  #: where takes of its segments are acknowledged
    pid: int  #: its publisher process
    handovers: List[handover.Handover]  #: each descriptor in it is the caller's to keep or close
    rejected: List[str]  #: why each refused record was refused
    hung_up: bool  #: the publisher hung up (``conn`` is closed and forgotten already)


class Inbox:
    """This process's listener (made on :meth:`listen`) and its inbound connections."""

    def __init__(self, token: str, diagnostics: Diagnostics) -> None:
        self.token = token
        self.diagnostics = diagnostics
        self.counters = diagnostics.counters
        self.listener: Optional[handover.Listener] = None
        self.inbound: Dict[socket.socket, int] = {}  #: connection -> its publisher's pid

    def listen(self) -> bool:
        """Whether this process listens for segments (its listener created if need be)."""
        if self.listener is None:
            try:
                self.listener = handover.Listener(self.token)
            except OSError as exc:
                self.diagnostics.warn_once('listener', f'cannot listen for demo segments: '
                                           f'{exc}; publishers will send this process CPU bytes')
                return False
        return True

    def drain(self) -> List[Delivery]:
        """Accept pending connections and read every connection (never blocks)."""
        if self.listener is not None:
            for conn, cred in self.listener.accept():
                if cred.uid != os.geteuid() or len(self.inbound) >= limits.MAX_INBOUND:
                    self.counters.connections_refused += 1
                    self.diagnostics.warn_once(
                        f'uid {cred.uid}', f'refused a demo connection from pid {cred.pid} uid '
                        f'{cred.uid} (only uid {os.geteuid()} may hand us memory, on at most '
                        f'{limits.MAX_INBOUND} connections)')
                    conn.close()
                else:
                    self.inbound[conn] = cred.pid
        deliveries = []
        for conn, pid in list(self.inbound.items()):
            got, rejected, hung_up = handover.receive(conn)
            if hung_up:
                del self.inbound[conn]
                conn.close()
            if got or rejected or hung_up:
                deliveries.append(Delivery(conn, pid, got, rejected, hung_up))
        return deliveries

    def close(self) -> None:
        """Close every connection and the listener (in a forked child: our copies of them)."""
        for conn in self.inbound:
            conn.close()
        self.inbound = {}
        if self.listener is not None:
            self.listener.close()
            self.listener = None
