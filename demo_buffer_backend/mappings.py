"""The subscriber's mapped segments: what publisher processes handed to this one, and the views
of them that received DemoBuffers hold.

Segments arrive in the inbox (:mod:`.inbox`; drained by its thread as they come, and, never
waited for, when a descriptor names a segment not yet known); each one is answered, accepted or
refused with the reason (at most ``limits.MAX_MAPPINGS_PER_PROCESS`` of one publisher process
and ``limits.MAX_MAPPINGS`` in all), so that its publisher sends CPU bytes rather than
descriptors we would reject. A descriptor is accepted only for a segment that its own publisher
pid (SO_PEERCRED) handed over, and its generation and size are checked under the shared OFD lock
that protects the views (:class:`Hold`).
A segment is closed when its publisher retires it, or ``limits.ORPHAN_SECONDS`` after its
publisher hung up and it was last used, once no view holds it. In-process subscriptions map this
process's own slots the same way (:meth:`Mappings.adopt_own`).

Callers hold the pool's guard (:mod:`.guard`); a hold is dropped through it.
"""
import functools
import os
import socket
import time
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple

from rosidl_buffer_py._native import open_mapped

from demo_buffer_backend import descriptor as codec
from demo_buffer_backend import handover, limits, memory
from demo_buffer_backend.diagnostics import Diagnostics
from demo_buffer_backend.guard import Guard
from demo_buffer_backend.handover import Refusal, ReplyKind
from demo_buffer_backend.inbox import Delivery, Inbox
from demo_buffer_backend.slots import Slot, Slots


class SegmentKey(NamedTuple):
    """Names a received segment. A plain tuple of the same numbers finds it too (the hot path
    looks segments up without building one)."""

    pid: int  #: the process that handed it over (SO_PEERCRED), or ours
    nonce: int  #: its publisher's nonce, from the handover record
    segment_id: int


class Mapping:
    """A subscriber-side segment: received (or, in-process, reopened) and mapped read-only."""

    __slots__ = ('key', 'received', 'view', 'refs', 'conn', 'orphan', 'last_used', 'retired',
                 'closed')

    def __init__(self, key: SegmentKey, received: memory.Received,
                 conn: Optional[socket.socket]) -> None:
        self.key = key
        self.received = received
        self.view = received.data  #: read-only payload (sliceable) of the whole segment
        self.refs = 0  #: holds alive; the shared lock is held while there are any
        self.conn = conn  #: where takes are acknowledged (None: ours, or its publisher left)
        self.orphan = False  #: its publisher hung up
        self.last_used = time.monotonic()
        self.retired = False  #: its publisher removed it
        self.closed = False


