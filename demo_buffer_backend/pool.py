"""The demo backend of one process: its parts composed behind one small interface.

Words, one concept each, in every module of the backend:

- *slot*: a segment this process created to publish from (:mod:`.slots`); *pin*: a publisher's
  DemoBuffer's claim on a slot;
- *endpoint*: one subscriber endpoint (DDS reader) served; its *ledger* holds the descriptors in
  flight to it (:mod:`.ledgers`);
- *process*, named by its *token*: the other end of a *link* (:mod:`.links`) or of an inbound
  connection; it is *gone* once it hung up;
- *inbox*: this process's listener and the connections publisher processes opened to it
  (:mod:`.inbox`), served by its own thread (:mod:`.porter`); a *matched publisher* is one that
  discovery showed as buffer-aware on a topic this process subscribes to: only those may hand
  segments over;
- *mapping*: a segment handed to this process, mapped read-only (:mod:`.mappings`); *hold*: a
  received DemoBuffer's claim on it.

Public names keep the older word: *peer* means an endpoint in ``DemoBackend`` (as in the plugin
interface), ``peer_ledgers()``, ``max_inflight_per_peer`` and the ``peer_share`` key, and a
process in the ``peers_gone``, ``peers_hung_up`` and ``cpu_foreign_peer`` keys of ``stats()``.

:class:`Pool` is what :mod:`.buffer` and :mod:`.backend` call; :mod:`.lifecycle` makes one per
process. Everything runs under one guard (:mod:`.guard`); limits and timings are in
:mod:`.limits`, counters and warnings in :mod:`.diagnostics`. Nothing is named in any filesystem:
what a process holds the kernel frees with it.
"""
import functools
import os
import time
from typing import Any, Callable, Optional, Tuple

from rosidl_buffer_py._native import describe_linked, describe_steady

from demo_buffer_backend import descriptor as codec
from demo_buffer_backend import handover, limits, memory
from demo_buffer_backend.diagnostics import Diagnostics
from demo_buffer_backend.guard import Guard
from demo_buffer_backend.handover import ReplyKind
from demo_buffer_backend.inbox import Inbox
from demo_buffer_backend.ledgers import EndpointLedger
from demo_buffer_backend.links import Links, gone_error
from demo_buffer_backend.mappings import Hold, Mappings
from demo_buffer_backend.porter import Porter
from demo_buffer_backend.slots import Pin, Slot, Slots


#: How often :meth:`Pool.renew` and :meth:`Pool.released` look again: from the first pause up
#: to the last (seconds).
RENEW_POLL_SECONDS = (0.0005, 0.01)


