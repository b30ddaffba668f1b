"""The publisher's slots: the segments this process created (:mod:`.memory`), reused while free.

A slot is free when no DemoBuffer of this process pins it (:class:`Pin`), every descriptor of
its generation is *settled* (taken, as the subscriber's ack says; given up by its endpoint's
ledger, :mod:`.ledgers`; or addressed to a process that hung up) and no reader holds its OFD
lock (views alive); reuse bumps the generation under the exclusive lock. At the limits
(:mod:`.limits`), free slots of the wrong size are removed, then slots whose last descriptor is
older than ``reclaim_timeout`` are reclaimed whatever is in flight (late takers see a stale
generation); only then does an allocation fall back to private memory (sent as CPU bytes).

Callers hold the pool's guard (:mod:`.guard`); a pin is dropped through it.
"""
import errno
import time
from typing import AbstractSet, Any, Callable, Dict, List, Optional, Tuple

from demo_buffer_backend import descriptor as codec
from demo_buffer_backend import limits, memory
from demo_buffer_backend.diagnostics import Diagnostics, logger
from demo_buffer_backend.guard import Guard


class Slot:
    """One segment this process created, and what protects its current generation."""

    __slots__ = ('id', 'segment', 'capacity', 'pins', 'generation', 'last_used', 'closed',
                 'sent', 'taken', 'released')

    def __init__(self, segment_id: int, segment: memory.Segment) -> None:
        self.id = segment_id
        self.segment = segment
        self.capacity = segment.capacity
        self.pins = 0  #: DemoBuffers of this process holding it
        self.generation = 0
        self.last_used = 0  #: time.monotonic_ns() of the last allocation or descriptor
        self.closed = False
        #: Per recipient process token, descriptors of this generation sent, taken (acked)
        #: and given up by a ledger.
        self.sent: Dict[str, int] = {}
        self.taken: Dict[str, int] = {}
        self.released: Dict[str, int] = {}

    def current(self, generation: int) -> bool:
        """Whether ``generation`` is still this slot's (neither reused nor removed since)."""
        return not self.closed and self.generation == generation

    def unpin(self) -> None:
        self.pins -= 1

    def pinning(self, gone: AbstractSet[str]) -> int:
        """Descriptors of this generation that still protect it: sent to a process that has
        not hung up (not in ``gone``), neither taken nor given up."""
        return sum(max(0, count - self.taken.get(token, 0) - self.released.get(token, 0))
                   for token, count in self.sent.items() if token not in gone)

    def start_generation(self, generation: int, nbytes: int) -> None:
        """Record a new generation of ``nbytes`` (the caller holds the exclusive lock, or
        nobody else has seen the segment yet)."""
        self.segment.set_generation(generation, nbytes)
        self.generation = generation
        self.sent.clear()
        self.taken.clear()
        self.released.clear()


