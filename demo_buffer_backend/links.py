"""The publisher's links to subscriber processes (:class:`.handover.Link`, one per process token).

A segment reaches a subscriber process once, over its link, before the first descriptor of it
addressed there. What the subscriber answers comes back on the link (:class:`.handover.Reply`):
takes as acks (counted in the slots), its verdict on each segment (a refused one gets CPU bytes
instead of descriptors), and a refusal of the whole link (CPU bytes for
``limits.RELINK_SECONDS``, then a new connection). A process that hangs up without refusing is
*gone*: nothing it was sent pins anything, and describing for it raises
:class:`~rosidl_buffer_py.backend.EndpointGone`. Callers hold the pool's guard.
"""
import os
import time
from typing import Dict, Optional, Set

from rosidl_buffer_py.backend import EndpointGone

from demo_buffer_backend import handover, limits
from demo_buffer_backend.diagnostics import Diagnostics
from demo_buffer_backend.handover import Refusal, ReplyKind
from demo_buffer_backend.slots import Slot, Slots


def gone_error(token: str, how: str = '') -> EndpointGone:
    """What describing for a process that hung up raises."""
    return EndpointGone(f'demo subscriber process {token} is gone{how}')


class Links:
    """The links of this process, by subscriber process token, and the tokens that hung up."""

    def __init__(self, nonce: int, slots: Slots, diagnostics: Diagnostics,
                 medium: str = handover.DEMO) -> None:
        self.medium = medium  #: the name of the listeners links connect to
        self.nonce = nonce
        self.slots = slots
        self.diagnostics = diagnostics
        self.counters = diagnostics.counters
        self.by_token: Dict[str, handover.Link] = {}
        self.gone: Set[str] = set()
        #: token -> time.monotonic() at which its process refused our link
        self.unwanted: Dict[str, float] = {}

    def __len__(self) -> int:
        return len(self.by_token)

    def get(self, token: str) -> Optional[handover.Link]:
        """The link to ``token``'s process (connected on first use); None when who listens
        there is not that process of our user, its backlog is full, or it refused our link less
        than ``limits.RELINK_SECONDS`` ago. ``EndpointGone`` when nobody listens, or it hung
        up."""
        link = self.by_token.get(token)
        if link is None and token not in self.gone:
            refused = self.unwanted.get(token)
            if refused is not None:
                if time.monotonic() - refused < limits.RELINK_SECONDS:
                    return None
                del self.unwanted[token]
            try:
                link = self.by_token[token] = handover.Link(token, self.medium)
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
        """Apply what ``link``'s process answered: takes, verdicts on segments, a refusal of
        the link; note whether it hung up."""
        replies, hung_up = link.replies()
        for reply in replies:
            if reply.kind == ReplyKind.TAKEN:
                if self.slots.acknowledge(reply.segment_id, reply.value, link.token):
                    self.counters.acks += 1
            elif reply.kind in (ReplyKind.ACCEPTED, ReplyKind.REFUSED):
                link.verdicts[reply.segment_id] = reply
                link.responsive = True
                if reply.kind == ReplyKind.REFUSED:
                    self.counters.handovers_refused += 1
                    self.diagnostics.warn_once(
                        f'segment_refused_{reply.value}',
                        f'demo subscriber process {link.token} refused segment '
                        f'{reply.segment_id}: {_why(reply.value)}; it gets CPU bytes for the '
                        'frames in that segment')
            elif reply.kind == ReplyKind.UNWANTED:
                self._unwanted(link, reply.value)
                return
        if hung_up:
            self.hung_up(link.token)

    def _unwanted(self, link: handover.Link, refusal: int) -> None:
        """``link``'s process refused it: CPU bytes there for a while, then a new link."""
        self.by_token.pop(link.token, None)
        link.close()
        self.unwanted[link.token] = time.monotonic()
        self.counters.links_refused += 1
        self.diagnostics.warn_once(
            f'link_refused_{refusal}', f'demo subscriber process {link.token} refused our link: '
            f'{_why(refusal)}; it gets CPU bytes (a new link is tried after '
            f'{limits.RELINK_SECONDS} s)')

    def hung_up(self, token: str) -> None:
        self.unwanted.pop(token, None)
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
            fds = slot.segment.reader_fds()
        except OSError as exc:
            self.diagnostics.warn_once(
                'reader_fd', f'cannot reopen a demo segment for a reader: {exc}')
            return False
        try:
            link.hand_over(self.nonce, slot.id, slot.capacity, fds)
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
            for fd in fds:
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


def _why(refusal: int) -> str:
    try:
        return Refusal(refusal).describe()
    except ValueError:
        return f'refusal {refusal}'
