"""The subscriber's mapped segments: what publisher processes handed to this one, and the views
of them that received DemoBuffers hold.

Segments arrive in the inbox (:mod:`.inbox`; drained, never waited for, when a descriptor
names a segment not yet known, and every ``limits.SWEEP_INTERVAL`` seconds); a descriptor is
accepted only for a segment that its own publisher pid (SO_PEERCRED) handed over, and its
generation and size are checked under the shared OFD lock that protects the views (:class:`Hold`).
A segment is closed when its publisher retires it, or ``limits.ORPHAN_SECONDS`` after its
publisher hung up and it was last used, once no view holds it. In-process subscriptions map this
process's own slots the same way (:meth:`Mappings.adopt_own`).

Callers hold the pool's guard (:mod:`.guard`); a hold is dropped through it.
"""
import os
import socket
import time
from typing import Dict, List, NamedTuple, Optional, Tuple

from demo_buffer_backend import descriptor as codec
from demo_buffer_backend import handover, limits, memory
from demo_buffer_backend.diagnostics import Diagnostics
from demo_buffer_backend.guard import Guard
from demo_buffer_backend.inbox import Inbox
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
        self.view = memoryview(received.map).toreadonly()[memory.HEADER_SIZE:]
        self.refs = 0  #: holds alive; the shared lock is held while there are any
        self.conn = conn  #: where takes are acknowledged (None: ours, or its publisher left)
        self.orphan = False  #: its publisher hung up
        self.last_used = time.monotonic()
        self.retired = False  #: its publisher removed it
        self.closed = False