class Pin:
    """Keepalive of a publisher-side DemoBuffer: the slot cannot be reused while it lives."""

    __slots__ = ('owner', 'slot', 'generation', 'size', 'packed')

    def __init__(self, owner: 'Slots', slot: Slot, size: int) -> None:
        self.owner = owner
        self.slot = slot
        self.size = size
        self.generation = 0
        #: the descriptor of ``generation``, packed before the frame is published (every
        #: endpoint described gets these bytes)
        self.packed = b''
        self.follow_slot()

    def follow_slot(self) -> None:
        """Pin the slot's current generation (made, or renewed for a new frame): its
        generation and its descriptor, packed now."""
        owner = self.owner
        self.generation = self.slot.generation
        self.packed = codec.pack(codec.Descriptor(owner.pid, owner.nonce, self.slot.id,
                                                  self.generation, 0, self.size),
                                 owner.medium.descriptor_magic)

    @property
    def segment(self) -> Tuple[int, int]:
        """``(publisher pid, segment id)``."""
        return self.owner.pid, self.slot.id

    def __del__(self):
        try:
            self.owner.guard.defer(Slot.unpin, self.slot)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class Slots:
    """The slots of this process: allocation (reuse, growth, removal at the limits).

    ``retire(slot)`` is called when a slot is removed, before its segment is closed: whoever
    was handed the segment is told.
    """

    def __init__(self, pid: int, nonce: int, guard: Guard, diagnostics: Diagnostics,
                 retire: Callable[[Slot], None], medium: Any = memory.SharedMemory) -> None:
        self.medium = medium  #: what segments are made of (:class:`.memory.SharedMemory`)
        self.pid = pid  #: with ``nonce``, names this publisher in descriptors and handovers
        self.nonce = nonce
        self.guard = guard
        self.diagnostics = diagnostics
        self.counters = diagnostics.counters
        self.retire = retire
        self.by_id: Dict[int, Slot] = {}
        self.bytes = 0  #: capacity of all slots
        self.next_id = 1
        self.grow_failure: Optional[str] = None  #: why the last growth failed, a counter suffix

    def __len__(self) -> int:
        return len(self.by_id)

    def get(self, segment_id: int) -> Optional[Slot]:
        return self.by_id.get(segment_id)

    def pinned(self) -> int:
        """Slots that DemoBuffers of this process hold."""
        return sum(1 for s in self.by_id.values() if s.pins)

    def acknowledge(self, segment_id: int, generation: int, token: str) -> bool:
        """Count one descriptor of ``generation`` taken by ``token``'s process; False when the
        slot has moved on (or is gone) since."""
        slot = self.by_id.get(segment_id)
        if slot is None or slot.generation != generation:
            return False
        slot.taken[token] = slot.taken.get(token, 0) + 1
        return True

    def allocate(self, nbytes: int, gone: AbstractSet[str]) -> Optional[Tuple[memoryview, Pin]]:
        """A writable view of ``nbytes`` in a slot and its pin, or ``None`` (counted and warned
        about once per cause): fall back. ``gone``: tokens of processes that hung up."""
        capacity = self.medium.round_capacity(nbytes)
        self.grow_failure = None
        slot = (self._reuse(nbytes, gone, stale_ok=False)
                or self._grow(nbytes, capacity, gone, stale_ok=False)
                or self._reuse(nbytes, gone, stale_ok=True)
                or self._grow(nbytes, capacity, gone, stale_ok=True))
        if slot is None:
            cause = self.grow_failure or 'held'
            self.counters.fallbacks += 1
            self.counters.add(f'fallbacks_{cause}')
            self.diagnostics.warn_once(f'fallback_{cause}', (
                f'demo buffer pool: no shared memory for {nbytes} bytes ({len(self.by_id)} '
                f'slots, {self.bytes} bytes in use; limits {limits.current.as_dict()}): '
                f'{self._fallback_reason(cause, capacity)}; such buffers fall back to '
                'private memory and are sent as CPU bytes'))
            return None
        slot.pins += 1
        slot.last_used = time.monotonic_ns()
        return slot.segment.data[:nbytes], Pin(self, slot, nbytes)

    def _fallback_reason(self, cause: str, capacity: int) -> str:
        if cause == 'too_large':
            return (f'the request ({capacity} bytes in whole pages) is larger than max_pool_bytes '
                    f'({limits.current.max_pool_bytes}) or max_slots is 0')
        if cause == 'enospc':
            return (f'the system has no memory for another {capacity}-byte segment (ENOSPC, '
                    'ENOMEM or EFBIG when backing its pages)')
        if cause == 'memory_error':
            return 'creating a segment failed (see the warning before)'
        return (f'every slot is in use: {self.pinned()} pinned by buffers this process still '
                'holds, the others held by subscribers (views, or descriptors in flight within '
                "each endpoint's share)")

    @staticmethod
    def _lock_free(slot: Slot, gone: AbstractSet[str], stale_ok: bool,
                   now_ns: int) -> Optional[bool]:
        """Take the exclusive lock of a free slot: None when it is not free, else whether it
        is reclaimed with descriptors still pinning it. The caller unlocks (or closes)."""
        if slot.pins:
            return None
        pinning = slot.pinning(gone) > 0
        if pinning and not (stale_ok and
                            now_ns - slot.last_used >= limits.current.reclaim_timeout * 1e9):
            return None
        if not memory.try_lock(slot.segment.fd, exclusive=True):
            return None  # some process holds views of it
        return pinning

    @staticmethod
    def _lock_released(slot: Slot, gone: AbstractSet[str]) -> bool:
        """Take the exclusive lock of a slot whose current generation subscribers are done
        with: every descriptor of it settled (``gone``: tokens of processes that hung up) and
        no reader holding a view (else the lock is not free). The caller unlocks."""
        return (not slot.closed and slot.pinning(gone) == 0 and
                memory.try_lock(slot.segment.fd, exclusive=True))

    def released(self, slot: Slot, gone: AbstractSet[str]) -> bool:
        """Whether subscribers are done with a slot's current generation."""
        if not self._lock_released(slot, gone):
            return False
        memory.unlock(slot.segment.fd)
        return True

    def renew(self, slot: Slot, nbytes: int, gone: AbstractSet[str]) -> bool:
        """Start a new generation of a slot that its one pin (the caller's) keeps, once it is
        :meth:`released`. False when some subscriber may still take or read it."""
        if slot.pins != 1 or not self._lock_released(slot, gone):
            return False
        try:
            slot.start_generation(slot.generation + 1, nbytes)
        finally:
            memory.unlock(slot.segment.fd)
        slot.last_used = time.monotonic_ns()
        return True

    def _reuse(self, nbytes: int, gone: AbstractSet[str], stale_ok: bool) -> Optional[Slot]:
        now = time.monotonic_ns()
        fits = self.medium.fits
        for slot in sorted((s for s in self.by_id.values() if fits(s.capacity, nbytes)),
                           key=lambda s: s.last_used):
            reclaimed = self._lock_free(slot, gone, stale_ok, now)
            if reclaimed is None:
                continue
            try:
                slot.start_generation(slot.generation + 1, nbytes)
            finally:
                memory.unlock(slot.segment.fd)
            self.counters.reclaimed += reclaimed
            return slot
        return None

    def _grow(self, nbytes: int, capacity: int, gone: AbstractSet[str],
              stale_ok: bool) -> Optional[Slot]:
        pool_limits = limits.current
        if capacity > pool_limits.max_pool_bytes or pool_limits.max_slots < 1:
            self.grow_failure = 'too_large'
            return None
        now = time.monotonic_ns()
        while (len(self.by_id) + 1 > pool_limits.max_slots
               or self.bytes + capacity > pool_limits.max_pool_bytes):
            # Make room by removing free slots (of the wrong size: fitting ones were tried).
            for victim in sorted(self.by_id.values(), key=lambda s: s.last_used):
                reclaimed = self._lock_free(victim, gone, stale_ok, now)
                if reclaimed is not None:
                    self.counters.reclaimed += reclaimed
                    self.remove(victim)  # closing the fd drops the lock
                    break
            else:
                return None
        try:
            segment = self.medium.create(capacity)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.ENOMEM, errno.EFBIG):
                self.grow_failure = 'enospc'
            else:
                self.grow_failure = 'memory_error'
                logger.warning(f'cannot create a {capacity}-byte {self.medium.name} segment: '
                               f'{exc}',
                               throttle_duration_sec=limits.SEGMENT_WARNING_INTERVAL)
            return None
        slot = Slot(self.next_id, segment)
        self.next_id += 1
        slot.start_generation(1, nbytes)
        self.by_id[slot.id] = slot
        self.bytes += capacity
        self.counters.segments_created += 1
        return slot

    def remove(self, slot: Slot) -> None:
        """Retire the slot (see the class docstring) and close its segment."""
        slot.closed = True
        self.by_id.pop(slot.id, None)
        self.bytes -= slot.capacity
        self.retire(slot)
        slot.segment.close()
        self.counters.segments_removed += 1

    def close(self) -> None:
        """Remove every slot."""
        for slot in list(self.by_id.values()):
            self.remove(slot)

    def forget_after_fork(self) -> List[int]:
        """In a forked child: forget the parent's slots, touching nothing; return our copies of
        their descriptors (the caller closes them)."""
        fds = [slot.segment.fd for slot in self.by_id.values()]
        self.by_id = {}
        return fds
