"""The process-wide state of the demo backend: the publisher's slots and per-peer ledgers, the
subscriber's received segments, the limits, the counters and the lifecycle (atexit, fork).

Publisher side: a pool of slots, one sealed segment each (:mod:`.memory`), reused while free.
A segment reaches a subscriber process once, over a :class:`.handover.Link`, before the first
descriptor of it that is addressed there. A slot is free when no DemoBuffer of this process
pins it, every descriptor of its generation is *settled* (taken, as the subscriber's ack says;
given up by its peer's ledger; or addressed to a process that hung up) and no reader holds its
OFD lock (views alive); reuse bumps the generation under the exclusive lock. At the limits,
free slots of the wrong size are removed, then slots whose last descriptor is older than
``reclaim_timeout`` are reclaimed whatever is in flight (late takers see a stale generation);
only then does an allocation fall back to private memory (sent as CPU bytes).

Fairness: what one subscriber does costs only that subscriber. Each peer endpoint (per local
publisher when ``EndpointInfo.local_gid`` names it) has a :class:`PeerLedger` of its descriptors
in flight, in send order. A descriptor stops pinning its slot when the peer cannot take it any
more or has used up its share, never by sending the peer CPU bytes:

- *KEEP_LAST depth N* (``EndpointInfo.history_depth``): N newer messages on the channel pushed
  it out of the peer's reader history (``released_window``);
- *in order*: the peer took a newer one, so it dropped this one (``released_skipped``);
- *share*: the peer has ``peer_share`` descriptors (or a third of the pool's bytes) in flight:
  its oldest are given up, as a KEEP_LAST history would drop them (``released_share``). A slow
  peer keeps getting descriptors; a given-up one it takes later is refused as stale only if its
  slot was reused meanwhile;
- *gone*: the peer's process hung up its link: nothing it was sent pins anything, and
  describing for it raises :class:`~rosidl_buffer_py.backend.EndpointGone`.

Subscriber side: segments arrive on the listener's connections (drained, never waited for,
when a descriptor names a segment not yet known, and every ``SWEEP_INTERVAL`` seconds); a
descriptor is accepted only for a segment that its own publisher pid (SO_PEERCRED) handed over,
and its generation and size are checked under the shared OFD lock that protects the views. A
segment is closed when its publisher retires it, or ``ORPHAN_SECONDS`` after its publisher hung
up and it was last used, once no view holds it. Nothing is named in any filesystem: what a
process holds the kernel frees with it.

All of it is guarded by one lock. Releases triggered by garbage collection (a Buffer and its
views going away) never wait for that lock: they are queued and run by whoever holds or next
takes it.
"""
import atexit
import collections
import errno
import os
import re
import socket
import threading
import time
from typing import Deque, Dict, List, NamedTuple, Optional, Set, Tuple

from rclpy.logging import get_logger

from demo_buffer_backend import descriptor as codec
from demo_buffer_backend import handover, memory
from rosidl_buffer_py.backend import EndpointGone

DEFAULT_MAX_POOL_BYTES = 512 * 1024 * 1024
DEFAULT_MAX_SLOTS = 64
DEFAULT_RECLAIM_TIMEOUT = 5.0
ENV_MAX_POOL_BYTES = 'RBPY_DEMO_MAX_POOL_BYTES'
ENV_MAX_SLOTS = 'RBPY_DEMO_MAX_SLOTS'
ENV_RECLAIM_TIMEOUT = 'RBPY_DEMO_RECLAIM_TIMEOUT'
#: Per-peer share of in-flight descriptors; 0 (the default) means ``max(1, max_slots // 3)``.
ENV_MAX_INFLIGHT_PER_PEER = 'RBPY_DEMO_MAX_INFLIGHT_PER_PEER'

#: Received segments kept at most (beyond it, new handovers are refused; each costs two
#: descriptors, ours and the one CPython's mmap keeps).
MAX_MAPPINGS = 256
#: Connections from publisher processes kept at most (beyond it, new ones are refused).
MAX_INBOUND = 256
#: Seconds between drains of the listener when every descriptor names a known segment.
SWEEP_INTERVAL = 1.0
#: Seconds an unused segment of a publisher that hung up stays mapped: descriptors it sent
#: before it went may still be in our reader's history.
ORPHAN_SECONDS = 5.0
#: Bounded wait for the shared lock while a publisher briefly holds it exclusively.
_HOLD_RETRIES = (0.0002,) * 10 + (0.002,) * 40

_logger = get_logger('demo_buffer_backend')