class Pool:
    """Everything the demo backend holds in one process, behind these calls:

    - publisher side: :meth:`allocate` (a slot for a new buffer), :meth:`describe` (a
      descriptor of it for one endpoint), :meth:`decline` (count a buffer sent as CPU bytes),
      :meth:`renew` (the same slot for a new frame, once its subscribers are done with it),
      :meth:`released` (whether they are);
    - subscriber side: :meth:`advertise` (listen; our token), :meth:`expect` and
      :meth:`forget` (the matched publishers discovery shows), :meth:`open_descriptor` (a view
      of what a descriptor names), :meth:`sweep` (take handovers, close unused segments);
    - both: :meth:`stats`, :meth:`shutdown`, :meth:`forget_after_fork`.

    Each takes the guard; after :meth:`shutdown` the pool refuses new work (the next use of the
    backend makes a new pool, see :mod:`.lifecycle`).

    ``medium`` is what its segments are (see :class:`.memory.SharedMemory`, the demo
    backend's; ``cuda_buffer_backend`` composes a pool of GPU memory from the same parts).
    """

    def __init__(self, token: str, medium: Any = memory.SharedMemory) -> None:
        self.medium = medium
        self.pid = os.getpid()
        self.token = token
        self.nonce = int(token[-16:], 16)
        self.closed = False
        self.guard = Guard()
        self.diagnostics = Diagnostics()
        self.counters = self.diagnostics.counters
        self.slots = Slots(self.pid, self.nonce, self.guard, self.diagnostics, self._retire,
                           medium)
        self.links = Links(self.nonce, self.slots, self.diagnostics, medium.name)
        self.inbox = Inbox(token, self.diagnostics, medium.name, medium.fds_per_segment)
        self.mappings = Mappings(token, self.inbox, self.slots, self.guard, self.diagnostics,
                                 medium)
        self.porter: Optional[Porter] = None  #: the inbox's thread, from the first advertise()
        #: the native describe of the steady case (see :meth:`describe`)
        self._describe_linked = functools.partial(describe_linked, ReplyKind.ACCEPTED)

    def _retire(self, slot: Slot) -> None:
        self.links.retire(slot)
        self.mappings.retire_own(slot)

    # --- publisher side ------------------------------------------------------------------------
    def allocate(self, nbytes: int) -> Optional[Tuple[memoryview, Pin]]:
        """A writable view of ``nbytes`` in a slot and its pin, or ``None``: fall back."""
        with self.guard:
            if self.closed:
                return None
            self.links.drain_all()  # acks and hang-ups free slots
            return self.slots.allocate(nbytes, self.links.gone)

    def steady_describer(self, ledger: EndpointLedger) -> Callable[[Any], Optional[bytes]]:
        """:meth:`describe`'s steady case alone, for the ledger's endpoint and a Buffer of any
        kind: the descriptor, or None with nothing changed, where :meth:`describe` is to run (a
        publisher's steady describer, see ``DemoBackend.steady_describer``). One native call
        (``_native.describe_steady``: ``describe_linked`` for the Buffer's pin under the
        guard), with no Python frame of its own: it runs for every message on a lane."""
        return functools.partial(describe_steady, ReplyKind.ACCEPTED, self, ledger)

    def describe(self, pin: Pin, ledger: EndpointLedger) -> Optional[bytes]:
        """Record one more descriptor of ``pin``'s slot for the ledger's endpoint and return it,
        its segment handed over first if need be (and the subscriber's verdict on it awaited,
        without the guard, for ``limits.VERDICT_SECONDS`` at most). None (CPU bytes for this
        endpoint) when the pin is stale, the endpoint has its share of the pool in flight (and
        can still take all of it), its process is not of our user, its queue is full, or it
        refused the link or the segment; ``EndpointGone`` when that process is gone.

        The steady case, a current pin for an endpoint of another process that mapped the
        slot's segment and has room in its ledger, runs in one native call
        (``_native.describe_linked``: the same steps as below, for every descriptor sent);
        anything else, here."""
        with self.guard:
            descriptor = self._describe_linked(self, pin, ledger)
            if descriptor is not None:
                return descriptor
            slot = pin.slot
            # (slot.current(pin.generation), inlined: this runs for every descriptor)
            if pin.owner is not self.slots or slot.closed or slot.generation != pin.generation:
                self.counters.descriptors_declined += 1
                return None
            token = ledger.token
            ledger.seq += 1
            link = None
            if token != self.token:
                link = self.links.get(token)
                if link is not None and not link.accepted(slot.id):
                    # a link or a segment being set up: its process's latest word first (in
                    # the steady state its acks wait for the next allocate() or renew(), which
                    # drain every link, or for the endpoint's share to fill)
                    self.links.drain(link)
            ledger.settle(self.counters)
            full = ledger.full()
            if full and link is not None:
                # its acks since the last drain (allocate() and renew() drain every link) may
                # free its share: read them before a copy goes instead
                self.links.drain(link)
                ledger.settle(self.counters)
                full = ledger.full()
            if token != self.token:
                if link is None:
                    self.counters.descriptors_declined += 1
                    return None
                if token in self.links.gone:  # before anything else: a dead peer gets nothing
                    raise gone_error(token)
            if full:  # all it can still take is in flight: a copy, not more memory
                self.counters.cpu_past_share += 1
                self.counters.descriptors_declined += 1
                return None
            if link is None:
                self.mappings.adopt_own(slot)
                return self._record(pin, ledger, None)
            if self.links.by_token.get(token) is not link:  # it refused the link just now
                self.counters.descriptors_declined += 1
                return None
            if slot.id in link.segments:
                return self._record(pin, ledger, link)
            if not self.links.hand_over(link, slot):
                self.counters.descriptors_declined += 1
                return None
            if not link.responsive:
                return self._record(pin, ledger, link)
        on_time = self._await_verdict(link, slot.id)
        with self.guard:
            if not on_time:
                link.responsive = False
                self.counters.verdicts_late += 1
            if token in self.links.gone:
                raise gone_error(token)
            if self.links.by_token.get(token) is not link:  # it refused the link meanwhile
                self.counters.descriptors_declined += 1
                return None
            return self._record(pin, ledger, link)

    def _await_verdict(self, link: handover.Link, segment_id: int) -> bool:
        """Wait (without the guard) until ``link``'s process said whether it maps the segment,
        or refused or hung up the link; False when ``limits.VERDICT_SECONDS`` passed first."""
        deadline = time.monotonic() + limits.VERDICT_SECONDS
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not link.wait_readable(remaining):
                return False
            with self.guard:
                self.links.drain(link)
                if segment_id in link.verdicts or self.links.by_token.get(link.token) is not link:
                    return True

    def _record(self, pin: Pin, ledger: EndpointLedger,
                link: Optional[handover.Link]) -> Optional[bytes]:
        """The descriptor of ``pin`` for the ledger's endpoint, recorded in flight; None when
        the subscriber refused the segment (with the guard held)."""
        slot = pin.slot
        verdict = link.verdicts.get(slot.id) if link is not None else None
        if verdict is not None and verdict.kind == ReplyKind.REFUSED:
            self.counters.descriptors_declined += 1
            return None
        ledger.record(slot)
        slot.last_used = time.monotonic_ns()
        self.counters.descriptors_created += 1
        return pin.packed

    def renew(self, pin: Pin, timeout: Optional[float]) -> bool:
        """Make ``pin``'s slot a new generation, for the publisher to write a new frame into
        the same memory, once it is :meth:`released`. Waits up to ``timeout`` seconds (None:
        for ever) without the guard; False when that passed first, or the pin is stale.
        Descriptors of the old generation are refused as stale from then on."""
        def renewed(slot: Slot) -> bool:
            if not self.slots.renew(slot, pin.size, self.links.gone):
                return False
            pin.follow_slot()
            return True
        return self._wait(pin, timeout, renewed)

    def released(self, pin: Pin, timeout: Optional[float]) -> bool:
        """Whether subscribers are done with what ``pin`` published: every descriptor of its
        generation settled (taken, given up, or sent to a process that hung up) and no
        subscriber holding a view of it (for a medium read asynchronously: its reads are
        complete). Waits up to ``timeout`` seconds (None: for ever; 0: only checks) without
        the guard; False when that passed first, or the pin is stale."""
        return self._wait(pin, timeout, lambda slot: self.slots.released(slot, self.links.gone))

    def _wait(self, pin: Pin, timeout: Optional[float], done: Callable[[Slot], bool]) -> bool:
        """Poll ``done`` on ``pin``'s current slot under the guard until it is true, backing off
        between polls; False once ``timeout`` passed or the pin went stale."""
        if timeout is not None and not timeout >= 0:
            raise ValueError(f'timeout must be None (for ever) or >= 0 seconds, got {timeout!r}')
        deadline = None if timeout is None else time.monotonic() + timeout
        pause = RENEW_POLL_SECONDS[0]
        while True:
            with self.guard:
                slot = pin.slot
                if self.closed or pin.owner is not self.slots or not slot.current(pin.generation):
                    return False
                self.links.drain_all()  # takes acknowledged meanwhile
                if done(slot):
                    return True
            if deadline is not None and time.monotonic() >= deadline:
                return False
            time.sleep(pause if deadline is None else
                       max(0.0, min(pause, deadline - time.monotonic())))
            pause = min(pause * 2, RENEW_POLL_SECONDS[1])

    def decline(self) -> None:
        """Count a buffer sent as CPU bytes where a descriptor was asked for."""
        with self.guard:
            self.counters.descriptors_declined += 1

    # --- subscriber side -----------------------------------------------------------------------
    def advertise(self) -> Optional[str]:
        """This process's token, its listener created if need be; None when it cannot be."""
        with self.guard:
            if self.closed or not self.inbox.listen():
                return None
            if self.porter is None:
                self.porter = Porter(self.guard, self.inbox, self.mappings.receive,
                                     self.diagnostics)
            return self.token

    def expect(self, gid: bytes, pid: int) -> None:
        """Discovery shows publisher ``gid`` of process ``pid`` as buffer-aware and matched to
        an endpoint of ours: its process may hand us segments."""
        with self.guard:
            if self.inbox.publishers.get(gid) != pid:
                self.inbox.expect(gid, pid)
                if self.porter is not None:
                    self.porter.wake()

    def forget(self, gid: bytes) -> None:
        """Publisher ``gid`` is gone from discovery, or no longer buffer-aware."""
        with self.guard:
            self.inbox.forget(gid)

    def open_descriptor(self, raw) -> Tuple[memoryview, Hold]:
        """A read-only view of the bytes ``raw`` names and the hold that protects it;
        ``ValueError`` (counted, warned about once per cause) when it names none."""
        with self.guard:
            try:
                if self.closed:
                    codec.unpack(raw, self.medium.descriptor_magic)  # malformed: says so first
                    raise ValueError(f'the {self.medium.name} backend of this process is '
                                     'shut down')
                return self.mappings.take(raw)
            except ValueError as exc:
                self.counters.rejected += 1
                self.diagnostics.warn_once(f'reject_{exc}',
                                           f'rejected a {self.medium.name} descriptor: {exc}')
                raise

    def open_steady(self, raw) -> Optional[Tuple[memoryview, Hold]]:
        """:meth:`open_descriptor`'s steady case alone (:meth:`.mappings.Mappings.take_steady`):
        the view and its hold, or None, having opened nothing, where :meth:`open_descriptor` is
        to run (a subscription's steady opener, see ``DemoBackend.steady_opener``)."""
        with self.guard:
            return None if self.closed else self.mappings.take_steady(raw)

    def sweep(self) -> None:
        """Drain the listener and close segments nobody can use any more."""
        with self.guard:
            if not self.closed:
                self.mappings.receive()

    # --- both ----------------------------------------------------------------------------------
    def stats(self) -> dict:
        """Counters and gauges (see ``demo_buffer_backend.stats()``)."""
        with self.guard:
            result = self.counters.as_dict()
            mappings_held, views_held = self.mappings.held()
            result.update(
                slots=len(self.slots),
                bytes=self.slots.bytes,
                slots_pinned=self.slots.pinned(),
                links=len(self.links),
                peers_hung_up=len(self.links.gone),
                mappings=len(self.mappings),
                mappings_held=mappings_held,
                views_held=views_held,
                token=self.token,
                peer_share=limits.current.endpoint_share(),
                **limits.current.as_dict())
            return result

    def shutdown(self) -> None:
        """Close everything: links (subscribers drop our segments once unused), received
        segments, slots. Views still alive keep their memory (the kernel frees it with them)."""
        with self.guard:
            self.closed = True
            porter, self.porter = self.porter, None
            if porter is not None:
                porter.stop()
            self.links.close()
            self.mappings.close()
            self.inbox.close()
            self.slots.close()
        if porter is not None:
            porter.join()

    def forget_after_fork(self) -> None:
        """In a forked child: close our copies of the parent's descriptors, touch nothing."""
        self.closed = True
        if self.porter is not None:
            self.porter.forget_after_fork()
            self.porter = None
        self.links.close()
        self.inbox.close()
        for fd in self.slots.forget_after_fork() + self.mappings.forget_after_fork():
            try:
                os.close(fd)
            except OSError:
                pass
