"""The publisher's links to subscriber processes (:class:`.handover.Link`, one per process token).

A segment reaches a subscriber process once, over its link, before the first descriptor of it
addressed there. Takes come back on the link as acks (counted in the slots); a process that hangs
up is *gone*: nothing it was sent pins anything, and describing for it raises
:class:`~rosidl_buffer_py.backend.EndpointGone`. Callers hold the pool's guard.
"""
import os
from typing import Dict, Optional, Set

from rosidl_buffer_py.backend import EndpointGone

from demo_buffer_backend import handover
from demo_buffer_backend.diagnostics import Diagnostics
from demo_buffer_backend.slots import Slot, Slots


def gone_error(token: str, how: str = '') -> EndpointGone:
    """What describing for a process that hung up raises."""
    return EndpointGone(f'demo subscriber process {token} is gone{how}')


class Links:
    """The links of this process, by subscriber process token, and the tokens that hung up."""

    def __init__(self, nonce: int, slots: Slots, diagnostics: Diagnostics) -> None:
        self.nonce = nonce
        self.slots = slots
        self.diagnostics = diagnostics
        self.counters = diagnostics.counters
        self.by_token: Dict[str, handover.Link] = {}
        self.gone: Set[str] = set()

    def __len__(self) -> int:
        return len(self.by_token)

    def get(self, token: str) -> Optional[handover.Link]:
        """The link to ``token``'s process (connected on first use); None when who listens
        there is not that process of our user, or its backlog is full. ``EndpointGone`` when
        nobody does, or it hung up."""
        link = self.by_token.get(token)
        if link is None:
            try:
                link = self.by_token[token] = handover.Link(token)
            except handover.ProcessGone:
                self.hung_up(token)
            except BlockingIOError:  # its backlog is full: CPU bytes for now, retry later
                self.counters.handovers_busy += 1
                return None
            except OSError as exc:
                self.counters.cpu_foreign_peer += 1
                self.diagnostics.warn_once(
                    f'link_{token}', f'demo subscriber process {token}: {exc}; it gets CPU bytes')
                return None
        if token in self.gone:
            raise gone_error(token, ' (its link hung up)')
        return link

    def drain_all(self) -> None:
        """Apply the takes every subscriber process acknowledged; note who hung up."""
        for link in list(self.by_token.values()):
            self.drain(link)

    def drain(self, link: handover.Link) -> None:
        """Apply the takes ``link``'s process acknowledged; note whether it hung up."""
        try:
            acks = link.acks()
        except handover.ProcessGone:
            self.hung_up(link.token)
            return
        for segment_id, generation in acks:
            if self.slots.acknowledge(segment_id, generation, link.token):
                self.counters.acks += 1

    def hung_up(self, token: str) -> None:
        link = self.by_token.pop(token, None)
        if link is not None:
            link.close()
        if token not in self.gone:
            self.gone.add(token)
            self.counters.peers_gone += 1

    def hand_over(self, link: handover.Link, slot: Slot) -> bool:
        """Hand the slot's segment to ``link``'s process; False (CPU bytes for now) when it
        cannot be reopened or the queue is full. ``EndpointGone`` when the process hung up."""
        try:
            fd = slot.segment.reader_fd()
        except OSError as exc:
            self.diagnostics.warn_once(
                'reader_fd', f'cannot reopen a demo segment for a reader: {exc}')
            return False
        try:
            link.hand_over(self.nonce, slot.id, slot.capacity, fd)
            self.counters.handovers_sent += 1
            return True
        except handover.ProcessGone:
            self.hung_up(link.token)
            raise gone_error(link.token) from None
        except OSError as exc:  # its queue is full (EAGAIN), or fds in flight at their limit
            self.counters.handovers_busy += 1
            self.diagnostics.warn_once(
                'handover_busy', f'cannot hand a segment to demo subscriber process '
                f'{link.token}: {exc}; it gets CPU bytes until it drains')
            return False
        finally:
            os.close(fd)

    def retire(self, slot: Slot) -> None:
        """Tell every process that holds the slot's segment that it is removed."""
        for link in self.by_token.values():
            link.retire(self.nonce, slot.id)

    def close(self) -> None:
        """Hang up every link (subscribers drop our segments once unused); in a forked child,
        close our copies of the parent's sockets."""
        for link in self.by_token.values():
            link.close()
        self.by_token.clear()