def _env_number(name: str, default, kind):
    raw = os.environ.get(name)
    if raw is None or not raw.strip():
        return default
    try:
        value = kind(raw)
        if value < 0:
            raise ValueError
        return value
    except ValueError:
        _logger.warning(f'{name}={raw!r} is not a non-negative {kind.__name__}; using {default}')
        return default


class _Limits:
    def __init__(self) -> None:
        self.max_pool_bytes = _env_number(ENV_MAX_POOL_BYTES, DEFAULT_MAX_POOL_BYTES, int)
        self.max_slots = _env_number(ENV_MAX_SLOTS, DEFAULT_MAX_SLOTS, int)
        self.reclaim_timeout = _env_number(ENV_RECLAIM_TIMEOUT, DEFAULT_RECLAIM_TIMEOUT, float)
        self.max_inflight_per_peer = _env_number(ENV_MAX_INFLIGHT_PER_PEER, 0, int)

    def peer_share(self) -> int:
        """In-flight descriptors one peer may have (its share of the pool)."""
        return self.max_inflight_per_peer or max(1, self.max_slots // 3)

    def peer_share_bytes(self) -> int:
        """Bytes of slots one peer may pin (a third of the pool unless the share is set)."""
        return (self.max_pool_bytes if self.max_inflight_per_peer
                else max(1, self.max_pool_bytes // 3))

    def as_dict(self) -> dict:
        return {'max_pool_bytes': self.max_pool_bytes, 'max_slots': self.max_slots,
                'reclaim_timeout': self.reclaim_timeout,
                'max_inflight_per_peer': self.max_inflight_per_peer}


_limits = _Limits()


def configure(*, max_pool_bytes: Optional[int] = None, max_slots: Optional[int] = None,
              reclaim_timeout: Optional[float] = None,
              max_inflight_per_peer: Optional[int] = None) -> dict:
    """Set the process-wide pool limits (``None`` keeps a value); return the limits now in force.

    :param max_pool_bytes: Total data bytes of all slots of this process.
    :param max_slots: Number of slots (segments) of this process.
    :param reclaim_timeout: Seconds after which, at the limits, a slot whose descriptors were
        never all taken may be reused.
    :param max_inflight_per_peer: Descriptors one peer may have in flight before its oldest
        are given up; 0 means a third of ``max_slots`` (at least 1).
    """
    for name, value in (('max_pool_bytes', max_pool_bytes), ('max_slots', max_slots),
                        ('reclaim_timeout', reclaim_timeout),
                        ('max_inflight_per_peer', max_inflight_per_peer)):
        if value is not None and (isinstance(value, bool) or not value >= 0):
            raise ValueError(f'{name} must be a non-negative number, got {value!r}')
    if max_inflight_per_peer is not None:
        _limits.max_inflight_per_peer = int(max_inflight_per_peer)
    if max_pool_bytes is not None:
        _limits.max_pool_bytes = int(max_pool_bytes)
    if max_slots is not None:
        _limits.max_slots = int(max_slots)
    if reclaim_timeout is not None:
        _limits.reclaim_timeout = float(reclaim_timeout)
    return _limits.as_dict()


class _Slot:
    """A publisher-side slot: one segment this process created."""

    __slots__ = ('id', 'segment', 'capacity', 'pins', 'generation', 'last_used', 'closed',
                 'sent', 'taken', 'released')

    def __init__(self, segment_id: int, segment: memory.Segment) -> None:
        self.id = segment_id
        self.segment = segment
        self.capacity = segment.capacity
        self.pins = 0
        self.generation = 0
        self.last_used = 0
        self.closed = False
        #: Per recipient process token, descriptors of this generation sent, taken (acked)
        #: and given up by a ledger.
        self.sent: Dict[str, int] = {}
        self.taken: Dict[str, int] = {}
        self.released: Dict[str, int] = {}


class Pin:
    """Keepalive of a publisher-side DemoBuffer: the slot cannot be reused while it lives."""

    __slots__ = ('state', 'slot', 'generation', 'size', 'packed')

    def __init__(self, state: 'State', slot: _Slot, size: int) -> None:
        self.state = state
        self.slot = slot
        self.generation = slot.generation
        self.size = size
        self.packed: Optional[bytes] = None  # the descriptor, packed on first use

    @property
    def segment(self) -> Tuple[int, int]:
        return self.state.pid, self.slot.id

    def __del__(self):
        try:
            self.state._defer(self.state._unpin, self.slot)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class _Mapping:
    """A subscriber-side segment: received (or, in-process, reopened) and mapped read-only."""

    __slots__ = ('key', 'received', 'view', 'refs', 'conn', 'orphan', 'last_used', 'retired',
                 'closed')

    def __init__(self, key: Tuple[int, int, int], received: memory.Received,
                 conn: Optional[socket.socket]) -> None:
        self.key = key
        self.received = received
        self.view = memoryview(received.map).toreadonly()[memory.HEADER_SIZE:]
        self.refs = 0
        self.conn = conn  #: where takes are acknowledged (None: a segment of this process)
        self.orphan = False
        self.last_used = time.monotonic()
        self.retired = False
        self.closed = False


class Hold:
    """Keepalive of a subscriber-side DemoBuffer: this process's hold on the slot's bytes."""

    __slots__ = ('state', 'mapping', 'generation')

    def __init__(self, state: 'State', mapping: _Mapping, generation: int) -> None:
        self.state = state
        self.mapping = mapping
        self.generation = generation

    @property
    def segment(self) -> Tuple[int, int]:
        return self.mapping.key[0], self.mapping.key[2]

    def __del__(self):
        try:
            self.state._defer(self.state._release, self.mapping)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class _InFlight(NamedTuple):
    """One descriptor a peer has not been seen to take."""

    slot: _Slot
    generation: int
    seq: int  #: the peer's message number it was sent with


class PeerLedger:
    """Per-peer accounting of descriptors in flight (see the module docstring, "Fairness").

    ``depth``: the peer's KEEP_LAST history depth, 0 for KEEP_ALL or unknown (or when the
    ledger may see the messages of several channels: no ``local_gid``).
    """

    __slots__ = ('token', 'depth', 'per_channel', 'seq', 'inflight')

    def __init__(self, token: str, depth: int = 0, per_channel: bool = True) -> None:
        self.token = token
        self.depth = depth
        self.per_channel = per_channel
        self.seq = 0  #: messages described for the peer
        self.inflight: Deque[_InFlight] = collections.deque()

    def summary(self) -> dict:
        return {'token': self.token, 'depth': self.depth, 'messages': self.seq,
                'in_flight': len(self.inflight)}


_COUNTERS = ('segments_created', 'segments_removed', 'fallbacks', 'fallbacks_held',
             'fallbacks_too_large', 'fallbacks_enospc', 'fallbacks_memory_error',
             'descriptors_created', 'descriptors_declined', 'handovers_sent', 'handovers_busy',
             'handovers_received', 'handovers_rejected', 'connections_refused', 'acks',
             'acks_unsent', 'taken', 'rejected', 'stale', 'reclaimed', 'mappings_opened',
             'mappings_closed', 'released_window', 'released_skipped', 'released_share',
             'peers_gone', 'cpu_foreign_peer')


class _Locked:
    __slots__ = ('state',)

    def __init__(self, state: 'State') -> None:
        self.state = state

    def __enter__(self) -> None:
        self.state.lock.acquire()

    def __exit__(self, *exc) -> None:
        self.state.lock.release()
        self.state._drain()


class State:
    """Everything the demo backend holds in one process."""

    def __init__(self) -> None:
        self.pid = os.getpid()
        self.token = own_token()
        self.nonce = int(self.token[-16:], 16)
        self.lock = threading.Lock()
        self.locked = _Locked(self)
        self.pending: List[tuple] = []
        self.closed = False
        self.counters = dict.fromkeys(_COUNTERS, 0)
        self.warned: Set[str] = set()
        # publisher side
        self.slots: Dict[int, _Slot] = {}
        self.next_id = 1
        self.pool_bytes = 0
        self.links: Dict[str, handover.Link] = {}
        self.gone: Set[str] = set()
        self.grow_failure: Optional[str] = None
        # subscriber side
        self.listener: Optional[handover.Listener] = None
        self.inbound: Dict[socket.socket, int] = {}  # connection -> its publisher's pid
        self.mappings: Dict[Tuple[int, int, int], _Mapping] = {}
        self.last_sweep = 0.0

    def _warn_once(self, cause: str, message: str) -> None:
        """Log ``message`` the first time its cause (numbers left out) is seen."""
        cause = re.sub(r'[0-9]+', '#', cause)[:48]
        if cause not in self.warned:
            self.warned.add(cause)
            _logger.warning(f'{message} (logged once; see demo_buffer_backend.stats())')

    # --- deferred releases -------------------------------------------------------------------
    def _defer(self, func, obj) -> None:
        self.pending.append((func, obj))
        self._drain()

    def _drain(self) -> None:
        # Whoever appends tries the lock after appending; whoever holds the lock drains after
        # releasing it: one of the two always sees every entry.
        while self.pending:
            if not self.lock.acquire(blocking=False):
                return
            try:
                while self.pending:
                    func, obj = self.pending.pop()
                    try:
                        func(obj)
                    except Exception as exc:  # pragma: no cover - never lose the others
                        _logger.error(f'demo backend release failed: {exc!r}')
            finally:
                self.lock.release()

    def _unpin(self, slot: _Slot) -> None:
        slot.pins -= 1

    def _release(self, mapping: _Mapping) -> None:
        mapping.refs -= 1
        if mapping.refs == 0 and not mapping.closed:
            memory.unlock(mapping.received.fd)
            if mapping.retired:
                self._close_mapping(mapping)

    # --- lifecycle ---------------------------------------------------------------------------
    def advertise(self) -> Optional[str]:
        """This process's token, its listener created if need be; None when it cannot be."""
        with self.locked:
            if self.closed:
                return None
            if self.listener is None:
                try:
                    self.listener = handover.Listener(self.token)
                except OSError as exc:
                    self._warn_once('listener', f'cannot listen for demo segments: {exc}; '
                                    'publishers will send this process CPU bytes')
                    return None
            return self.token

    def shutdown(self) -> None:
        """Close everything: links (subscribers drop our segments once unused), received
        segments, slots. Views still alive keep their memory (the kernel frees it with them)."""
        with self.locked:
            self.closed = True
            for link in self.links.values():
                link.close()
            self.links.clear()
            for mapping in list(self.mappings.values()):
                self._close_mapping(mapping)
            for conn in self.inbound:
                conn.close()
            self.inbound.clear()
            if self.listener is not None:
                self.listener.close()
                self.listener = None
            for slot in list(self.slots.values()):
                self._remove_slot(slot)

    def forget_after_fork(self) -> None:
        """In a forked child: close our copies of the parent's descriptors, touch nothing."""
        self.closed = True
        socks = list(self.links.values()) + list(self.inbound) + \
            ([self.listener] if self.listener else [])
        for sock in socks:
            sock.close()
        for fd in [s.segment.fd for s in self.slots.values()] + \
                [m.received.fd for m in self.mappings.values()]:
            try:
                os.close(fd)
            except OSError:
                pass
        self.slots, self.mappings, self.links, self.inbound = {}, {}, {}, {}
        self.listener = None

    # --- publisher side ----------------------------------------------------------------------
    def allocate(self, nbytes: int) -> Optional[Tuple[memoryview, Pin]]:
        """A writable view of ``nbytes`` in a slot and its pin, or ``None``: fall back."""
        with self.locked:
            if self.closed:
                return None
            self._drain_links()  # acks and hang-ups free slots
            capacity = memory.round_capacity(nbytes)
            self.grow_failure = None
            slot = (self._reuse(nbytes, stale_ok=False)
                    or self._grow(nbytes, capacity, stale_ok=False)
                    or self._reuse(nbytes, stale_ok=True)
                    or self._grow(nbytes, capacity, stale_ok=True))
            if slot is None:
                cause = self.grow_failure or 'held'
                self.counters['fallbacks'] += 1
                self.counters[f'fallbacks_{cause}'] += 1
                self._warn_once(f'fallback_{cause}', (
                    f'demo buffer pool: no shared memory for {nbytes} bytes ({len(self.slots)} '
                    f'slots, {self.pool_bytes} bytes in use; limits {_limits.as_dict()}): '
                    f'{self._fallback_reason(cause, capacity)}; such buffers fall back to '
                    'private memory and are sent as CPU bytes'))
                return None
            slot.pins += 1
            slot.last_used = time.monotonic_ns()
            return slot.segment.data[:nbytes], Pin(self, slot, nbytes)

    def _fallback_reason(self, cause: str, capacity: int) -> str:
        if cause == 'too_large':
            return (f'the request ({capacity} bytes in whole pages) is larger than max_pool_bytes '
                    f'({_limits.max_pool_bytes}) or max_slots is 0')
        if cause == 'enospc':
            return (f'the system has no memory for another {capacity}-byte segment (ENOSPC, '
                    'ENOMEM or EFBIG when backing its pages)')
        if cause == 'memory_error':
            return 'creating a segment failed (see the warning before)'
        held = sum(1 for s in self.slots.values() if s.pins)
        return (f'every slot is in use: {held} pinned by buffers this process still holds, the '
                'others held by subscribers (views, or descriptors in flight within each '
                "peer's share)")

    @staticmethod
    def _fits(slot: _Slot, nbytes: int) -> bool:
        return nbytes <= slot.capacity <= 2 * max(nbytes, memory.PAGE_SIZE)

    def _pinning(self, slot: _Slot) -> int:
        """Descriptors of the slot's generation that still protect it: sent to a process that
        has not hung up, neither taken nor given up."""
        return sum(max(0, count - slot.taken.get(token, 0) - slot.released.get(token, 0))
                   for token, count in slot.sent.items() if token not in self.gone)

    def _lock_free(self, slot: _Slot, stale_ok: bool, now_ns: int) -> Optional[bool]:
        """Take the exclusive lock of a free slot: None when it is not free, else whether it
        is reclaimed with descriptors still pinning it. The caller unlocks (or closes)."""
        if slot.pins:
            return None
        pinning = self._pinning(slot) > 0
        if pinning and not (stale_ok and
                            now_ns - slot.last_used >= _limits.reclaim_timeout * 1e9):
            return None
        if not memory.try_lock(slot.segment.fd, exclusive=True):
            return None  # some process holds views of it
        return pinning

    def _reuse(self, nbytes: int, stale_ok: bool) -> Optional[_Slot]:
        now = time.monotonic_ns()
        for slot in sorted((s for s in self.slots.values() if self._fits(s, nbytes)),
                           key=lambda s: s.last_used):
            reclaimed = self._lock_free(slot, stale_ok, now)
            if reclaimed is None:
                continue
            try:
                self._set_generation(slot, slot.generation + 1, nbytes)
            finally:
                memory.unlock(slot.segment.fd)
            self.counters['reclaimed'] += reclaimed
            return slot
        return None

    @staticmethod
    def _set_generation(slot: _Slot, generation: int, nbytes: int) -> None:
        slot.segment.set_generation(generation, nbytes)
        slot.generation = generation
        slot.sent.clear()
        slot.taken.clear()
        slot.released.clear()

    def _grow(self, nbytes: int, capacity: int, stale_ok: bool) -> Optional[_Slot]:
        if capacity > _limits.max_pool_bytes or _limits.max_slots < 1:
            self.grow_failure = 'too_large'
            return None
        now = time.monotonic_ns()
        while (len(self.slots) + 1 > _limits.max_slots
               or self.pool_bytes + capacity > _limits.max_pool_bytes):
            # Make room by removing free slots (of the wrong size: fitting ones were tried).
            for victim in sorted(self.slots.values(), key=lambda s: s.last_used):
                reclaimed = self._lock_free(victim, stale_ok, now)
                if reclaimed is not None:
                    self.counters['reclaimed'] += reclaimed
                    self._remove_slot(victim)  # closing the fd drops the lock
                    break
            else:
                return None
        try:
            segment = memory.Segment(capacity)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.ENOMEM, errno.EFBIG):
                self.grow_failure = 'enospc'
            else:
                self.grow_failure = 'memory_error'
                _logger.warning(f'cannot create a {capacity}-byte demo segment: {exc}',
                                throttle_duration_sec=10.0)
            return None
        slot = _Slot(self.next_id, segment)
        self.next_id += 1
        self._set_generation(slot, 1, nbytes)
        self.slots[slot.id] = slot
        self.pool_bytes += capacity
        self.counters['segments_created'] += 1
        return slot

    def _remove_slot(self, slot: _Slot) -> None:
        slot.closed = True
        self.slots.pop(slot.id, None)
        self.pool_bytes -= slot.capacity
        for link in self.links.values():
            link.retire(self.nonce, slot.id)
        own = self.mappings.get((self.pid, self.nonce, slot.id))
        if own is not None:
            own.retired = True
            if own.refs == 0:
                self._close_mapping(own)
        slot.segment.close()
        self.counters['segments_removed'] += 1

    def _drain_links(self) -> None:
        """Apply the takes every subscriber acknowledged; note who hung up."""
        for link in list(self.links.values()):
            self._drain_link(link)

    def _drain_link(self, link: handover.Link) -> None:
        try:
            acks = link.acks()
        except handover.PeerGone:
            self._hung_up(link.token)
            return
        for segment_id, generation in acks:
            slot = self.slots.get(segment_id)
            if slot is not None and slot.generation == generation:
                slot.taken[link.token] = slot.taken.get(link.token, 0) + 1
                self.counters['acks'] += 1

    def _hung_up(self, token: str) -> None:
        link = self.links.pop(token, None)
        if link is not None:
            link.close()
        if token not in self.gone:
            self.gone.add(token)
            self.counters['peers_gone'] += 1

    def _link(self, token: str) -> Optional[handover.Link]:
        """The link to ``token``'s process (connected on first use); None when who listens
        there is not that process of our user. ``EndpointGone`` when nobody does."""
        link = self.links.get(token)
        if link is None:
            try:
                link = self.links[token] = handover.Link(token)
            except handover.PeerGone:
                self._hung_up(token)
            except BlockingIOError:  # its backlog is full: CPU bytes for now, retry later
                self.counters['handovers_busy'] += 1
                return None
            except OSError as exc:
                self.counters['cpu_foreign_peer'] += 1
                self._warn_once(f'link_{token}', f'demo peer {token}: {exc}; it gets CPU bytes')
                return None
        if token in self.gone:
            raise EndpointGone(f'the process of demo peer {token} is gone (its link hung up)')
        return link

    def describe(self, pin: Pin, ledger: PeerLedger) -> Optional[bytes]:
        """Record one more descriptor of ``pin``'s slot for the ledger's peer and return it,
        its segment handed over first if need be. None (CPU bytes for this peer) when the pin
        is stale, the peer is not of our user, or its queue is full; ``EndpointGone`` when its
        process is gone."""
        with self.locked:
            slot = pin.slot
            if pin.state is not self or slot.closed or slot.generation != pin.generation:
                self.counters['descriptors_declined'] += 1
                return None
            token = ledger.token
            ledger.seq += 1
            if token == self.token:
                self._adopt_own(slot)
                link = None
            else:
                link = self._link(token)
                if link is None:
                    self.counters['descriptors_declined'] += 1
                    return None
                self._drain_link(link)
                if token in self.gone:
                    raise EndpointGone(f'the process of demo peer {token} is gone')
            self._settle(ledger)
            if link is not None and slot.id not in link.segments:
                if not self._hand_over(link, slot):
                    self.counters['descriptors_declined'] += 1
                    return None
            now = time.monotonic_ns()
            slot.sent[token] = slot.sent.get(token, 0) + 1
            slot.last_used = now
            ledger.inflight.append(_InFlight(slot, slot.generation, ledger.seq))
            self.counters['descriptors_created'] += 1
            if pin.packed is None:
                pin.packed = codec.pack(codec.Descriptor(
                    self.pid, self.nonce, slot.id, pin.generation, 0, pin.size))
            return pin.packed

    def _hand_over(self, link: handover.Link, slot: _Slot) -> bool:
        try:
            fd = slot.segment.reader_fd()
        except OSError as exc:
            self._warn_once('reader_fd', f'cannot reopen a demo segment for a reader: {exc}')
            return False
        try:
            link.hand_over(self.nonce, slot.id, slot.capacity, fd)
            self.counters['handovers_sent'] += 1
            return True
        except handover.PeerGone:
            self._hung_up(link.token)
            raise EndpointGone(f'the process of demo peer {link.token} is gone') from None
        except OSError as exc:  # its queue is full (EAGAIN), or fds in flight at their limit
            self.counters['handovers_busy'] += 1
            self._warn_once('handover_busy', f'cannot hand a segment to demo peer '
                            f'{link.token}: {exc}; it gets CPU bytes until it drains')
            return False
        finally:
            os.close(fd)

    def _settle(self, ledger: PeerLedger) -> None:
        """Bring the peer's in-flight list up to date: drop what it took or what was reclaimed,
        give up what it can no longer take and what exceeds its share."""
        token = ledger.token
        kept: List[_InFlight] = []
        for entry in ledger.inflight:
            slot = entry.slot
            if slot.closed or slot.generation != entry.generation:
                continue  # reclaimed or removed: nothing left to protect
            if slot.taken.get(token, 0) + slot.released.get(token, 0) >= slot.sent.get(token, 0):
                if ledger.per_channel:  # taken in order: what it had not taken, it dropped
                    for skipped in kept:
                        self._give_up(skipped, token, 'released_skipped')
                    kept = []
                continue
            kept.append(entry)
        inflight = collections.deque(kept)
        if ledger.depth:  # seq is the message being described now
            while inflight and ledger.seq - inflight[0].seq >= ledger.depth:
                self._give_up(inflight.popleft(), token, 'released_window')
        share, share_bytes = _limits.peer_share(), _limits.peer_share_bytes()
        while inflight and (len(inflight) >= share or sum(
                e.slot.capacity for e in inflight) >= share_bytes):
            self._give_up(inflight.popleft(), token, 'released_share')
        ledger.inflight = inflight

    def _give_up(self, entry: _InFlight, token: str, counter: str) -> None:
        slot = entry.slot
        if not slot.closed and slot.generation == entry.generation:
            slot.released[token] = slot.released.get(token, 0) + 1
            self.counters[counter] += 1

    def decline(self) -> None:
        with self.locked:
            self.counters['descriptors_declined'] += 1

    # --- subscriber side ---------------------------------------------------------------------
    def _adopt_own(self, slot: _Slot) -> None:
        """Map our own slot as a reader would (in-process subscriptions)."""
        key = (self.pid, self.nonce, slot.id)
        if key not in self.mappings:
            fd = slot.segment.reader_fd()
            try:
                self._map(key, fd, slot.capacity, None)
            except ValueError:
                os.close(fd)
                raise

    def _map(self, key: Tuple[int, int, int], fd: int, capacity: int,
             conn: Optional[socket.socket]) -> None:
        mapping = _Mapping(key, memory.open_received(fd, capacity), conn)
        self.mappings[key] = mapping
        self.counters['mappings_opened'] += 1

    def _receive(self) -> None:
        """Accept pending connections and take every segment handed over (never blocks)."""
        self.last_sweep = time.monotonic()
        if self.listener is not None:
            for conn, cred in self.listener.accept():
                if cred.uid != os.geteuid() or len(self.inbound) >= MAX_INBOUND:
                    self.counters['connections_refused'] += 1
                    self._warn_once(f'uid {cred.uid}', f'refused a demo connection from pid '
                                    f'{cred.pid} uid {cred.uid} (only uid {os.geteuid()} may '
                                    f'hand us memory, on at most {MAX_INBOUND} connections)')
                    conn.close()
                else:
                    self.inbound[conn] = cred.pid
        for conn, pid in list(self.inbound.items()):
            got, rejected, hung_up = handover.receive(conn)
            for problem in rejected:
                self._refuse_handover(pid, problem)
            for record in got:
                self._take_handover(conn, pid, record)
            if hung_up:
                del self.inbound[conn]
                conn.close()
                for mapping in self.mappings.values():
                    if mapping.conn is conn:
                        mapping.orphan = True
                        mapping.conn = None
        self._close_unused()

    def _refuse_handover(self, pid: int, problem: str) -> None:
        self.counters['handovers_rejected'] += 1
        self._warn_once(f'handover_{problem}', f'refused a demo segment from pid {pid}: '
                        f'{problem}')

    def _take_handover(self, conn: socket.socket, pid: int, record: handover.Handover) -> None:
        key = (pid, record.nonce, record.segment_id)
        if record.fd < 0:  # retired by its publisher
            mapping = self.mappings.get(key)
            if mapping is not None and mapping.conn is conn:
                mapping.retired = True
            return
        problem = None
        if key in self.mappings:
            problem = f'segment {record.segment_id} was handed over already'
        elif len(self.mappings) >= MAX_MAPPINGS:
            problem = f'{MAX_MAPPINGS} segments are mapped already'
        else:
            try:
                self._map(key, record.fd, record.capacity, conn)
                self.counters['handovers_received'] += 1
                return
            except (ValueError, OSError) as exc:
                problem = str(exc)
        os.close(record.fd)
        self._refuse_handover(pid, problem)

    def _close_unused(self) -> None:
        """Close segments nobody can use any more: retired, or orphaned and unused for
        ``ORPHAN_SECONDS``, and held by no view."""
        now = time.monotonic()
        for mapping in list(self.mappings.values()):
            if mapping.refs == 0 and (mapping.retired or (
                    mapping.orphan and now - mapping.last_used >= ORPHAN_SECONDS)):
                self._close_mapping(mapping)

    def _close_mapping(self, mapping: _Mapping) -> None:
        mapping.closed = True
        self.mappings.pop(mapping.key, None)
        self.counters['mappings_closed'] += 1
        try:
            mapping.view.release()
            mapping.received.map.close()
        except BufferError:
            pass  # a view is still exported: the mapping goes when it does
        os.close(mapping.received.fd)

    def open_descriptor(self, raw) -> Tuple[memoryview, Hold]:
        """A read-only view of the bytes ``raw`` names and the hold that protects it."""
        with self.locked:
            try:
                d = codec.unpack(raw)
                if self.closed:
                    raise ValueError('the demo backend of this process is shut down')
                return self._open(d)
            except ValueError as exc:
                self.counters['rejected'] += 1
                self._warn_once(f'reject_{exc}', f'rejected a demo descriptor: {exc}')
                raise

    def _open(self, d: codec.Descriptor) -> Tuple[memoryview, Hold]:
        key = (d.pid, d.nonce, d.segment_id)
        mapping = self.mappings.get(key)
        if mapping is None or time.monotonic() - self.last_sweep >= SWEEP_INTERVAL:
            self._receive()
            mapping = self.mappings.get(key)
        if mapping is None or mapping.retired:
            raise ValueError(f'demo descriptor names segment {d.segment_id} of publisher pid '
                             f'{d.pid}, which that process did not hand to this one (or '
                             'removed since)')
        capacity = mapping.received.capacity
        if d.offset > capacity or d.size > capacity - d.offset:
            raise ValueError(f'demo descriptor range [{d.offset}, {d.offset + d.size}) is '
                             f'outside its segment ({capacity} data bytes)')
        if mapping.refs == 0 and not self._acquire_hold(mapping.received.fd):
            self.counters['stale'] += 1
            raise ValueError(f'demo descriptor for segment {d.segment_id} generation '
                             f'{d.generation} is stale: its publisher is reusing the slot')
        mapping.refs += 1
        try:
            header = mapping.received.map
            generation = memory.read_u64(header, memory.OFF_GENERATION)
            if generation != d.generation:
                self.counters['stale'] += 1
                raise ValueError(f'demo descriptor for segment {d.segment_id} is stale: '
                                 f'generation {d.generation}, the slot is at {generation}')
            recorded = (memory.read_u64(header, memory.OFF_OFFSET),
                        memory.read_u64(header, memory.OFF_SIZE))
            if recorded != (d.offset, d.size):
                raise ValueError(f'demo descriptor names bytes [{d.offset}, {d.offset + d.size})'
                                 f' but its publisher recorded [{recorded[0]}, '
                                 f'{sum(recorded)}) for generation {generation}')
        except BaseException:
            self._release(mapping)
            raise
        self._acknowledge(mapping, d)
        mapping.last_used = time.monotonic()
        self.counters['taken'] += 1
        return mapping.view[d.offset:d.offset + d.size], Hold(self, mapping, generation)

    def _acknowledge(self, mapping: _Mapping, d: codec.Descriptor) -> None:
        if mapping.conn is not None:
            if not handover.send_ack(mapping.conn, d.segment_id, d.generation):
                self.counters['acks_unsent'] += 1
        elif d.pid == self.pid and d.nonce == self.nonce:
            slot = self.slots.get(d.segment_id)
            if slot is not None and slot.generation == d.generation:
                slot.taken[self.token] = slot.taken.get(self.token, 0) + 1

    @staticmethod
    def _acquire_hold(fd: int) -> bool:
        if memory.try_lock(fd, exclusive=False):
            return True
        for pause in _HOLD_RETRIES:  # the publisher holds it exclusively for microseconds
            time.sleep(pause)
            if memory.try_lock(fd, exclusive=False):
                return True
        return False

    def sweep(self) -> None:
        """Drain the listener and close segments nobody can use any more."""
        with self.locked:
            if not self.closed:
                self._receive()

    # --- diagnostics -------------------------------------------------------------------------
    def stats(self) -> dict:
        with self.locked:
            result = dict(self.counters)
            result.update(
                slots=len(self.slots),
                bytes=self.pool_bytes,
                slots_pinned=sum(1 for s in self.slots.values() if s.pins),
                links=len(self.links),
                peers_hung_up=len(self.gone),
                mappings=len(self.mappings),
                mappings_held=sum(1 for m in self.mappings.values() if m.refs),
                views_held=sum(m.refs for m in self.mappings.values()),
                token=self.token,
                peer_share=_limits.peer_share(),
                **_limits.as_dict())
            return result


_state: Optional[State] = None
_state_lock = threading.Lock()
_atexit_registered = False
#: (pid, token): this process's token, the same for its whole life (it is advertised in the
#: backend metadata, which endpoints keep), even across pool shutdowns.
_token: Optional[Tuple[int, str]] = None


def own_token() -> str:
    global _token
    token = _token
    if token is None or token[0] != os.getpid():
        token = _token = (os.getpid(), handover.new_token())
    return token[1]


def get_state() -> State:
    """The process-wide state (created on first use, and anew after :func:`shutdown`)."""
    global _state, _atexit_registered
    state = _state
    if state is not None and state.pid == os.getpid():
        return state
    with _state_lock:
        if _state is None or _state.pid != os.getpid():
            _state = State()
            if not _atexit_registered:
                _atexit_registered = True
                atexit.register(_shutdown_at_exit)
        return _state


def shutdown() -> None:
    """Close every segment, link and listener of this process (also done at exit).

    The backend stays usable: the next use starts afresh (with the same token).
    """
    global _state
    with _state_lock:
        state, _state = _state, None
    if state is not None and state.pid == os.getpid():
        state.shutdown()


def _shutdown_at_exit() -> None:
    try:
        shutdown()
    except Exception:  # pragma: no cover - never fail the interpreter's exit
        pass


def _after_fork_in_child() -> None:
    global _state, _state_lock
    _state_lock = threading.Lock()
    state, _state = _state, None
    if state is not None:
        state.forget_after_fork()


os.register_at_fork(after_in_child=_after_fork_in_child)


def stats() -> dict:
    """Counters and gauges of this process's demo backend (see the package docstring)."""
    return get_state().stats()