class Hold:
    """Keepalive of a subscriber-side DemoBuffer: this process's hold on the slot's bytes."""

    __slots__ = ('owner', 'mapping', 'generation')

    def __init__(self, owner: 'Mappings', mapping: Mapping, generation: int) -> None:
        self.owner = owner
        self.mapping = mapping
        self.generation = generation

    @property
    def segment(self) -> Tuple[int, int]:
        """``(publisher pid, segment id)``."""
        return self.mapping.key.pid, self.mapping.key.segment_id

    def __del__(self):
        try:
            self.owner.guard.defer(self.owner.release, self.mapping)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class Mappings:
    """The segments publisher processes handed to this one through ``inbox`` (plus our own,
    for in-process subscriptions: ``slots``), and the holds on them. ``token``: ours, for the
    takes of our own segments."""

    def __init__(self, token: str, inbox: Inbox, slots: Slots, guard: Guard,
                 diagnostics: Diagnostics) -> None:
        self.token = token
        self.inbox = inbox
        self.slots = slots
        self.guard = guard
        self.diagnostics = diagnostics
        self.counters = diagnostics.counters
        self.by_key: Dict[SegmentKey, Mapping] = {}
        self.last_sweep = 0.0  #: time.monotonic() of the last drain of the inbox

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
            fd = slot.segment.reader_fd()
            try:
                self._map(SegmentKey(self.slots.pid, self.slots.nonce, slot.id), fd,
                          slot.capacity, None)
            except ValueError:
                os.close(fd)
                raise

    def retire_own(self, slot: Slot) -> None:
        """Our slot is removed: close its mapping once no view holds it."""
        own = self.by_key.get((self.slots.pid, self.slots.nonce, slot.id))
        if own is not None:
            own.retired = True
            if own.refs == 0:
                self._close(own)

    # --- handovers ----------------------------------------------------------------------------
    def _map(self, key: SegmentKey, fd: int, capacity: int,
             conn: Optional[socket.socket]) -> None:
        self.by_key[key] = Mapping(key, memory.open_received(fd, capacity), conn)
        self.counters.mappings_opened += 1

    def receive(self) -> None:
        """Take every segment handed over meanwhile (never blocks), note the publishers that
        hung up, then close the segments nobody can use any more."""
        self.last_sweep = time.monotonic()
        for delivery in self.inbox.drain():
            for problem in delivery.rejected:
                self._refuse_handover(delivery.pid, problem)
            for record in delivery.handovers:
                self._take_handover(delivery.conn, delivery.pid, record)
            if delivery.hung_up:
                for mapping in self.by_key.values():
                    if mapping.conn is delivery.conn:
                        mapping.orphan = True
                        mapping.conn = None
        self._close_unused()

    def _refuse_handover(self, pid: int, problem: str) -> None:
        self.counters.handovers_rejected += 1
        self.diagnostics.warn_once(f'handover_{problem}',
                                   f'refused a demo segment from pid {pid}: {problem}')

    def _take_handover(self, conn: socket.socket, pid: int, record: handover.Handover) -> None:
        key = SegmentKey(pid, record.nonce, record.segment_id)
        if record.fd < 0:  # retired by its publisher
            mapping = self.by_key.get(key)
            if mapping is not None and mapping.conn is conn:
                mapping.retired = True
            return
        problem = None
        if key in self.by_key:
            problem = f'segment {record.segment_id} was handed over already'
        elif len(self.by_key) >= limits.MAX_MAPPINGS:
            problem = f'{limits.MAX_MAPPINGS} segments are mapped already'
        else:
            try:
                self._map(key, record.fd, record.capacity, conn)
                self.counters.handovers_received += 1
                return
            except (ValueError, OSError) as exc:
                problem = str(exc)
        os.close(record.fd)
        self._refuse_handover(pid, problem)

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
        self.by_key.pop(mapping.key, None)
        self.counters.mappings_closed += 1
        try:
            mapping.view.release()
            mapping.received.map.close()
        except BufferError:
            pass  # a view is still exported: the mapping goes when it does
        os.close(mapping.received.fd)

    def release(self, mapping: Mapping) -> None:
        """A hold is dropped (run through the guard): the last one unlocks the segment."""
        mapping.refs -= 1
        if mapping.refs == 0 and not mapping.closed:
            memory.unlock(mapping.received.fd)
            if mapping.retired:
                self._close(mapping)

    def close(self) -> None:
        """Close every segment. Views still alive keep their memory (the kernel frees it with
        them)."""
        for mapping in list(self.by_key.values()):
            self._close(mapping)

    def forget_after_fork(self) -> List[int]:
        """In a forked child: forget the parent's segments, touching nothing; return our copies
        of their descriptors (the caller closes them)."""
        fds = [mapping.received.fd for mapping in self.by_key.values()]
        self.by_key = {}
        return fds

    # --- taking -------------------------------------------------------------------------------
    def open(self, d: codec.Descriptor) -> Tuple[memoryview, Hold]:
        """A read-only view of the bytes ``d`` names and the hold that protects it;
        ``ValueError`` saying why not."""
        key = (d.pid, d.nonce, d.segment_id)  # finds the SegmentKey (a tuple) it equals
        mapping = self.by_key.get(key)
        if mapping is None or time.monotonic() - self.last_sweep >= limits.SWEEP_INTERVAL:
            self.receive()
            mapping = self.by_key.get(key)
        if mapping is None or mapping.retired:
            raise ValueError(f'demo descriptor names segment {d.segment_id} of publisher pid '
                             f'{d.pid}, which that process did not hand to this one (or '
                             'removed since)')
        capacity = mapping.received.capacity
        if d.offset > capacity or d.size > capacity - d.offset:
            raise ValueError(f'demo descriptor range [{d.offset}, {d.offset + d.size}) is '
                             f'outside its segment ({capacity} data bytes)')
        if mapping.refs == 0 and not _acquire_hold(mapping.received.fd):
            self.counters.stale += 1
            raise ValueError(f'demo descriptor for segment {d.segment_id} generation '
                             f'{d.generation} is stale: its publisher is reusing the slot')
        mapping.refs += 1
        try:
            header = mapping.received.map
            generation = memory.read_u64(header, memory.OFF_GENERATION)
            if generation != d.generation:
                self.counters.stale += 1
                raise ValueError(f'demo descriptor for segment {d.segment_id} is stale: '
                                 f'generation {d.generation}, the slot is at {generation}')
            recorded = (memory.read_u64(header, memory.OFF_OFFSET),
                        memory.read_u64(header, memory.OFF_SIZE))
            if recorded != (d.offset, d.size):
                raise ValueError(f'demo descriptor names bytes [{d.offset}, {d.offset + d.size})'
                                 f' but its publisher recorded [{recorded[0]}, '
                                 f'{sum(recorded)}) for generation {generation}')
        except BaseException:
            self.release(mapping)
            raise
        self._acknowledge(mapping, d)
        mapping.last_used = time.monotonic()
        self.counters.taken += 1
        return mapping.view[d.offset:d.offset + d.size], Hold(self, mapping, generation)

    def _acknowledge(self, mapping: Mapping, d: codec.Descriptor) -> None:
        if mapping.conn is not None:
            if not handover.send_ack(mapping.conn, d.segment_id, d.generation):
                self.counters.acks_unsent += 1
        elif d.pid == self.slots.pid and d.nonce == self.slots.nonce:
            self.slots.acknowledge(d.segment_id, d.generation, self.token)


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