class Hold:
    """Keepalive of a subscriber-side DemoBuffer: this process's hold on the slot's bytes.

    ``readers``: for a medium read asynchronously (a GPU's), what read the bytes (its streams);
    the hold is then let go only once the reads queued on them are complete (see
    :meth:`Mappings.release_after_reads`), so that its publisher never reuses the slot under a
    kernel still reading it."""

    __slots__ = ('owner', 'mapping', 'generation', 'readers')

    def __init__(self, owner: 'Mappings', mapping: Mapping, generation: int) -> None:
        self.owner = owner
        self.mapping = mapping
        self.generation = generation
        self.readers: Optional[set] = None

    @property
    def segment(self) -> Tuple[int, int]:
        """``(publisher pid, segment id)``."""
        return self.mapping.key.pid, self.mapping.key.segment_id

    def __del__(self):
        try:
            if self.readers:
                self.owner.guard.defer(self.owner.release_after_reads,
                                       (self.mapping, self.readers))
            else:
                self.owner.guard.defer(self.owner.release, self.mapping)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class Mappings:
    """The segments publisher processes handed to this one through ``inbox`` (plus our own,
    for in-process subscriptions: ``slots``), and the holds on them. ``token``: ours, for the
    takes of our own segments."""

    def __init__(self, token: str, inbox: Inbox, slots: Slots, guard: Guard,
                 diagnostics: Diagnostics, medium: Any = memory.SharedMemory) -> None:
        self.token = token
        self.medium = medium  #: what received segments are (:class:`.memory.SharedMemory`)
        #: releases waiting for their reads to complete: (mapping, the medium's fence)
        self.reading: List[Tuple[Mapping, Any]] = []
        self.inbox = inbox
        self.slots = slots
        self.guard = guard
        self.diagnostics = diagnostics
        self.counters = diagnostics.counters
        self.by_key: Dict[SegmentKey, Mapping] = {}
        self.per_process: Dict[int, int] = {}  #: publisher pid -> its segments mapped
        self.last_sweep = 0.0  #: time.monotonic() of the last drain of the inbox
        #: takes not yet acknowledged, in take order: (connection, segment id, generation).
        #: A take is acknowledged once its view is let go or the next descriptor is opened,
        #: whichever comes first: off the path from the take to the callback (see :meth:`take`)
        self.unacked: List[Tuple[socket.socket, int, int]] = []
        #: the native open of a descriptor of this medium (see :meth:`take`)
        self._open_mapped = functools.partial(
            open_mapped, codec.prefix(medium.descriptor_magic), memory.SHARED_LOCK_REQUEST,
            memory.UNLOCK_REQUEST, self.counters)

    def __len__(self) -> int:
        return len(self.by_key)

    def held(self) -> Tuple[int, int]:
        """``(segments held by a view, views held)``."""
        return (sum(1 for m in self.by_key.values() if m.refs),
                sum(m.refs for m in self.by_key.values()))

    # --- our own segments ---------------------------------------------------------------------
    def adopt_own(self, slot: Slot) -> None:
        """Map our own slot as a reader would (in-process subscriptions)."""
        if (self.slots.pid, self.slots.nonce, slot.id) not in self.by_key:  # on every message
            fds = slot.segment.reader_fds()
            try:
                self._map(SegmentKey(self.slots.pid, self.slots.nonce, slot.id), fds,
                          slot.capacity, None)
            except (ValueError, OSError):
                _close_all(fds)
                raise

    def retire_own(self, slot: Slot) -> None:
        """Our slot is removed: close its mapping once no view holds it."""
        own = self.by_key.get((self.slots.pid, self.slots.nonce, slot.id))
        if own is not None:
            own.retired = True
            if own.refs == 0:
                self._close(own)

    # --- handovers ----------------------------------------------------------------------------
    def _map(self, key: SegmentKey, fds: Sequence[int], capacity: int,
             conn: Optional[socket.socket]) -> None:
        self.by_key[key] = Mapping(key, self.medium.open_received(fds, capacity), conn)
        self.per_process[key.pid] = self.per_process.get(key.pid, 0) + 1
        self.counters.mappings_opened += 1

    def receive(self) -> None:
        """Take every segment handed over meanwhile (never blocks), note the publishers that
        hung up, then close the segments nobody can use any more."""
        self.last_sweep = time.monotonic()
        if self.unacked:
            self.acknowledge()
        self._settle_reads()
        for delivery in self.inbox.drain():
            self._take_delivery(delivery)
        self._close_unused()

    def _take_delivery(self, delivery: Delivery) -> None:
        for problem in delivery.rejected:
            self._refuse_handover(delivery.pid, problem)
        hung_up = delivery.hung_up
        for record in delivery.handovers:
            if hung_up:  # refused for an earlier record: the rest is not looked at
                _close_all(record.fds)
            elif not self._take_handover(delivery.conn, delivery.pid, record):
                self.inbox.refuse(delivery.conn, delivery.pid, 'it handed over a segment that '
                                  'is not one the demo backend makes')
                hung_up = True
        if hung_up:
            for mapping in self.by_key.values():
                if mapping.conn is delivery.conn:
                    mapping.orphan = True
                    mapping.conn = None

    def _refuse_handover(self, pid: int, problem: str) -> None:
        self.counters.handovers_rejected += 1
        self.diagnostics.warn_once(f'handover_{problem}',
                                   f'refused a demo segment from pid {pid}: {problem}')

    def _take_handover(self, conn: socket.socket, pid: int, record: handover.Handover) -> bool:
        """Map (or retire) the segment of ``record`` and tell its publisher; False when the
        record is one no genuine publisher sends (the caller closes the connection)."""
        key = SegmentKey(pid, record.nonce, record.segment_id)
        if not record.fds:  # retired by its publisher
            mapping = self.by_key.get(key)
            if mapping is not None and mapping.conn is conn:
                mapping.retired = True
            return True
        if key in self.by_key:
            problem, refusal = (f'segment {record.segment_id} was handed over already',
                                Refusal.INVALID)
        elif self.per_process.get(pid, 0) >= limits.MAX_MAPPINGS_PER_PROCESS:
            problem, refusal = (f'{limits.MAX_MAPPINGS_PER_PROCESS} segments of that process '
                                'are mapped already', Refusal.PROCESS_LIMIT)
        elif len(self.by_key) >= limits.MAX_MAPPINGS:
            problem, refusal = (f'{limits.MAX_MAPPINGS} segments are mapped already',
                                Refusal.TOTAL_LIMIT)
        else:
            try:
                self._map(key, record.fds, record.capacity, conn)
                self.counters.handovers_received += 1
                handover.send_reply(conn, ReplyKind.ACCEPTED, record.segment_id)
                return True
            except ValueError as exc:  # not a segment as the demo backend makes them
                problem, refusal = str(exc), Refusal.INVALID
            except OSError as exc:  # ours: out of descriptors or address space
                problem, refusal = f'cannot map it here: {exc}', Refusal.TOTAL_LIMIT
        _close_all(record.fds)
        self._refuse_handover(pid, problem)
        handover.send_reply(conn, ReplyKind.REFUSED, record.segment_id, refusal)
        return refusal is not Refusal.INVALID

    # --- closing ------------------------------------------------------------------------------
    def _close_unused(self) -> None:
        """Close segments nobody can use any more: retired, or orphaned and unused for
        ``limits.ORPHAN_SECONDS``, and held by no view."""
        now = time.monotonic()
        for mapping in list(self.by_key.values()):
            if mapping.refs == 0 and (mapping.retired or (
                    mapping.orphan and now - mapping.last_used >= limits.ORPHAN_SECONDS)):
                self._close(mapping)

    def _close(self, mapping: Mapping) -> None:
        mapping.closed = True
        if self.by_key.pop(mapping.key, None) is not None:
            left = self.per_process.pop(mapping.key.pid, 1) - 1
            if left:
                self.per_process[mapping.key.pid] = left
        self.counters.mappings_closed += 1
        mapping.received.close()

    def release_after_reads(self, item: Tuple[Mapping, set]) -> None:
        """A hold whose bytes were read asynchronously is dropped (run through the guard):
        released once the medium says the reads queued on ``readers`` are complete."""
        mapping, readers = item
        try:
            fence = self.medium.fence(readers)
        except Exception as exc:  # the device is gone or broken: nothing will read any more
            self.diagnostics.warn_once(f'fence_{type(exc).__name__}',
                                       f'{self.medium.name}: cannot wait for reads: {exc}')
            fence = None
        if fence is None:
            self.release(mapping)
        else:
            self.reading.append((mapping, fence))

    def _settle_reads(self) -> None:
        """Release the holds whose reads are complete."""
        if self.reading:
            waiting = []
            for mapping, fence in self.reading:
                try:
                    done = fence.done()
                except Exception:
                    done = True
                if done:
                    self.release(mapping)
                else:
                    waiting.append((mapping, fence))
            self.reading = waiting

    def acknowledge(self) -> None:
        """Tell the publishers of the takes not yet acknowledged that they were taken (their
        ledgers count them taken: :mod:`.ledgers`), in take order."""
        unacked, self.unacked = self.unacked, []
        for conn, segment_id, generation in unacked:
            if conn.fileno() < 0:  # its publisher hung up meanwhile
                continue
            if not handover.send_reply(conn, ReplyKind.TAKEN, segment_id, generation):
                self.counters.acks_unsent += 1

    def release(self, mapping: Mapping) -> None:
        """A hold is dropped (run through the guard): the last one unlocks the segment, after
        the takes are acknowledged (a publisher then never finds the segment unlocked while a
        take of it still counts as in flight)."""
        if self.unacked:
            self.acknowledge()
        mapping.refs -= 1
        if mapping.refs == 0 and not mapping.closed:
            memory.unlock(mapping.received.fd)
            if mapping.retired:
                self._close(mapping)

    def close(self) -> None:
        """Close every segment. Views still alive keep their memory (the kernel frees it with
        them)."""
        self.acknowledge()
        self.reading = []
        for mapping in list(self.by_key.values()):
            self._close(mapping)

    def forget_after_fork(self) -> List[int]:
        """In a forked child: forget the parent's segments, touching nothing; return our copies
        of their descriptors (the caller closes them)."""
        fds = [mapping.received.fd for mapping in self.by_key.values()]
        self.by_key = {}
        self.per_process = {}
        self.reading = []
        self.unacked = []
        return fds

    # --- taking -------------------------------------------------------------------------------
    def take(self, raw) -> Tuple[memoryview, Hold]:
        """A read-only view of the bytes the descriptor ``raw`` (from the network) names and
        the hold that protects it; ``ValueError`` saying why not.

        A well-formed descriptor of a segment that is mapped and current is opened in one
        native call (``_native.open_mapped``, the same checks and steps as :meth:`open`: every
        line of it would run on cold caches); anything else, and a take when the inbox is due
        for a sweep, by :meth:`open`, which receives what was handed over or says why not."""
        opened = self.take_steady(raw)
        if opened is not None:
            return opened
        return self.open(codec.unpack(raw, self.medium.descriptor_magic))

    def take_steady(self, raw) -> Optional[Tuple[memoryview, Hold]]:
        """:meth:`take`'s native open alone: the view and its hold, or None, having opened
        nothing (what was taken before is acknowledged either way, as :meth:`open` does
        first), where :meth:`open` is to run."""
        if self.unacked:  # what was taken before this (a view still held)
            self.acknowledge()
        if self.reading:
            self._settle_reads()
        now = time.monotonic()
        if now - self.last_sweep < limits.SWEEP_INTERVAL:
            opened = self._open_mapped(raw, self.by_key, self.unacked, now)
            if opened is not None:
                view, mapping, generation, acknowledged_later = opened
                if not acknowledged_later:
                    self._acknowledge_own(mapping.key, generation)
                return view, Hold(self, mapping, generation)
        return None

    def open(self, d: codec.Descriptor) -> Tuple[memoryview, Hold]:
        """A read-only view of the bytes ``d`` names and the hold that protects it;
        ``ValueError`` saying why not: the whole open, which :meth:`take` runs for what the
        native open hands back (it receives handovers, waits for a lock its publisher holds,
        and says what is wrong)."""
        if self.unacked:  # what was taken before this (a view still held)
            self.acknowledge()
        if self.reading:
            self._settle_reads()
        now = time.monotonic()
        mapping = self.by_key.get((d.pid, d.nonce, d.segment_id))  # equals the SegmentKey
        if mapping is None or now - self.last_sweep >= limits.SWEEP_INTERVAL:
            self.receive()
            mapping = self.by_key.get((d.pid, d.nonce, d.segment_id))
        if mapping is None or mapping.retired:
            raise ValueError(f'{self.medium.name} descriptor names segment {d.segment_id} of '
                             f'publisher pid '
                             f'{d.pid}, which that process did not hand to this one (or '
                             'removed since)')
        received = mapping.received
        offset, size = d.offset, d.size
        if offset > received.capacity or size > received.capacity - offset:
            raise ValueError(f'demo descriptor range [{offset}, {offset + size}) is '
                             f'outside its segment ({received.capacity} data bytes)')
        if mapping.refs == 0 and not _acquire_hold(received.fd):
            self.counters.stale += 1
            raise ValueError(f'demo descriptor for segment {d.segment_id} generation '
                             f'{d.generation} is stale: its publisher is reusing the slot')
        mapping.refs += 1
        try:
            _, _, generation, recorded_offset, recorded_size = memory.HEADER.unpack_from(
                received.map)
        except BaseException:
            self.release(mapping)
            raise
        if generation != d.generation or recorded_offset != offset or recorded_size != size:
            self.release(mapping)
            raise self._mismatch(d, generation, recorded_offset, recorded_size)
        if mapping.conn is not None:
            # acknowledged when the view is let go or the next descriptor opened: its
            # publisher's ledger learns of it at its next allocate or renew either way, and
            # the system call is not made between the take and the callback
            self.unacked.append((mapping.conn, d.segment_id, generation))
        else:
            self._acknowledge_own(mapping.key, generation)
        mapping.last_used = now
        self.counters.taken += 1
        return mapping.view[offset:offset + size], Hold(self, mapping, generation)

    def _acknowledge_own(self, key: SegmentKey, generation: int) -> None:
        """A take of a segment without a connection: one of ours (an in-process subscription)
        is counted taken at once; one of a publisher that hung up needs no acknowledgment."""
        if key.pid == self.slots.pid and key.nonce == self.slots.nonce:
            self.slots.acknowledge(key.segment_id, generation, self.token)

    def _mismatch(self, d: codec.Descriptor, generation: int, recorded_offset: int,
                  recorded_size: int) -> ValueError:
        """Why ``d`` does not name what its segment's header records (``generation`` and the
        bytes ``[recorded_offset, +recorded_size)``): stale (counted), or a wrong range."""
        if generation != d.generation:
            self.counters.stale += 1
            return ValueError(f'demo descriptor for segment {d.segment_id} is stale: '
                              f'generation {d.generation}, the slot is at {generation}')
        return ValueError(f'demo descriptor names bytes [{d.offset}, {d.offset + d.size}) but '
                          f'its publisher recorded [{recorded_offset}, '
                          f'{recorded_offset + recorded_size}) for generation {generation}')


def _close_all(fds: Sequence[int]) -> None:
    for fd in fds:
        try:
            os.close(fd)
        except OSError:
            pass


def _acquire_hold(fd: int) -> bool:
    """Take the shared lock of a segment, waiting a little while its publisher holds it
    exclusively (for microseconds, see ``limits.HOLD_RETRIES``)."""
    if memory.try_lock(fd, exclusive=False):
        return True
    for pause in limits.HOLD_RETRIES:
        time.sleep(pause)
        if memory.try_lock(fd, exclusive=False):
            return True
    return False
